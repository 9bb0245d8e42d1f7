"""Composite scans (not in the paper): readings of a stretch of odometry mapped as one scan.

D-SLAM maps a feature only from a scan that also sees two mapped features (eqs. 7-9 of [1]_),
and uses only such scans for the map. A sensor that sees one or two landmarks at a time
(MRCLAM's camera) rarely gives one, so most of its landmarks would never be mapped. A
composite scan is a run of consecutive scans whose readings are brought into one robot frame
with the odometry between them, then recast (eqs. 3-4, the composite's full covariance
propagated into R_map as for one scan) and mapped by eqs. (9)-(10).

**Window.** :class:`CompositeScan` keeps the scans the map has not used yet: each scan's
readings as robot-frame points (eq. 4) with their covariances, and between consecutive scans
the odometry link (the increments composed, with covariance, :func:`slamreplay.algorithms.common.motion.predict`).
:meth:`CompositeScan.build` expresses a run of scans in the frame of its last scan: moving the
points over a link ``u`` gives ``p' = R(u_theta)^T (p - u_t)`` with Jacobians ``R^T`` on the
points and ``[-R^T, dR^T/dtheta (p - u_t)]`` on the link, so the joint covariance
``C' = J_p C J_p^T + J_u Q J_u^T`` correlates the readings that share a link. Readings of the
same landmark are then fused by generalized least squares over that joint Gaussian (exact for
the linear model; a reading whose residual fails a chi-square gate is dropped first), and the
fused points go to range-bearing form with the full covariance.

**Split rule** (:meth:`CompositeScan.split`). Each reading and each link may be used by the
map once. The window's scans are cut at the latest scan t such that the scans before t hold
two mapped landmarks (anchors, eq. 9) and the scans from t on hold two landmarks that are
mapped once the part before t is (so the next composite can be anchored too). The part before t
is mapped, the rest stays. The two parts share no reading and no link (the link across t is
dropped), and ``z_map`` is invariant to a rigid motion of a whole composite, so the odometry
after a composite's last scan, shared with the next one, carries no information into it:
the two updates are independent and nothing is counted twice. A scan with two mapped features
followed by one with two more gives the paper's one-scan updates, one scan late.

**Limits.** A scan is dropped from the window (after mapping the whole window, if it can be)
once it is ``max_scans`` scans old, or ``max_distance_m`` of travel lies behind it, or the
odometry since it has accrued a heading standard deviation above ``max_heading_sigma_rad``
(the variances of the increments' headings add): beyond that the linearised transport of its
readings (first order in the heading error) no longer holds. A strict chain (each new
landmark seen only together with one mapped landmark) still cannot be mapped: no cut gives both
parts two anchors.

References
----------
.. [1] Z. Wang, S. Huang, G. Dissanayake, "Implementation issues and experimental evaluation
   of D-SLAM", FSR 2005, eqs. (2)-(4), (7)-(10).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from slamreplay.algorithms.common import motion, rangebearing

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]


@dataclass(frozen=True, slots=True)
class WindowScan:
    """One scan in the window: landmark keys (m,), robot-frame points (m, 2) and their covariances (m, 2, 2)."""

    keys: tuple[int, ...]
    points: F64
    covs: F64
    scan: int


@dataclass(frozen=True, slots=True)
class Composite:
    """A run of scans as one scan, in the frame of its last scan; one reading per landmark."""

    keys: I64  # (k,) landmark keys
    ranges: F64  # (k,)
    bearings: F64  # (k,)
    cov: F64  # (2k, 2k) over (r_1, theta_1, r_2, ...)
    scans: int  # scans merged
    readings: int  # readings fused into the k points
    rejected: int  # readings dropped by the fusion gate


class CompositeScan:
    """The scans the map has not used yet, and the odometry between them (module docstring)."""

    def __init__(self, max_scans: int, max_distance_m: float, max_heading_sigma_rad: float) -> None:
        self.max_scans, self.max_distance_m = max_scans, max_distance_m
        self.max_heading_var = max_heading_sigma_rad**2
        self.scans: list[WindowScan] = []
        self.links: list[tuple[F64, F64]] = []  # links[i]: pose of scans[i + 1] in the frame of scans[i], cov
        self._pending = (np.zeros(3), np.zeros((3, 3)))  # odometry since the newest scan
        self._travel: list[F64] = []  # per scan: distance driven and heading variance accrued since it

    def __len__(self) -> int:
        return len(self.scans)

    def keys(self) -> set[int]:
        return {k for s in self.scans for k in s.keys}

    def clear(self) -> None:
        self.scans, self.links, self._travel = [], [], []
        self._pending = (np.zeros(3), np.zeros((3, 3)))

    def move(self, u: F64, q: F64) -> None:
        """Odometry increment ``u`` (3,) with noise ``q`` (3, 3) since the newest scan."""
        if not self.scans or not np.any(u):
            return
        pose, cov = self._pending
        pose, cov, _ = motion.predict(pose, cov, u, q)
        self._pending = (pose, cov)
        step = np.array([np.hypot(u[0], u[1]), q[2, 2]])  # heading variances add along a chain of increments
        self._travel = [t + step for t in self._travel]

    def add(self, keys: list[int], ranges: F64, bearings: F64, r_blocks: F64, scan: int) -> None:
        """Append one scan's readings (one landmark key each; ``r_blocks`` (m, 2, 2) over (r, theta))."""
        if not keys:
            return
        points, jac = rangebearing.to_points(ranges, bearings)  # eq. (4)
        covs = jac @ r_blocks @ jac.transpose(0, 2, 1)
        if self.scans:
            self.links.append(self._pending)
        self.scans.append(WindowScan(tuple(keys), points, covs, scan))
        self._travel.append(np.zeros(2))
        self._pending = (np.zeros(3), np.zeros((3, 3)))

    def expired(self, scan: int) -> bool:
        """Whether the oldest scan is beyond the window's age, distance or heading-uncertainty limit at ``scan``."""
        if not self.scans:
            return False
        dist, heading_var = self._travel[0]
        return (scan - self.scans[0].scan >= self.max_scans or dist > self.max_distance_m
                or heading_var > self.max_heading_var)

    def drop_oldest(self) -> None:
        del self.scans[0], self._travel[0]
        if self.links:
            del self.links[0]
        if not self.scans:
            self.clear()

    def split(self, mapped: set[int]) -> int:
        """The cut of the split rule (module docstring): how many of the oldest scans to map now (0: none)."""
        n = len(self.scans)
        suffix: set[int] = set()
        prefix = [set[int]() for _ in range(n + 1)]
        for i, s in enumerate(self.scans):
            prefix[i + 1] = prefix[i] | set(s.keys)
        for t in range(n - 1, 0, -1):
            suffix |= set(self.scans[t].keys)
            before = prefix[t]
            if len(before & mapped) >= 2 and len(suffix & (mapped | before)) >= 2:
                return t
        return 0

    def take(self, count: int, gate: float) -> Composite:
        """Remove the ``count`` oldest scans and return them as one composite (the link after them is dropped)."""
        part, links = self.scans[:count], self.links[:count - 1]
        self.scans, self.links, self._travel = self.scans[count:], self.links[count:], self._travel[count:]
        if not self.scans:
            self.clear()
        return build(part, links, gate)


