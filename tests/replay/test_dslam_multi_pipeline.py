"""The ``dslam-multi`` pipeline on a tiny three-robot MCAP: one shared map against single-robot ``dslam`` runs,
per-robot scoring, routing by namespace, bad input."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from conftest import write_tiny_recording

from slamreplay.algorithms.common import se2
from slamreplay.recorder import GroundTruthPose, LandmarkMap, OdometryPose, RangeBearingScan, Recorder
from slamreplay.replay.errors import ReplayError
from slamreplay.replay.run import run_recording

STARTS = {1: np.array([4.0, 5.0, 0.3]), 2: np.array([12.0, 6.0, -1.0]), 3: np.array([20.0, 5.0, 2.0])}
SIGMA_R, SIGMA_B = 0.05, np.radians(1.0)


def write_multi_recording(path: Path, steps: int = 200, seed: int = 4, robots: tuple[int, ...] = (1, 2, 3),
                          truth: tuple[int, ...] = (1, 2, 3)) -> Path:
    """Robots wandering around their own part of a 8 x 4 landmark grid, topics under /robotN/, ground truth
    for the robots in ``truth``; one step is 0.2 s, the robots' messages 1 ms apart within a step."""
    rng = np.random.default_rng(seed)
    gx, gy = np.arange(8) * 3.0 + 1.0, np.arange(4) * 3.0 + 1.0
    lm = np.stack(np.meshgrid(gx, gy), -1).reshape(-1, 2)
    pose = {k: STARTS[k].copy() for k in robots}
    odo = {k: np.zeros(3) for k in robots}
    with Recorder(path, source={"test": "multi"}, seed=seed) as rec:
        rec.write("/ground_truth/landmarks", LandmarkMap(1_000_000_000, np.arange(len(lm)), lm))
        for step in range(steps):
            for k in robots:
                t = 1_000_000_000 + step * 200_000_000 + k * 1_000_000
                ns = f"/robot{k}"
                if k in truth:
                    rec.write(f"{ns}/ground_truth/pose", GroundTruthPose(t, *pose[k]))
                rec.write(f"{ns}/odom", OdometryPose(t, *odo[k]))
                rel = se2.transform_points(se2.inverse(pose[k]), lm)
                r, b = np.hypot(rel[:, 0], rel[:, 1]), np.arctan2(rel[:, 1], rel[:, 0])
                ids = np.flatnonzero((r < 5) & (np.abs(b) < np.pi / 2))
                rec.write(f"{ns}/landmarks/range_bearing",
                          RangeBearingScan(t, r[ids] + rng.normal(0, SIGMA_R, len(ids)),
                                           b[ids] + rng.normal(0, SIGMA_B, len(ids)), ids, SIGMA_R, SIGMA_B))
                home = STARTS[k][:2] + np.array([0.0, 0.5]) - pose[k][:2]
                w = float(np.clip(rng.normal(0, 0.1), -0.3, 0.3))
                if np.hypot(*home) > 3:
                    w = float(np.clip(se2.wrap_angle(np.arctan2(home[1], home[0]) - pose[k][2]), -0.3, 0.3))
                u = np.array([0.04, 0.0, 0.2 * w])
                pose[k] = se2.compose(pose[k], u)
                odo[k] = se2.compose(odo[k], u + rng.normal(0, [0.004, 0.001, 0.004]))
    return path


