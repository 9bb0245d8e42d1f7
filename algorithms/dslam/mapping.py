"""D-SLAM mapping updates (section 2.2 of [1]_): phase I, phase II (eqs. 9-10) and the anchor rule.

The map is the absolute feature positions X (eq. 5) in the initial robot frame, estimated by an
Extended Information Filter with no prediction step: every function here returns the increment
``(dI, di)`` that eq. (10) adds to I and i on the observed features.

References
----------
.. [1] Z. Wang, S. Huang, G. Dissanayake, "Implementation issues and experimental evaluation
   of D-SLAM", FSR 2005, section 2.2, eqs. (5)-(10).
"""

from __future__ import annotations

import numpy as np
import scipy.linalg as sla
from numpy.typing import NDArray

from slamreplay.algorithms.common import rangebearing
from slamreplay.algorithms.common.se2 import wrap_angle
from slamreplay.algorithms.dslam.recast import Recast, angle_rows, map_invariants

F64 = NDArray[np.float64]


def eif_increment(h_jac: F64, r_cov: F64, innovation: F64, x_lin: F64) -> tuple[F64, F64]:
    """Eq. (10): ``dI = H^T R^-1 H`` and ``di = H^T R^-1 (nu + H x_lin)``, with nu = z - h(x_lin) wrapped."""
    chol = sla.cho_factor(0.5 * (r_cov + r_cov.T), check_finite=False)
    w_h = sla.cho_solve(chol, h_jac, check_finite=False)
    d_matrix = h_jac.T @ w_h
    d_vector = w_h.T @ (innovation + h_jac @ x_lin)
    return 0.5 * (d_matrix + d_matrix.T), d_vector


def phase_one_increment(position: F64, z: F64, r_cov: F64) -> tuple[F64, F64]:
    """Phase I: one feature's EIF increment (2, 2), (2,) from its range-bearing ``z`` (2,).

    The robot is at the origin of the map frame, exactly known: the original measurement
    (eq. 1) is a direct, nonlinear observation of the feature, linearised at ``position`` (2,).
    """
    d_matrix, d_vector, _ = phase_one_terms(position, z, r_cov)
    return d_matrix, d_vector


def phase_one_terms(position: F64, z: F64, r_cov: F64) -> tuple[F64, F64, F64]:
    """:func:`phase_one_increment` and the Jacobian dz/dX_f (2, 2) it was linearised with (eq. 1)."""
    zp, _, h_l = rangebearing.predict(np.zeros(3), position[None, :])
    nu = z - zp[0]
    nu[1] = wrap_angle(nu[1])
    d_matrix, d_vector = eif_increment(h_l[0], r_cov, nu, position)
    return d_matrix, d_vector, h_l[0]


def recast_increment(positions: F64, rc: Recast) -> tuple[F64, F64]:
    """Phase II: eq. (10) with the model ``H_map`` of eq. (8) at the features' estimates (m, 2).

    ``positions`` are ordered like the recast measurement: anchors f_1, f_2 first.
    """
    d_matrix, d_vector, _ = recast_terms(positions, rc)
    return d_matrix, d_vector


def recast_terms(positions: F64, rc: Recast) -> tuple[F64, F64, F64]:
    """:func:`recast_increment` and the Jacobian ``grad H_map`` (2m-3, 2m) it was linearised with (eq. 8)."""
    return invariant_terms(positions, rc.z_map, rc.r_map)


def invariant_terms(positions: F64, z_map: F64, r_map: F64) -> tuple[F64, F64, F64]:
    """:func:`recast_terms` from ``z_map`` (2m-3,) and its noise ``r_map`` (2m-3, 2m-3) alone."""
    h, jac = map_invariants(positions)
    nu = z_map - h
    rows = angle_rows(len(positions))
    nu[rows] = wrap_angle(nu[rows])
    d_matrix, d_vector = eif_increment(jac, r_map, nu, positions.reshape(-1))
    return d_matrix, d_vector, jac


def bootstrap_increment(pose: F64, pose_cov: F64, ranges: F64, bearings: F64, r_old: F64
                        ) -> tuple[F64, F64, F64]:
    """Features initialised from the robot estimate, for a map with fewer than two features in phase II.

    Not in the paper, which assumes phase I maps at least two features. Returns positions (k, 2)
    and the information ``(Sigma^-1, Sigma^-1 l)`` of their joint first-order covariance
    ``Sigma = G_r P G_r^T + G_z R G_z^T`` (G_z block-diagonal, R = ``r_old`` (2k, 2k)), which keeps the
    shared robot error.
    """
    lm, g_pose, g_z = rangebearing.landmarks_from(pose, ranges, bearings)
    k = len(lm)
    gr = g_pose.reshape(2 * k, 3)
    gz = sla.block_diag(*g_z)
    sigma = gr @ pose_cov @ gr.T + gz @ r_old @ gz.T
    info = np.linalg.inv(0.5 * (sigma + sigma.T))
    info = 0.5 * (info + info.T)
    return lm, info, info @ lm.reshape(-1)


def choose_anchors(points: F64, traces: F64) -> tuple[int, int]:
    """The anchor pair f_1, f_2 among ``m1 >= 2`` mapped features observed in one scan.

    Rule: the pair whose baseline direction is best known, i.e. minimising
    ``(tr P_a + tr P_b) / |p_a - p_b|^2`` (``points`` (m1, 2) are the robot-frame observations, ``traces``
    (m1,) the traces of the features' marginal covariances); f_1 is the better known of the two.
    The direction f_1 -> f_2 carries the new features' bearings in eq. (9). Ties go to the
    earlier observations. Returns indices into ``points``.
    """
    m = len(points)
    if m < 2:
        raise ValueError(f"points must hold at least two features, got {m}")
    d2 = np.sum((points[:, None, :] - points[None, :, :]) ** 2, axis=-1)
    score = (traces[:, None] + traces[None, :]) / np.maximum(d2, 1e-12)
    score[np.tril_indices(m)] = np.inf
    a, b = divmod(int(np.argmin(score)), m)
    return (a, b) if traces[a] <= traces[b] else (b, a)
