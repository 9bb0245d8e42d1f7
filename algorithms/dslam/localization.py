"""D-SLAM localization from measurements: the robot pose from ``z_loc`` and the mapped features (eq. 12).

Section 2.3 of [1]_: the original range-bearing measurements of the previously seen features
``f_1 .. f_m1`` (``z_loc``, eq. 12), together with the current estimates of those features and
their joint covariance (a sub-block of I^-1), give an estimate of the robot pose that does not
use odometry. It is fused with the odometry prediction by Covariance Intersection
(:mod:`slamreplay.algorithms.common.ci`), since the two are correlated in an unknown way.

The estimate is a weighted least-squares fit: a closed-form rigid alignment of the observed
points to the mapped ones (2D Procrustes) starts Gauss-Newton on

    min_X  (z_loc - H_loc(X, X_f))^T S^-1 (z_loc - H_loc(X, X_f)),   S = R_loc + H_f P_ff H_f^T,

where the feature uncertainty ``P_ff`` enters through ``S``; the covariance is ``(H_X^T S^-1 H_X)^-1``
at the solution. Neither step needs an initial guess from odometry.

References
----------
.. [1] Z. Wang, S. Huang, G. Dissanayake, "Implementation issues and experimental evaluation
   of D-SLAM", FSR 2005, section 2.3, eq. (12).
"""

from __future__ import annotations

import enum
import functools
import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.stats import chi2

from slamreplay.algorithms.common import rangebearing
from slamreplay.algorithms.common.se2 import wrap_angle

F64 = NDArray[np.float64]
STEP_TOLERANCE = 1e-9  # Gauss-Newton stops when no pose component moves more than this (m, rad)


class PoseStatus(enum.Enum):
    OK = "ok"
    TOO_FEW_FEATURES = "too_few_features"  # fewer than two mapped features observed
    DEGENERATE = "degenerate"  # the geometry does not determine the pose
    INCONSISTENT = "inconsistent"  # the fit's residual fails the chi-square test


@dataclass(frozen=True, slots=True)
class MeasurementPose:
    """The measurement-based robot pose (3,), its covariance (3, 3), the fit's chi-square and status."""

    status: PoseStatus
    pose: F64
    cov: F64
    chi2: float
    iterations: int


@functools.lru_cache(maxsize=256)
def chi2_quantile(probability: float, dof: int) -> float:
    """The chi-square quantile (cached: scipy.stats is slow per call)."""
    return float(chi2.ppf(probability, dof))


def align(points: F64, landmarks: F64) -> F64:
    """The pose (3,) whose rigid motion best maps robot-frame ``points`` (m, 2) onto ``landmarks`` (m, 2)."""
    pc, lc = points.mean(0), landmarks.mean(0)
    h = (points - pc).T @ (landmarks - lc)
    theta = math.atan2(h[0, 1] - h[1, 0], h[0, 0] + h[1, 1])
    c, s = math.cos(theta), math.sin(theta)
    t = lc - np.array([[c, -s], [s, c]]) @ pc
    return np.array([t[0], t[1], theta])


def measurement_pose(ranges: F64, bearings: F64, r_loc: F64, landmarks: F64,
                     landmark_cov: F64, gate_probability: float = 0.9999, max_iterations: int = 20
                     ) -> MeasurementPose:
    """The robot pose from the measurements of ``m1`` mapped features (module docstring).

    Parameters
    ----------
    ranges, bearings : (m1,) the original measurements of the mapped features (``z_loc``).
    r_loc : (2 m1, 2 m1) their noise covariance (eq. 2, or a merged scan's full one).
    landmarks : (m1, 2) the features' current estimates, map frame.
    landmark_cov : (2 m1, 2 m1) their joint covariance.
    gate_probability : a fit whose residual chi-square exceeds this quantile (2 m1 - 3 degrees of
        freedom) is reported ``INCONSISTENT`` (a wrong association or an outlier).
    """
    m = len(ranges)
    nan = np.full(3, np.nan)
    if m < 2:
        return MeasurementPose(PoseStatus.TOO_FEW_FEATURES, nan, np.full((3, 3), np.nan), math.nan, 0)
    points, _ = rangebearing.to_points(ranges, bearings)
    pose = align(points, landmarks)
    z = np.stack([ranges, bearings], -1).reshape(-1)
    idx = np.arange(m)
    h_f = np.zeros((2 * m, 2 * m))
    info = np.zeros((3, 3))
    g = np.zeros(3)  # H_X^T S^-1 nu
    nu_w_nu = 0.0
    it = 0
    for it in range(1, max_iterations + 1):
        zp, hp, hl = rangebearing.predict(pose, landmarks)
        nu = z - zp.reshape(-1)
        nu[1::2] = wrap_angle(nu[1::2])
        h_f.reshape(m, 2, m, 2)[idx, :, idx, :] = hl  # block-diagonal dz/dX_f
        s = r_loc + h_f @ landmark_cov @ h_f.T
        h_x = hp.reshape(2 * m, 3)
        try:
            w = np.linalg.solve(0.5 * (s + s.T), np.column_stack([h_x, nu]))  # S^-1 [H_X, nu]
            info = h_x.T @ w[:, :3]
            g = h_x.T @ w[:, 3]
            step = np.linalg.solve(info, g)
        except np.linalg.LinAlgError:
            return MeasurementPose(PoseStatus.DEGENERATE, nan, np.full((3, 3), np.nan), math.nan, it)
        nu_w_nu = float(nu @ w[:, 3])
        pose = pose + step
        pose[2] = float(wrap_angle(pose[2]))
        if np.max(np.abs(step)) < STEP_TOLERANCE:
            break
    eig = np.linalg.eigvalsh(info)
    if not eig[0] > 1e-12 * eig[-1]:
        return MeasurementPose(PoseStatus.DEGENERATE, nan, np.full((3, 3), np.nan), math.nan, it)
    cov = np.linalg.inv(info)
    cov = 0.5 * (cov + cov.T)
    stat = nu_w_nu - float(g @ cov @ g)  # residual (nu - H d)^T S^-1 (nu - H d) at the last linearisation
    dof = 2 * m - 3
    status = PoseStatus.OK if stat <= chi2_quantile(gate_probability, dof) else PoseStatus.INCONSISTENT
    return MeasurementPose(status, pose, cov, stat, it)
