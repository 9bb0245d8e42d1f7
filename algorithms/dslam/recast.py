"""D-SLAM's recast measurements: eqs. (3), (4), (7), (8) and (9) of [1]_.

One scan observes features ``f_1 .. f_m`` (``f_1, f_2`` the anchors, both already mapped). The
original measurement ``z_old = [r_1, theta_1, ..., r_m, theta_m]`` (eq. 1, noise R_old of eq. 2)
is recast as ``z_new = [z_rob; z_map]`` (eq. 3), where, with the robot-frame points of eq. (4),

    z_rob = [alpha_r12, d_1r, alpha_phi12]
    z_map = [d_12, alpha_312, d_13, ..., alpha_m12, d_1m]

``d_1i`` is the distance from f_1 to f_i and ``alpha_i12`` the angle at f_1 from the direction
f_1 -> f_2 to f_1 -> f_i. ``z_map`` is invariant to shifts and rotations: the same function of
the features' absolute positions is the mapping model ``H_map(X)`` of eqs. (7)-(8). The recast
noise covariance ``R_new = J R_old J^T`` uses the Jacobian ``J = dz_new / dz_old`` at the measured
values (the paper's linearisation, section 2.1): it is a full matrix, and ``R_map``, its
``z_map`` block, is not diagonal.

References
----------
.. [1] Z. Wang, S. Huang, G. Dissanayake, "Implementation issues and experimental evaluation
   of D-SLAM", FSR 2005.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from slamreplay.algorithms.common.rangebearing import to_points
from slamreplay.algorithms.common.se2 import wrap_angle

F64 = NDArray[np.float64]


def _positive_definite(a: F64) -> bool:
    """Whether the symmetric part of ``a`` is positive definite (a diagonal one: positive diagonal)."""
    diag = np.diagonal(a)
    if np.count_nonzero(a) == np.count_nonzero(diag):
        return bool(np.all(diag > 0))
    try:
        np.linalg.cholesky(0.5 * (a + a.T))
    except np.linalg.LinAlgError:
        return False
    return True


def angle_rows(m: int) -> NDArray[np.int64]:
    """Indices of the angle entries ``alpha_i12`` of an ``m``-feature ``z_map`` (eq. 7)."""
    return np.arange(1, 2 * m - 3, 2, dtype=np.int64)


def _unit_and_normal(v: F64) -> tuple[F64, F64, F64]:
    """|v|, d|v|/dv = v/|v| and d atan2(v)/dv = (-v_y, v_x)/|v|^2 for rows of v (k, 2)."""
    q = np.maximum(np.einsum("ki,ki->k", v, v), 1e-18)
    n = np.sqrt(q)
    return n, v / n[:, None], np.stack([-v[:, 1], v[:, 0]], -1) / q[:, None]


def map_invariants(points: F64) -> tuple[F64, F64]:
    """Eq. (8): ``H_map`` of ``m >= 2`` points (m, 2), anchors first, and its Jacobian.

    Returns the values (2m-3,) ordered as eq. (7), ``[d_12, alpha_312, d_13, ...]``, and the
    Jacobian (2m-3, 2m) with respect to the flattened points ``[x_1, y_1, ..., x_m, y_m]``. The
    same function gives ``z_map`` from the robot-frame points of eq. (4) (eq. 3).
    """
    m = len(points)
    if points.shape != (m, 2) or m < 2:
        raise ValueError(f"points must have shape (m, 2) with m >= 2, got {points.shape}")
    v = points[1:] - points[0]  # f_1 -> f_i for i = 2..m
    dist, unit, normal = _unit_and_normal(v)
    beta = np.arctan2(v[:, 1], v[:, 0])
    values = np.empty(2 * m - 3)
    jac = np.zeros((2 * m - 3, 2 * m))
    values[0] = dist[0]
    jac[0, 2:4], jac[0, 0:2] = unit[0], -unit[0]
    if m > 2:  # features f_3 .. f_m (paper numbering): rows alpha_i12 = 2i - 3 and d_1i = 2i - 2, i = 2..m-1
        i = np.arange(2, m)
        ra, rd = 2 * i - 3, 2 * i - 2
        values[ra] = wrap_angle(beta[1:] - beta[0])
        values[rd] = dist[1:]
        cols = 2 * i[:, None] + np.arange(2)
        jac[ra[:, None], cols] = normal[1:]
        jac[ra, 2:4] = -normal[0]
        jac[ra, 0:2] = normal[0] - normal[1:]
        jac[rd[:, None], cols] = unit[1:]
        jac[rd, 0:2] = -unit[1:]
    return values, jac


def robot_invariants(points: F64) -> tuple[F64, F64]:
    """Eq. (3), first block: ``z_rob = [alpha_r12, d_1r, alpha_phi12]`` and its Jacobian (3, 2m).

    ``points`` are robot-frame positions (m, 2) of the observed features, anchors first; the
    robot sits at the origin of that frame with heading 0.
    """
    m = len(points)
    to_robot = -points[0:1]
    to_f2 = points[1:2] - points[0:1]
    d_r, unit_r, normal_r = _unit_and_normal(to_robot)
    _, _, normal_2 = _unit_and_normal(to_f2)
    beta_2 = float(np.arctan2(to_f2[0, 1], to_f2[0, 0]))
    values = np.array([wrap_angle(np.arctan2(to_robot[0, 1], to_robot[0, 0]) - beta_2), d_r[0], wrap_angle(-beta_2)])
    jac = np.zeros((3, 2 * m))
    jac[0, 0:2], jac[0, 2:4] = -normal_r[0] + normal_2[0], -normal_2[0]
    jac[1, 0:2] = -unit_r[0]
    jac[2, 0:2], jac[2, 2:4] = normal_2[0], -normal_2[0]
    return values, jac


@dataclass(frozen=True, slots=True)
class Recast:
    """One scan's recast measurement (eq. 3) with its full noise covariance.

    ``r_new`` (2m, 2m) is ``J R_old J^T`` with ``jacobian`` = dz_new/dz_old (2m, 2m); ``r_map`` and
    ``r_rob`` are its diagonal blocks, correlated through the off-diagonal block.
    """

    z_rob: F64  # (3,)
    z_map: F64  # (2m - 3,)
    r_new: F64  # (2m, 2m)
    jacobian: F64  # (2m, 2m)

    @property
    def r_map(self) -> F64:
        """Noise covariance of ``z_map`` (2m-3, 2m-3): the mapping model's R_map (eq. 7)."""
        return self.r_new[3:, 3:]

    @property
    def r_rob(self) -> F64:
        """Noise covariance of ``z_rob`` (3, 3)."""
        return self.r_new[:3, :3]


