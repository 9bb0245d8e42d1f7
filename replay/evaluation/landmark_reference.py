"""The reference a data set without ground truth is scored against: the batch optimum of its own measurements.

For Victoria Park (no GPS in the iSAM file) the reference is the full-SLAM least-squares optimum
of the same odometry and landmark observations with the noise GTSAM's loader assigns them
(:func:`slamreplay.recorder.importers.victoria_park.gtsam_noise`), found by
:func:`slamreplay.algorithms.common.landmark_graph.solve_incremental`. A filter scored against it is
scored on how close it gets to the best estimate the measurements allow, not on the truth.

That optimum weighs the measurements as GTSAM's loader does; the recording's sensor model, the noise the
filters are given, is what the sightings show about it (:func:`measured_noise`), several times tighter in
range and bearing. Two weightings, two optima: :func:`optimum_under` is the optimum of the same measurements
under the noise a filter is given, the efficient estimate that filter's consistency is judged against.
:func:`recording_reference` is what ``slamreplay record victoria-park`` writes as ``/ground_truth/*``: the
optimum under the recording's own sensor model, the noise every pipeline is given unless a user sets
another, so that a consistent filter's NEES against it stays below the upper end of its band (the lower
end is 0: an efficient estimate scores 0 against itself).
"""

from __future__ import annotations

import math
from dataclasses import fields, replace

import numpy as np
from numpy.typing import NDArray

from slamreplay.algorithms.common.landmark_graph import (
    LandmarkGraph,
    LsqConfig,
    LsqResult,
    landmark_covariance,
    noise_scales,
    optimize,
    solve_incremental,
)
from slamreplay.algorithms.common.motion import OdometryNoise
from slamreplay.recorder.importers.victoria_park import VictoriaPark, gtsam_noise, sensor_model


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


def measured_scales(data: VictoriaPark, poses: NDArray[np.float64], landmarks: NDArray[np.float64], *,
                    seed: int = 0) -> NDArray[np.float64]:
    """Each residual kind's noise relative to its model at the reference (odometry x, y, θ, range, bearing:
    :func:`slamreplay.algorithms.common.landmark_graph.noise_scales`, seeded); 1 where it cannot be measured."""
    c = noise_scales(victoria_park_graph(data), poses, landmarks, np.random.default_rng(seed))
    return np.where(np.isfinite(c), c, 1.0)  # not measurable: the model's own sigma stands


def reference_covariance(data: VictoriaPark, poses: NDArray[np.float64], landmarks: NDArray[np.float64],
                         scales: NDArray[np.float64]) -> NDArray[np.float64]:
    """The joint covariance (2 L, 2 L) of the reference's landmarks under the measured noise (``scales``): how far
    the batch optimum itself is from the truth, to first order. A filter scored against the reference is
    judged on its error's covariance ``P - P_ref`` (:func:`slamreplay.replay.evaluation.metrics.mean_nees_band`)."""
    return landmark_covariance(victoria_park_graph(data), poses, landmarks, scales)


def measured_noise(data: VictoriaPark, poses: NDArray[np.float64], landmarks: NDArray[np.float64], *,
                   seed: int = 0) -> dict[str, float]:
    """The noise the measurements show about the reference, as pipeline config keys.

    Each residual kind's modelled sigma (:func:`slamreplay.recorder.importers.victoria_park.gtsam_noise` and the
    file's odometry covariance) times the factor its residuals show at the optimum, corrected for
    the unknowns that kind absorbs (:func:`slamreplay.algorithms.common.landmark_graph.noise_scales`, seeded).
    A kind the optimum absorbs almost whole keeps its modelled sigma (factor 1).
    Odometry becomes per square root of a metre driven, as the pipelines' noise model
    (algorithms/common/motion.py) is: the forward sigma of a step of mean length.
    """
    c = measured_scales(data, poses, landmarks, seed=seed)
    step_m = float(np.mean(np.hypot(data.odo_z[:, 0], data.odo_z[:, 1])))
    sig_step = np.sqrt(np.mean(np.diagonal(data.odo_cov, axis1=1, axis2=2), axis=0))  # (3,) x, y, θ per step
    model = gtsam_noise()
    return {
        "translation_sigma_per_sqrt_m": float(c[0] * sig_step[0] / math.sqrt(step_m)),
        "heading_sigma_per_sqrt_m": float(c[2] * sig_step[2] / math.sqrt(step_m)),
        "heading_sigma_per_sqrt_rad": 0.0,
        "range_sigma_m": float(c[3] * model["range_sigma_m"]),
        "bearing_sigma_rad": float(c[4] * model["bearing_sigma_rad"]),
    }


