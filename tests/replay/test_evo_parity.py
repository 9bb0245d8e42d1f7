"""evo itself (its Python API, as ``evo_ape``/``evo_rpe`` use it) against slamreplay's trajectory metrics.

Every trajectory metric a run reports (``TRAJECTORY_METRICS``: APE without and with SE(2) alignment, heading
APE, RPE per step and per metre, translation and rotation) and the APE after ``--align_origin`` that
``slamreplay trajectory`` prints are computed by evo on the same poses, and must agree to 6 significant digits.
slamreplay is planar; evo is SE(3): the poses go to evo with z = 0 and a quaternion about +z.

evo's settings, one per metric (the command lines its users type):

- ``ape_rmse_m``: ``evo_ape tum truth.tum trajectory.tum`` (``--pose_relation trans_part``, no alignment)
- ``ape_se2_rmse_m``: ``... --align`` (Umeyama without scale, in 3D)
- ``ape_rot_rmse_deg``: ``... --pose_relation angle_deg``
- ``rpe_step_*``: ``evo_rpe tum truth.tum trajectory.tum --delta 1 --delta_unit f`` (``trans_part``, ``angle_deg``)
- ``rpe_m_*``: ``evo_rpe ... --delta 1 --delta_unit m`` (consecutive pairs, measured on the estimate's path)

Skipped when evo is not installed (it is in the ``dev`` extra).
"""

from __future__ import annotations

import copy
import math
from pathlib import Path

import numpy as np
import pytest
from conftest import write_tiny_recording

from slamreplay.algorithms.common import se2
from slamreplay.replay.engine.trajectory import read_tum
from slamreplay.replay.evaluation.evaluate import TRAJECTORY_METRICS, ape, rpe, trajectory_metrics
from slamreplay.replay.metric_registry import RPE_METRE_DELTA_M
from slamreplay.replay.runs.run import run_recording
from slamreplay.replay.runs.trajectory_eval import evaluate_run

evo = pytest.importorskip("evo", reason="evo is not installed (pip install -e '.[dev]' brings it): the parity of "
                                        "the trajectory metrics with evo is not checked")
from evo.core import metrics, sync, trajectory  # noqa: E402
from evo.tools import file_interface  # noqa: E402

SIGNIFICANT = 1e-6  # 6 significant digits


def _evo_trajectory(t_s: np.ndarray, poses: np.ndarray) -> trajectory.PoseTrajectory3D:
    """Planar poses (n, 3) as evo's SE(3) trajectory: z = 0, the yaw as a quaternion about +z (w, x, y, z)."""
    half = poses[:, 2] / 2
    xyz = np.column_stack([poses[:, 0], poses[:, 1], np.zeros(len(poses))])
    wxyz = np.column_stack([np.cos(half), np.zeros(len(poses)), np.zeros(len(poses)), np.sin(half)])
    return trajectory.PoseTrajectory3D(positions_xyz=xyz, orientations_quat_wxyz=wxyz, timestamps=t_s)


def evo_figures(ref: trajectory.PoseTrajectory3D, est: trajectory.PoseTrajectory3D) -> dict[str, float]:
    """The eight figures as evo computes them (the RMSE of each, evo's defaults but for the settings named)."""

    def rmse(metric: metrics.PE, data: tuple[trajectory.PosePath3D, trajectory.PosePath3D]) -> float:
        metric.process_data(data)
        return float(metric.get_statistic(metrics.StatisticsType.rmse))

    trans, angle = metrics.PoseRelation.translation_part, metrics.PoseRelation.rotation_angle_deg
    out = {"ape_rmse_m": rmse(metrics.APE(trans), (ref, est)),
           "ape_rot_rmse_deg": rmse(metrics.APE(angle), (ref, est))}
    aligned = copy.deepcopy(est)
    aligned.align(ref, correct_scale=False)
    out["ape_se2_rmse_m"] = rmse(metrics.APE(trans), (ref, aligned))
    origin = copy.deepcopy(est)
    origin.align_origin(ref)
    out["ape_origin_rmse_m"] = rmse(metrics.APE(trans), (ref, origin))
    for key, delta, unit in (("step", 1, metrics.Unit.frames), ("m", RPE_METRE_DELTA_M, metrics.Unit.meters)):
        out[f"rpe_{key}_trans_rmse_m"] = rmse(metrics.RPE(trans, delta, unit), (ref, est))
        out[f"rpe_{key}_rot_rmse_deg"] = rmse(metrics.RPE(angle, delta, unit), (ref, est))
    return out


def slamreplay_figures(est: np.ndarray, ref: np.ndarray) -> dict[str, float]:
    """The same eight figures from slamreplay: a run's metrics and `trajectory --align origin`'s APE."""
    return {**trajectory_metrics(est, ref), "ape_origin_rmse_m": ape(est, ref, "origin")[0].rmse}


