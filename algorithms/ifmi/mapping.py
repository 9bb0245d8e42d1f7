"""From registrations to a photo map: flattened illumination, pose-graph edges, scales, mosaics.

Image frame: pixel ``p = (u, v)`` (x right, y down) sees the body point
``b = res J (p - c)``, ``J = [[0, -1], [-1, 0]]`` (image up = body +x, image left = body +y),
where ``res`` is the metres (or reference pixels) per pixel of that image. For a registration
``(angle, scale, d)`` of image i (reference) onto image j (moving), the pose of j in the frame
of i is then ``z = (-res_j R(-angle) J d, -angle)`` and ``res_i / res_j = scale``.

References
----------
.. [1] M. Pfingsthorn et al., ICRA 2010, sections II-B and III (edge covariance from the POMF,
   squared Mahalanobis objective, composite map).
"""

from __future__ import annotations

import math

import cv2
import numpy as np
from numpy.typing import NDArray
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from slamreplay.algorithms.ifmi.registration import Registration

F64 = NDArray[np.float64]
J = np.array([[0.0, -1.0], [-1.0, 0.0]])


def flatten_illumination(image: NDArray[np.generic], sigma_fraction: float = 1.0 / 24.0) -> NDArray[np.float32]:
    """Homomorphic high-pass: ``log(1 + I)`` minus its Gaussian blur (sigma = fraction of the smaller side).

    A lamp's uneven light multiplies the scene, so in the log it adds a smooth pattern that the
    blur removes; a fixed pattern left in would lock phase correlation at zero shift.
    """
    img = np.asarray(image, dtype=np.float32)
    if img.ndim == 3:
        img = img.mean(axis=2)
    log = np.log1p(np.maximum(img, 0.0))
    sigma = max(1.0, sigma_fraction * min(img.shape))
    return np.asarray(log - cv2.GaussianBlur(log, (0, 0), sigma), dtype=np.float32)


def edge_from_registration(reg: Registration, res_j: float) -> tuple[F64, F64]:
    """Measurement ``z`` (3,) of j in the frame of i and its covariance (3, 3) (x, y, theta in rad).

    The covariance (the registration's, eq. 10 or calibrated) is propagated through ``z(d, angle)`` to first order.
    """
    theta = -math.radians(reg.angle_deg)
    c, s = math.cos(theta), math.sin(theta)
    rot = np.array([[c, -s], [s, c]])
    drot = np.array([[-s, -c], [c, -s]])
    d = np.asarray(reg.shift_px)
    xy = -res_j * rot @ J @ d
    jac = np.zeros((3, 3))
    jac[:2, :2] = -res_j * rot @ J
    jac[:2, 2] = -res_j * drot @ J @ d * (-math.pi / 180.0)
    jac[2, 2] = -math.pi / 180.0
    cov = jac @ reg.covariance @ jac.T
    return np.array([xy[0], xy[1], theta]), 0.5 * (cov + cov.T)


def solve_log_scales(n: int, i: NDArray[np.int64], j: NDArray[np.int64], log_ratio: F64, var: F64) -> F64:
    """Least-squares log-scales (n,) with ``log s_j - log s_i = log_ratio`` per edge, ``log s_0 = 0``.

    The scale part of the graph is linear in the log, so it is solved exactly and apart from the
    planar poses.
    """
    if n == 1:
        return np.zeros(1)
    a = np.zeros((len(i), n))
    a[np.arange(len(i)), j] = 1.0
    a[np.arange(len(i)), i] -= 1.0
    w = 1.0 / np.sqrt(np.maximum(var, 1e-12))
    sol, *_ = np.linalg.lstsq(a[:, 1:] * w[:, None], log_ratio * w, rcond=None)
    return np.concatenate([[0.0], sol])


def gated_log_scales(n: int, i: NDArray[np.int64], j: NDArray[np.int64], log_ratio: F64, var: F64,
                     gate: float, max_dropped: float = 0.2) -> tuple[F64, NDArray[np.bool_]]:
    """:func:`solve_log_scales` without the edges whose normalized squared residual exceeds ``gate``.

    With calibrated scale variances a wrong registration that passed the PNR test (on sim-seabed
    a loop closure 7 % off in scale; on seed 2 a consecutive pair) is far outside its variance,
    and the linear solve spreads it over every node's resolution. The worst edge beyond the gate
    (a chi-square quantile, 1 dof) is dropped and the rest solved again, one at a time (a wrong
    edge makes the right ones around it look wrong too), never an edge whose removal would
    disconnect the nodes, up to ``max_dropped`` of the edges. Returns the log-scales and the
    mask of the edges kept.
    """
    keep = np.ones(len(i), dtype=bool)
    sol = solve_log_scales(n, i, j, log_ratio, var)
    for _ in range(int(max_dropped * len(i))):
        r2 = np.where(keep, (log_ratio - (sol[j] - sol[i])) ** 2 / np.maximum(var, 1e-12), -1.0)
        for k in np.argsort(-r2, kind="stable"):
            if r2[k] <= gate:
                return sol, keep
            trial = keep.copy()
            trial[k] = False
            if _connected(n, i[trial], j[trial]):
                keep = trial
                break
        else:
            return sol, keep
        sol = solve_log_scales(n, i[keep], j[keep], log_ratio[keep], var[keep])
    return sol, keep