def recast(ranges: F64, bearings: F64, r_old: F64) -> Recast:
    """Eqs. (2)-(4): recast ``m >= 2`` range-bearing measurements (anchors first) as ``z_new``.

    Parameters
    ----------
    ranges, bearings : (m,) metres and radians, robot frame; entries 0 and 1 are f_1 and f_2.
    r_old : (2m, 2m) covariance of ``[r_1, theta_1, ..., r_m, theta_m]``: eq. (2)'s diagonal
        ``rangebearing.noise(m, sigma_r, sigma_b)``, or a full one (merged scans).
    """
    m = len(ranges)
    if m < 2 or bearings.shape != (m,):
        raise ValueError(f"ranges and bearings must be (m,) with m >= 2, got {ranges.shape} and {bearings.shape}")
    if r_old.shape != (2 * m, 2 * m) or not _positive_definite(r_old):
        raise ValueError(f"r_old must be a positive definite ({2 * m}, {2 * m}) matrix")
    points, d_points = to_points(ranges, bearings)
    z_rob, j_rob = robot_invariants(points)
    z_map, j_map = map_invariants(points)
    j_points = np.vstack([j_rob, j_map])  # dz_new / d(points)
    # chain rule through eq. (4), block-diagonal in the features
    jacobian = np.einsum("rkj,kji->rki", j_points.reshape(2 * m, m, 2), d_points).reshape(2 * m, 2 * m)
    diag = np.diagonal(r_old)
    if np.count_nonzero(r_old) == np.count_nonzero(diag):  # eq. (2): a diagonal R_old
        r_new = (jacobian * diag) @ jacobian.T
    else:
        r_new = jacobian @ r_old @ jacobian.T
    return Recast(z_rob=z_rob, z_map=z_map, r_new=0.5 * (r_new + r_new.T), jacobian=jacobian)


def init_features(x1: F64, x2: F64, alpha: F64, dist: F64) -> tuple[F64, F64, F64]:
    """Eq. (9): positions (k, 2) of new features from the anchors' estimates and ``z_map`` entries.

    ``alpha`` and ``dist`` (k,) are each new feature's ``alpha_i12`` and ``d_1i``. Also returns the
    Jacobians with respect to ``[x1, x2]`` (k, 2, 4) and to ``[alpha_i12, d_1i]`` (k, 2, 2).
    """
    v = x2 - x1
    q = max(float(v @ v), 1e-18)
    normal = np.array([-v[1], v[0]]) / q  # d alpha_12 / d x2
    phi = np.arctan2(v[1], v[0]) + alpha
    c, s = np.cos(phi), np.sin(phi)
    pos = np.stack([x1[0] + dist * c, x1[1] + dist * s], -1)
    tangent = np.stack([-dist * s, dist * c], -1)  # d pos / d phi
    k = len(alpha)
    j_x = np.zeros((k, 2, 4))
    outer = tangent[:, :, None] * normal[None, None, :]
    j_x[:, :, 0:2] = np.eye(2) - outer
    j_x[:, :, 2:4] = outer
    j_z = np.stack([tangent, np.stack([c, s], -1)], -1)
    return pos, j_x, j_z