def graph_under(data: VictoriaPark, odometry_noise: OdometryNoise, range_sigma_m: float,
                bearing_sigma_rad: float) -> LandmarkGraph:
    """The least-squares problem of ``data`` with each odometry step weighed by ``odometry_noise``'s covariance of
    that step (as a filter predicting with it does) and each sighting by ``range_sigma_m`` and
    ``bearing_sigma_rad``; ValueError for a sigma that is not finite and positive."""
    for name, value in (("range_sigma_m", range_sigma_m), ("bearing_sigma_rad", bearing_sigma_rad)):
        if not (math.isfinite(value) and value > 0):
            raise ValueError(f"{name} must be finite and > 0, got {value}")
    graph = victoria_park_graph(data)
    # a step the model gives no noise (the robot stood still) is held by the floor, as a filter holds it exactly
    odo_info = np.array([np.linalg.inv(odometry_noise.covariance(u) + 1e-12 * np.eye(3)) for u in graph.odo_z])
    obs_info = np.broadcast_to(np.diag([1.0 / range_sigma_m**2, 1.0 / bearing_sigma_rad**2]), graph.obs_info.shape)
    return replace(graph, odo_info=odo_info.reshape(-1, 3, 3), obs_info=obs_info.copy())


def optimum_under(data: VictoriaPark, odometry_noise: OdometryNoise, range_sigma_m: float, bearing_sigma_rad: float,
                  poses: NDArray[np.float64], landmarks: NDArray[np.float64]
                  ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """The batch optimum of ``data`` under the noise a filter is given, and its joint landmark covariance.

    Each odometry step weighed by ``odometry_noise``'s covariance of that step (as a filter predicting with it
    does), each sighting by ``range_sigma_m`` and ``bearing_sigma_rad``; Levenberg-Marquardt from ``poses`` and
    ``landmarks`` (the reference), pose 0 held where it is. Returns poses (n, 3), landmarks (L, 2) and their joint
    covariance (2 L, 2 L) at that optimum (first order). A filter that is the maximum-likelihood estimate under that
    noise lands on it; a consistent one's error from it has covariance ``P - P_opt`` (the optimum is efficient),
    below ``P``, so its mean landmark NEES against it stays below the upper end of the band against the truth.
    RuntimeError when Levenberg-Marquardt does not converge."""
    graph = graph_under(data, odometry_noise, range_sigma_m, bearing_sigma_rad)
    res = optimize(graph, poses, landmarks, LsqConfig())
    if not res.converged:
        raise RuntimeError(f"the optimum under the given noise did not converge in {res.iterations} iterations")
    return res.poses, res.landmarks, landmark_covariance(graph, res.poses, res.landmarks)


def recording_reference(data: VictoriaPark) -> tuple[NDArray[np.float64], NDArray[np.float64], dict[str, float], str]:
    """The reference a Victoria Park recording carries: poses (n, 3) and landmarks (L, 2), the noise measured
    about GTSAM's optimum (config keys) and a note saying what the reference is.

    First GTSAM's optimum (:func:`victoria_park_reference`, whose χ² checks that the file is read as GTSAM reads
    it) and the noise the sightings show about it (:func:`measured_noise`), then from it the optimum under the
    recording's sensor model (:func:`~slamreplay.recorder.importers.victoria_park.sensor_model`, that noise
    rounded: what every pipeline is given). Should that not converge, GTSAM's optimum is the reference, and the
    note says so."""
    poses, landmarks, res = victoria_park_reference(data)
    measured = measured_noise(data, poses, landmarks)
    model = sensor_model()
    odometry = OdometryNoise(**{f.name: model[f.name] for f in fields(OdometryNoise)})  # the same config keys
    gtsam = (f"GTSAM's optimum of the file's weights, chi2 {res.chi2:.1f}, "
             f"{'converged' if res.converged else 'not converged'}")
    under = optimize(graph_under(data, odometry, model["range_sigma_m"], model["bearing_sigma_rad"]), poses,
                     landmarks, LsqConfig())
    if not under.converged:
        return poses, landmarks, measured, (f"{gtsam} (its optimum under the recording's sensor model did not "
                                            f"converge); the file has no ground truth")
    moved = float(np.sqrt(np.mean(np.sum((under.landmarks - landmarks) ** 2, axis=1)))) if len(landmarks) else 0.0
    return under.poses, under.landmarks, measured, (
        f"batch least-squares optimum of the same measurements under the recording's sensor model (from {gtsam}, "
        f"{moved:.2f} m tree RMSE away); the file has no ground truth")