def _connected(n: int, i: NDArray[np.int64], j: NDArray[np.int64]) -> bool:
    """Whether edges ``i - j`` connect all ``n`` nodes."""
    adj = coo_matrix((np.ones(len(i)), (i, j)), shape=(n, n))
    return bool(connected_components(adj, directed=False)[0] == 1)


def mosaic_consistency(images: list[NDArray[np.generic]], poses: F64, res: F64, min_overlap: float = 0.3) -> F64:
    """Normalized cross-correlation of every pair of images that overlap by ``min_overlap`` or more at ``poses``.

    Each image of a pair is resampled into the other's pixels through the poses and resolutions
    (``res`` (n,), the frame convention of the module), both with their illumination flattened
    (:func:`flatten_illumination`); a mosaic that agrees with itself scores near 1 on textured
    ground. Returns (m,) NCCs, one per overlapping pair (i < j).
    """
    h, w = images[0].shape[:2]
    c = np.array([(w - 1) / 2.0, (h - 1) / 2.0])
    flat = [flatten_illumination(im) for im in images]
    ones = np.ones((h, w), np.float32)
    out = []
    for i in range(len(images)):
        ci, si = math.cos(poses[i, 2]), math.sin(poses[i, 2])
        rot_i_t = np.array([[ci, si], [-si, ci]])
        for j in range(i + 1, len(images)):
            cj, sj = math.cos(poses[j, 2]), math.sin(poses[j, 2])
            lin = (J @ rot_i_t @ np.array([[cj, -sj], [sj, cj]]) @ J) * (res[j] / res[i])  # pixel of j -> pixel of i
            off = J @ rot_i_t @ (poses[j, :2] - poses[i, :2]) / res[i] + c - lin @ c
            m = np.hstack([lin, off[:, None]])
            mask = cv2.warpAffine(ones, m, (w, h), flags=cv2.INTER_NEAREST) > 0.5
            if mask.mean() < min_overlap:
                continue
            a = flat[i][mask].astype(np.float64)
            b = cv2.warpAffine(flat[j], m, (w, h), flags=cv2.INTER_LINEAR)[mask].astype(np.float64)
            a -= a.mean()
            b -= b.mean()
            den = math.sqrt(float(a @ a) * float(b @ b))
            out.append(float(a @ b) / den if den > 0 else 0.0)
    return np.array(out)


def render_mosaic(images: list[NDArray[np.uint8]], poses: F64, res: F64, max_side: int = 1600
                  ) -> NDArray[np.uint8]:
    """Composite map: every image placed at its pose (x east, y north), feathered average.

    ``res`` (n,) is each image's metres (or units) per pixel; the canvas resolution is the
    finest of them, coarsened so the canvas's longer side is at most ``max_side``.
    """
    h, w = images[0].shape[:2]
    c = np.array([(w - 1) / 2.0, (h - 1) / 2.0])
    corners = np.array([[0, 0], [w - 1, 0], [0, h - 1], [w - 1, h - 1]], float) - c
    pts = []
    for p, r in zip(poses, res, strict=True):
        rot = np.array([[math.cos(p[2]), -math.sin(p[2])], [math.sin(p[2]), math.cos(p[2])]])
        pts.append(p[:2] + (r * (rot @ J @ corners.T)).T)
    allp = np.concatenate(pts)
    lo, hi = allp.min(axis=0), allp.max(axis=0)
    cell = max(float(res.min()), float((hi - lo).max()) / max_side)
    size = (math.ceil((hi[0] - lo[0]) / cell) + 1, math.ceil((hi[1] - lo[1]) / cell) + 1)
    acc = np.zeros((size[1], size[0]), np.float32)
    wsum = np.zeros_like(acc)
    yy, xx = np.mgrid[0:h, 0:w]
    feather = (np.minimum(np.minimum(xx, w - 1 - xx), np.minimum(yy, h - 1 - yy)).astype(np.float32) + 1.0)
    feather /= feather.max()
    for img, p, r in zip(images, poses, res, strict=True):
        rot = np.array([[math.cos(p[2]), -math.sin(p[2])], [math.sin(p[2]), math.cos(p[2])]])
        flip = np.array([[1.0 / cell, 0.0], [0.0, -1.0 / cell]])
        lin = flip @ rot @ (r * J)
        off = flip @ (p[:2] - np.array([lo[0], hi[1]])) - lin @ c
        m = np.hstack([lin, off[:, None]])
        gray = img if img.ndim == 2 else cv2.cvtColor(img, cv2.COLOR_RGB2GRAY)
        acc += cv2.warpAffine(gray.astype(np.float32) * feather, m, size, flags=cv2.INTER_LINEAR)
        wsum += cv2.warpAffine(feather, m, size, flags=cv2.INTER_LINEAR)
    out = np.where(wsum > 1e-3, acc / np.maximum(wsum, 1e-3), 0.0)
    return np.clip(out + 0.5, 0, 255).astype(np.uint8)
