"""The reference a data set without ground truth is scored against: the batch optimum of its own measurements.

For Victoria Park (no GPS in the iSAM file) the reference is the full-SLAM least-squares optimum
of the same odometry and landmark observations with the noise GTSAM's loader assigns them
(:func:`recorder.importers.victoria_park.gtsam_noise`), found by
:func:`algorithms.common.landmark_graph.solve_incremental`. A filter scored against it is
scored on how close it gets to the best estimate the measurements allow, not on the truth.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from algorithms.common.landmark_graph import LandmarkGraph, LsqConfig, LsqResult, residuals, solve_incremental
from recorder.importers.victoria_park import VictoriaPark, gtsam_noise


def victoria_park_graph(data: VictoriaPark) -> LandmarkGraph:
    """The data set as a pose-landmark graph; landmarks indexed in ``data.landmark_ids`` order."""
    model = gtsam_noise()
    rb = data.ranges_bearings()
    info = np.diag([1.0 / model["range_sigma_m"] ** 2, 1.0 / model["bearing_sigma_rad"] ** 2])
    odo_info = np.asarray(np.linalg.inv(data.odo_cov), dtype=np.float64)
    lm_index = np.searchsorted(data.landmark_ids, data.obs_landmark)
    return LandmarkGraph(len(data.pose_ids), len(data.landmark_ids), data.odo_i, data.odo_j, data.odo_z, odo_info,
                         data.obs_pose, lm_index, rb, np.broadcast_to(info, (len(rb), 2, 2)).copy())


def victoria_park_reference(data: VictoriaPark, cfg: LsqConfig | None = None
                            ) -> tuple[NDArray[np.float64], NDArray[np.float64], LsqResult]:
    """Poses (n, 3), landmarks (L, 2) of the batch optimum, and the solver's result (χ², iterations)."""
    res = solve_incremental(victoria_park_graph(data), cfg or LsqConfig())
    return res.poses, res.landmarks, res


def measured_noise(data: VictoriaPark, poses: NDArray[np.float64], landmarks: NDArray[np.float64]
                   ) -> dict[str, float]:
    """The noise the measurements show about the reference, as pipeline config keys.

    Root-mean-square residuals at the optimum, scaled by ``sqrt(residuals / degrees of freedom)``
    (the optimum absorbs part of the noise: 28,184 residuals against 21,206 unknowns on Victoria
    Park, so the scale is about 2). One scale for all residual kinds is an approximation: odometry
    residuals are absorbed more than landmark ones. Odometry is per square root of a metre driven,
    as the pipelines' noise model (algorithms/common/motion.py) is.
    """
    e_odo, e_obs = residuals(victoria_park_graph(data), poses, landmarks)
    n_res = e_odo.size + e_obs.size
    dof = n_res - 3 * (len(poses) - 1) - 2 * len(landmarks)
    scale = math.sqrt(n_res / dof) if dof > 0 else math.nan
    dist = float(np.sum(np.hypot(data.odo_z[:, 0], data.odo_z[:, 1])))
    return {
        "translation_sigma_per_sqrt_m": scale * math.sqrt(float(np.sum(e_odo[:, :2] ** 2)) / 2.0 / dist),
        "heading_sigma_per_sqrt_m": scale * math.sqrt(float(np.sum(e_odo[:, 2] ** 2)) / dist),
        "heading_sigma_per_sqrt_rad": 0.0,
        "range_sigma_m": scale * float(np.sqrt(np.mean(e_obs[:, 0] ** 2))),
        "bearing_sigma_rad": scale * float(np.sqrt(np.mean(e_obs[:, 1] ** 2))),
    }