def build(scans: list[WindowScan], links: list[tuple[F64, F64]], gate: float) -> Composite:
    """Scans with the links between them as one scan in the frame of the last (module docstring)."""
    points = np.zeros((0, 2))
    cov = np.zeros((0, 0))
    keys: list[int] = []
    for i, s in enumerate(scans):
        if i:
            points, cov = _move(points, cov, *links[i - 1])
        k, m = len(keys), len(s.keys)
        grown = np.zeros((2 * (k + m), 2 * (k + m)))
        grown[:2 * k, :2 * k] = cov
        for p in range(m):
            grown[2 * (k + p):2 * (k + p) + 2, 2 * (k + p):2 * (k + p) + 2] = s.covs[p]
        points, cov = np.vstack([points, s.points]), grown
        keys += s.keys
    readings = len(keys)
    points, cov, keys, rejected = _fuse(points, cov, keys, gate)
    r, b, polar_cov = _polar(points, cov)
    return Composite(np.asarray(keys, dtype=np.int64), r, b, polar_cov, len(scans), readings, rejected)


def _move(points: F64, cov: F64, u: F64, q: F64) -> tuple[F64, F64]:
    """Points (k, 2) and their covariance into the frame of pose ``u`` (3,) with covariance ``q``."""
    k = len(points)
    c, s = np.cos(u[2]), np.sin(u[2])
    rt = np.array([[c, s], [-s, c]])  # R(theta)^T
    drt = np.array([[-s, c], [-c, -s]])  # d R(theta)^T / d theta
    d = points - u[:2]
    blocks = np.zeros((k, 2, 3))
    blocks[:, :, :2] = -rt
    blocks[:, :, 2] = d @ drt.T
    j_u = blocks.reshape(2 * k, 3)
    rotated = np.einsum("ab,ibjc,dc->iajd", rt, cov.reshape(k, 2, k, 2), rt).reshape(2 * k, 2 * k)
    return d @ rt.T, rotated + j_u @ q @ j_u.T