def _assert_same(ours: dict[str, float], theirs: dict[str, float]) -> None:
    assert set(TRAJECTORY_METRICS) | {"ape_origin_rmse_m"} == set(ours) == set(theirs)
    for name, value in theirs.items():
        assert ours[name] == pytest.approx(value, rel=SIGNIFICANT, abs=1e-12), (name, ours[name], value)


def _noisy_loop(seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(t_s, truth, estimate): two laps of a 3 m figure eight at 10 Hz with stops, the estimate drifting (a
    random walk in the odometry increments) and jittering, headings across +-pi many times."""
    rng = np.random.default_rng(seed)
    n = 1200
    s = np.linspace(0.0, 4 * np.pi, n)
    s[300:340] = s[300]  # the robot stands still for 4 s: no path, and pairs must not form there
    truth = np.column_stack([3 * np.sin(s), 1.5 * np.sin(2 * s), np.zeros(n)])
    d = np.diff(truth[:, :2], axis=0)
    heading = np.arctan2(d[:, 1], d[:, 0])
    for k in range(1, n):  # along the path; standing still, the heading it had
        truth[k, 2] = heading[k - 1] if np.hypot(*d[k - 1]) > 0 else truth[k - 1, 2]
    steps = se2.between(truth[:-1], truth[1:])
    noisy = steps + rng.normal(0.0, [0.004, 0.002, 0.003], steps.shape) + [0.001, 0.0, 0.0005]
    est = np.zeros_like(truth)
    est[0] = truth[0]
    for k, step in enumerate(noisy):
        est[k + 1] = se2.compose(est[k], step)
    est[:, :2] += rng.normal(0.0, 0.01, (n, 2))  # position jitter: the estimate's path is longer than the truth's
    return 1.0 + 0.1 * np.arange(n), truth, est


def test_a_noisy_simulated_trajectory_agrees_with_evo() -> None:
    """A drifting, jittering estimate of a figure eight with a stop: the eight figures equal evo's."""
    t, truth, est = _noisy_loop(7)
    theirs = evo_figures(_evo_trajectory(t, truth), _evo_trajectory(t, est))
    ours = slamreplay_figures(est, truth)
    _assert_same(ours, theirs)
    # the per-metre pairs are the estimate's (evo's default): the truth's give another figure, as evo's
    # --pairs_from_reference does
    by_truth = rpe(est, truth, RPE_METRE_DELTA_M, "m", pairs_from_reference=True)[0].rmse
    evo_by_truth = metrics.RPE(metrics.PoseRelation.translation_part, RPE_METRE_DELTA_M, metrics.Unit.meters,
                               pairs_from_reference=True)
    evo_by_truth.process_data((_evo_trajectory(t, truth), _evo_trajectory(t, est)))
    assert by_truth == pytest.approx(evo_by_truth.get_statistic(metrics.StatisticsType.rmse), rel=SIGNIFICANT)
    assert abs(by_truth / ours["rpe_m_trans_rmse_m"] - 1) > 1e-3


def test_large_errors_and_headings_across_pi_agree_with_evo() -> None:
    """An estimate rotated by 170 degrees about a far point, with heading errors past 90 degrees: angles wrap
    as evo's rotation angles do (0 to 180 degrees)."""
    rng = np.random.default_rng(3)
    n = 400
    a = np.linspace(0.0, 6 * np.pi, n)
    truth = np.column_stack([5 * np.cos(a), 5 * np.sin(a), se2.wrap_angle(a + np.pi / 2)])
    est = se2.compose(np.array([20.0, -4.0, math.radians(170.0)]), truth)
    est[:, 2] = se2.wrap_angle(est[:, 2] + rng.uniform(-2.5, 2.5, n))
    est[:, :2] += rng.normal(0.0, 0.3, (n, 2))
    t = 100.0 + 0.05 * np.arange(n)
    _assert_same(slamreplay_figures(est, truth), evo_figures(_evo_trajectory(t, truth), _evo_trajectory(t, est)))


def test_a_runs_files_agree_with_evo_reading_them(tmp_path: Path) -> None:
    """A dslam run of a simulated landmark world: evo reads its trajectory.tum and truth.tum (evo_ape/evo_rpe's
    way: TUM files, associated by time) and gives the run's own metrics.json figures."""
    rec = write_tiny_recording(tmp_path / "tiny.mcap")
    result = run_recording(rec, "dslam", tmp_path / "run")
    est_file, truth_file = result.run_dir / "trajectory.tum", result.run_dir / "truth.tum"
    ref = file_interface.read_tum_trajectory_file(str(truth_file))
    est = file_interface.read_tum_trajectory_file(str(est_file))
    ref, est = sync.associate_trajectories(ref, est, max_diff=1e-6)
    theirs = evo_figures(ref, est)
    ours = {**{k: v for k, v in result.metrics.items() if k in TRAJECTORY_METRICS},
            "ape_origin_rmse_m": evaluate_run(result.run_dir, "origin").ape_trans.rmse}
    assert ref.num_poses == est.num_poses == len(read_tum(truth_file.read_text())[0])
    _assert_same(ours, theirs)
