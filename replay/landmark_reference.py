"""The reference a data set without ground truth is scored against: the batch optimum of its own measurements.

For Victoria Park (no GPS in the iSAM file) the reference is the full-SLAM least-squares optimum
of the same odometry and landmark observations with the noise GTSAM's loader assigns them
(:func:`recorder.importers.victoria_park.sensor_model`), found by
:func:`algorithms.common.landmark_graph.solve_incremental`. A filter scored against it is
scored on how close it gets to the best estimate the measurements allow, not on the truth.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from algorithms.common.landmark_graph import LandmarkGraph, LsqConfig, LsqResult, solve_incremental
from recorder.importers.victoria_park import VictoriaPark, sensor_model


def victoria_park_graph(data: VictoriaPark) -> LandmarkGraph:
    """The data set as a pose-landmark graph; landmarks indexed in ``data.landmark_ids`` order."""
    model = sensor_model()
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
