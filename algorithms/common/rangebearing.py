"""The planar range-bearing sensor model shared by D-SLAM and EKF-SLAM.

A landmark at ``l = (x, y)`` seen from the robot pose ``X_r = (x_r, y_r, phi_r)`` gives
``z = (r, theta)`` with ``r = |l - t|`` and ``theta = atan2(l - t) - phi_r`` (robot frame: x
forward, bearing counter-clockwise). The noise is ``diag(sigma_r^2, sigma_theta^2)`` per landmark,
independent between landmarks: D-SLAM's R_old, eq. (2) of [1]_.

References
----------
.. [1] Z. Wang, S. Huang, G. Dissanayake, "Implementation issues and experimental evaluation
   of D-SLAM", FSR 2005, eqs. (1), (2), (4).
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike, NDArray

from slamreplay.algorithms.common.se2 import wrap_angle

F64 = NDArray[np.float64]


def check_scan(ranges: ArrayLike, bearings: ArrayLike) -> tuple[F64, F64]:
    """Validated float64 copies of one scan's ranges and bearings (ValueError naming the argument)."""
    r = np.array(ranges, dtype=np.float64, copy=True).reshape(-1)
    b = np.array(bearings, dtype=np.float64, copy=True).reshape(-1)
    if r.shape != b.shape:
        raise ValueError(f"ranges and bearings must have the same length, got {r.shape} and {b.shape}")
    if not np.all(np.isfinite(r)):
        raise ValueError("ranges contains NaN or infinite values")
    if not np.all(np.isfinite(b)):
        raise ValueError("bearings contains NaN or infinite values")
    if np.any(r < 0):
        raise ValueError("ranges must be >= 0")
    return r, b


def scan_sigmas(range_sigma: float, bearing_sigma: float, default_range_sigma: float,
                default_bearing_sigma: float) -> tuple[float, float]:
    """A scan's range and bearing sigmas: the ones it states, or where it states 0 (none) the filter's defaults.
    ValueError naming a sigma that is negative or not finite."""
    for name, value in (("range_sigma", range_sigma), ("bearing_sigma", bearing_sigma)):
        if not math.isfinite(value) or value < 0:
            raise ValueError(f"{name} must be finite and >= 0, got {value}")
    return (range_sigma if range_sigma > 0 else default_range_sigma,
            bearing_sigma if bearing_sigma > 0 else default_bearing_sigma)


def to_points(ranges: F64, bearings: F64) -> tuple[F64, F64]:
    """Eq. (4): robot-frame points (m, 2), and their Jacobians d(x~, y~)/d(r, theta), (m, 2, 2)."""
    c, s = np.cos(bearings), np.sin(bearings)
    points = np.empty((len(ranges), 2))
    points[:, 0], points[:, 1] = ranges * c, ranges * s
    jac = np.empty((len(ranges), 2, 2))
    jac[:, 0, 0], jac[:, 0, 1], jac[:, 1, 0], jac[:, 1, 1] = c, -ranges * s, s, ranges * c
    return points, jac


def predict(pose: F64, landmarks: F64) -> tuple[F64, F64, F64]:
    """Predicted measurements (n, 2) of landmarks (n, 2) from ``pose``, with the Jacobians.

    Returns ``z`` (n, 2) as (range, bearing), ``H_pose`` (n, 2, 3) = dz/dX_r and
    ``H_landmark`` (n, 2, 2) = dz/dl. Ranges are floored at 1e-9 m to keep the Jacobian finite.
    """
    d = landmarks - pose[:2]
    dx, dy = d[:, 0], d[:, 1]
    q = np.maximum(dx * dx + dy * dy, 1e-18)
    r = np.sqrt(q)
    z = np.empty((len(d), 2))
    z[:, 0] = r
    z[:, 1] = wrap_angle(np.arctan2(dy, dx) - pose[2])
    h_l = np.empty((len(d), 2, 2))
    h_l[:, 0, 0], h_l[:, 0, 1] = dx / r, dy / r
    h_l[:, 1, 0], h_l[:, 1, 1] = -dy / q, dx / q
    h_pose = np.zeros((len(d), 2, 3))
    h_pose[:, :, :2] = -h_l
    h_pose[:, 1, 2] = -1.0
    return z, h_pose, h_l


def landmarks_from(pose: F64, ranges: F64, bearings: F64) -> tuple[F64, F64, F64]:
    """Inverse model: landmark positions (m, 2) from a pose and measurements, with Jacobians.

    Returns ``l`` (m, 2), ``G_pose`` (m, 2, 3) = dl/dX_r and ``G_z`` (m, 2, 2) = dl/d(r, theta).
    """
    a = pose[2] + bearings
    c, s = np.cos(a), np.sin(a)
    lm = np.stack([pose[0] + ranges * c, pose[1] + ranges * s], -1)
    ones, zeros = np.ones_like(a), np.zeros_like(a)
    g_pose = np.stack([np.stack([ones, zeros, -ranges * s], -1), np.stack([zeros, ones, ranges * c], -1)], -2)
    g_z = np.stack([np.stack([c, -ranges * s], -1), np.stack([s, ranges * c], -1)], -2)
    return lm, g_pose, g_z


def noise(m: int, sigma_r: float, sigma_b: float) -> F64:
    """Eq. (2): R_old = diag(sigma_r^2, sigma_theta^2, ...) for m measurements, shape (2m, 2m)."""
    return np.diag(np.tile([sigma_r**2, sigma_b**2], m))


def blocks(r_old: F64) -> F64:
    """The 2x2 diagonal blocks (m, 2, 2) of a (2m, 2m) measurement covariance."""
    m = len(r_old) // 2
    idx = np.arange(m)
    return np.stack([np.stack([r_old[2 * idx, 2 * idx], r_old[2 * idx, 2 * idx + 1]], -1),
                     np.stack([r_old[2 * idx + 1, 2 * idx], r_old[2 * idx + 1, 2 * idx + 1]], -1)], -2)