def _fuse(points: F64, cov: F64, keys: list[int], gate: float) -> tuple[F64, F64, list[int], int]:
    """One point per key by generalized least squares; readings whose residual fails ``gate`` are dropped.

    Model ``z = A y + e``, e ~ N(0, C), A mapping each key's point to its readings:
    ``y = P A^T C^-1 z``, ``P = (A^T C^-1 A)^-1``. A reading's residual ``z_i - y_key`` has
    covariance ``C_ii - P_key`` (the fused point is a linear function of the reading); the
    worst reading beyond the gate is dropped and the fit repeated.
    """
    rejected = 0
    while True:
        unique = list(dict.fromkeys(keys))
        if len(unique) == len(keys):
            return points, cov, keys, rejected
        n, u = len(keys), len(unique)
        a_mat = np.zeros((2 * n, 2 * u))
        col = [unique.index(k) for k in keys]
        for i, c in enumerate(col):
            a_mat[2 * i:2 * i + 2, 2 * c:2 * c + 2] = np.eye(2)
        c_inv_a = np.linalg.solve(cov, a_mat)
        p = np.linalg.inv(a_mat.T @ c_inv_a)
        p = 0.5 * (p + p.T)
        y = p @ (c_inv_a.T @ points.reshape(-1))
        fused = y.reshape(-1, 2)
        worst, worst_d2 = -1, gate
        for i, c in enumerate(col):
            if keys.count(keys[i]) < 2:
                continue
            res = points[i] - fused[c]
            s = cov[2 * i:2 * i + 2, 2 * i:2 * i + 2] - p[2 * c:2 * c + 2, 2 * c:2 * c + 2]
            d2 = float(res @ np.linalg.solve(s, res))
            if d2 > worst_d2:
                worst, worst_d2 = i, d2
        if worst < 0:
            return fused, p, unique, rejected
        keep = [i for i in range(n) if i != worst]
        rows = np.stack([2 * np.asarray(keep), 2 * np.asarray(keep) + 1], 1).ravel()
        points, cov, keys = points[keep], cov[np.ix_(rows, rows)], [keys[i] for i in keep]
        rejected += 1


def _polar(points: F64, cov: F64) -> tuple[F64, F64, F64]:
    """Points (k, 2) to ranges, bearings and their full covariance (2k, 2k) over (r_1, theta_1, ...)."""
    x, y = points[:, 0], points[:, 1]
    q = np.maximum(x * x + y * y, 1e-18)
    r = np.sqrt(q)
    k = len(r)
    jac = np.zeros((2 * k, 2 * k))
    idx = np.arange(k)
    jac[2 * idx, 2 * idx], jac[2 * idx, 2 * idx + 1] = x / r, y / r
    jac[2 * idx + 1, 2 * idx], jac[2 * idx + 1, 2 * idx + 1] = -y / q, x / q
    out = jac @ cov @ jac.T
    return r, np.arctan2(y, x), 0.5 * (out + out.T)