@pytest.fixture(scope="module")
def multi(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_multi_recording(tmp_path_factory.mktemp("multi") / "multi.mcap")


def test_shared_map_against_single_robot_runs(multi: Path, tmp_path: Path) -> None:
    """Three robots map more landmarks together than any one alone; every robot scored against its own truth."""
    res = run_recording(multi, "dslam-multi", tmp_path / "multi", config={"final_relinearization_iterations": 0})
    m = res.metrics
    singles = [run_recording(multi, "dslam", tmp_path / f"r{k}", robot=str(k),
                             config={"final_relinearization_iterations": 0}).metrics for k in STARTS]
    assert m["robots"] == 3 and m["steps"] == 600 and m["false_landmarks"] == 0 and m["landmarks_true"] == 32
    assert m["landmarks_mapped"] > max(s["landmarks_mapped"] for s in singles)
    assert m["landmarks_mapped"] >= 24  # 28; alone: 13, 13 and 9
    assert 0.005 < m["landmark_rmse_m"] < 0.1
    assert 0.1 < m["landmark_nees_mean"] < 6.0
    for k in STARTS:
        assert m[f"robot{k}_scans"] == 200
        assert 0.005 < m[f"robot{k}_ate_rmse_m"] < 0.15
    assert m["robot_ate_rmse_m"] < 0.15 and m["info_nnz_blocks_per_landmark"] < 20
    first_only = run_recording(multi, "dslam-multi", tmp_path / "first", preset="paper").metrics
    assert max(s["landmarks_mapped"] for s in singles) < first_only["landmarks_mapped"] < m["landmarks_mapped"]
    manifest = json.loads((res.run_dir / "manifest.json").read_text())
    assert manifest["recording"]["robot"] == "all"
    assert manifest["recording"]["topic_map"]["/robot2/odom"] == "/robot2/odom"
    log = (res.run_dir / "log.txt").read_text()
    assert "robot 2 starts at" in log and "map frame: robot 1's start" in log
    again = run_recording(multi, "dslam-multi", tmp_path / "again", config={"final_relinearization_iterations": 0})
    assert again.metrics == m  # deterministic


def test_missing_robot_topics_and_bad_config(multi: Path, tmp_path: Path) -> None:
    """A robot without ground truth, --robot, a bad start sigma, composite scans, one robot's recording: refused."""
    no_truth = write_multi_recording(tmp_path / "no-truth.mcap", steps=5, truth=(1, 3))
    with pytest.raises(ReplayError, match=r"robot 2 has no /robot2/ground_truth/pose messages, which dslam-multi "
                                          r"needs \(its start pose in robot 1's frame comes from ground truth\)"):
        run_recording(no_truth, "dslam-multi", tmp_path / "a")
    no_ref = write_multi_recording(tmp_path / "no-ref.mcap", steps=5, robots=(2, 3), truth=(2, 3))
    with pytest.raises(ReplayError, match="has no /robot1/odom topic"):
        run_recording(no_ref, "dslam-multi", tmp_path / "b")
    with pytest.raises(ReplayError, match="replays every robot of the recording at once: drop --robot"):
        run_recording(multi, "dslam-multi", tmp_path / "c", robot="2")
    with pytest.raises(ReplayError, match="start_sigma_m must be finite and >= 0, got -1.0"):
        run_recording(multi, "dslam-multi", tmp_path / "d", config={"start_sigma_m": "-1"})
    with pytest.raises(ReplayError, match="composite_max_scans must be 0 for dslam-multi"):
        run_recording(multi, "dslam-multi", tmp_path / "e", config={"composite_max_scans": "10"})
    with pytest.raises(ReplayError, match="association must be 'known' or 'auto'"):
        run_recording(multi, "dslam-multi", tmp_path / "f", config={"association": "unknown"})
    with pytest.raises(ReplayError, match=r"holds no multi-robot topics \(none under /robotN/\)"):
        run_recording(write_tiny_recording(tmp_path / "one.mcap", n=20), "dslam-multi", tmp_path / "g")


def test_each_robot_is_drawn(multi: Path) -> None:
    """The shared map once; each robot's pose, trajectory estimate and truth under its own entity."""
    from slamreplay.replay.engine import replay
    from slamreplay.replay.observer import MemoryObserver
    from slamreplay.replay.pipeline import all_robots_topic_map, get_pipeline, resolve_config
    from slamreplay.replay.reader import RecordingReader

    reader = RecordingReader(multi, all_robots_topic_map(RecordingReader(multi).info))
    obs = MemoryObserver()
    cls = get_pipeline("dslam-multi")
    stats = replay(reader, cls, resolve_config(cls, {"final_relinearization_iterations": "0"}), obs, seed=0,
                   log=lambda _: None)
    assert stats.metrics["landmarks_mapped"] >= 24
    paths = obs.paths()
    assert {"world/landmarks/estimate", "world/landmarks/truth", "world/information/links",
            "dslam/information/sparsity"} <= paths
    for k in STARTS:
        assert {f"world/robots/robot{k}", f"world/trajectory/robot{k}/estimate",
                f"world/trajectory/robot{k}/truth"} <= paths
