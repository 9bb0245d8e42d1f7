"""The ``dslam-multi`` pipeline on a tiny three-robot MCAP: one shared map against single-robot ``dslam`` runs,
per-robot scoring, routing by namespace, bad input."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from conftest import write_tiny_recording

from slamreplay.replay.errors import ReplayError
from slamreplay.replay.runs.run import run_recording
from tests.replay.view_runs import STARTS, write_multi_recording


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
        assert 0.005 < m[f"robot{k}_ape_rmse_m"] < 0.15
    assert m["ape_rmse_m"] < 0.15 and m["info_nnz_blocks_per_landmark"] < 20
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
    from slamreplay.replay.engine.loop import replay
    from slamreplay.replay.engine.observer import MemoryObserver
    from slamreplay.replay.engine.pipeline import all_robots_topic_map, get_pipeline, resolve_config
    from slamreplay.replay.engine.reader import RecordingReader

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
