"""The odometry process model shared by D-SLAM's localization and EKF-SLAM.

The robot pose is propagated by the odometry increment ``u = (dx, dy, dtheta)`` expressed in the
robot frame at the previous pose: ``X_r' = X_r ⊕ u``. The increment is read from the cumulative
odometry poses (``u_k = ⊖o_{k-1} ⊕ o_k``), and its error is modelled as zero-mean Gaussian with a
covariance that grows with the motion, so that a robot standing still stays exactly where it is
(what D-SLAM's phase I assumes):

    Var(dx) = Var(dy) = s_t^2 |d|,     Var(dtheta) = s_h^2 |d| + s_r^2 |dtheta|,     |d| = hypot(dx, dy),

independent components. Variances linear in the distance make the accumulated uncertainty
independent of the odometry rate (a random walk in distance travelled).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

F64 = NDArray[np.float64]


@dataclass(frozen=True, slots=True)
class OdometryNoise:
    """Process noise densities (module docstring); all >= 0."""

    translation_sigma_per_sqrt_m: float = 0.02  # s_t, m / sqrt(m)
    heading_sigma_per_sqrt_m: float = 0.02  # s_h, rad / sqrt(m)
    heading_sigma_per_sqrt_rad: float = 0.05  # s_r, rad / sqrt(rad): turning on the spot

    def __post_init__(self) -> None:
        for name in ("translation_sigma_per_sqrt_m", "heading_sigma_per_sqrt_m", "heading_sigma_per_sqrt_rad"):
            value = getattr(self, name)
            if not math.isfinite(value) or value < 0:
                raise ValueError(f"{name} must be finite and >= 0, got {value}")

    def covariance(self, u: F64) -> F64:
        """Q (3, 3) of the increment ``u`` (module docstring)."""
        dist = math.hypot(float(u[0]), float(u[1]))
        var_t = self.translation_sigma_per_sqrt_m**2 * dist
        var_h = self.heading_sigma_per_sqrt_m**2 * dist + self.heading_sigma_per_sqrt_rad**2 * abs(float(u[2]))
        return np.diag([var_t, var_t, var_h])


def compose1(a: F64, b: F64) -> F64:
    """a ⊕ b for single poses (3,): se2.compose without the vectorisation overhead (hot path, 100 Hz odometry)."""
    c, s = math.cos(a[2]), math.sin(a[2])
    return np.array([a[0] + c * b[0] - s * b[1], a[1] + s * b[0] + c * b[1],
                     math.remainder(a[2] + b[2], math.tau)])


def between1(a: F64, b: F64) -> F64:
    """⊖a ⊕ b for single poses (3,)."""
    c, s = math.cos(a[2]), math.sin(a[2])
    dx, dy = b[0] - a[0], b[1] - a[1]
    return np.array([c * dx + s * dy, -s * dx + c * dy, math.remainder(b[2] - a[2], math.tau)])


def check_increment(u: ArrayLike) -> F64:
    """A validated (3,) float64 odometry increment (ValueError naming the argument)."""
    arr = np.array(u, dtype=np.float64, copy=True)
    if arr.shape != (3,) or not np.all(np.isfinite(arr)):
        raise ValueError(f"odometry increment must be a finite (3,) [dx, dy, dtheta], got {arr!r}")
    return arr


def predict(pose: F64, cov: F64, u: F64, q: F64) -> tuple[F64, F64, F64]:
    """Propagate ``(pose, cov)`` by the increment ``u`` with increment covariance ``q``.

    Returns the predicted pose (3,), its covariance ``F P F^T + G Q G^T`` (3, 3) and ``F`` (3, 3),
    the Jacobian with respect to the previous pose (EKF-SLAM applies it to the cross-covariances).
    """
    c, s = math.cos(pose[2]), math.sin(pose[2])
    f = np.array([[1.0, 0.0, -s * u[0] - c * u[1]], [0.0, 1.0, c * u[0] - s * u[1]], [0.0, 0.0, 1.0]])
    g = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    new_cov = f @ cov @ f.T + g @ q @ g.T
    return compose1(pose, u), 0.5 * (new_cov + new_cov.T), f
