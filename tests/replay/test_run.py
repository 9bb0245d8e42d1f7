"""Runs: the odometry pipeline end to end, determinism, and what a failed run leaves behind."""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import numpy as np
import pytest
from conftest import write_tiny_recording

from slamreplay.recorder import GroundTruthPose, OdometryPose, Recorder
from slamreplay.replay.engine.loop import replay, start_pose
from slamreplay.replay.engine.observer import MemoryObserver
from slamreplay.replay.engine.pipeline import get_pipeline, resolve_config
from slamreplay.replay.engine.reader import RecordingReader
from slamreplay.replay.errors import ReplayError
from slamreplay.replay.runs.rrd_compare import rerun_cli
from slamreplay.replay.runs.run import run_recording


def test_dead_reckoning_known_answer(tmp_path: Path) -> None:
    """Odometry 5 % long on a straight line: the error grows linearly to 5 % of the distance."""
    path = tmp_path / "line.mcap"
    with Recorder(path, source={}) as rec:
        for k in range(101):
            t = 10**9 + k * 10**8
            rec.write("/ground_truth/pose", GroundTruthPose(t, 3.0 + 0.1 * k, -2.0, 0.0))
            rec.write("/odom", OdometryPose(t, 100.0, 50.0 + 0.105 * k, np.pi / 2))  # other frame, 5 % long
    result = run_recording(path, "odometry", tmp_path / "run")
    m = result.metrics
    assert m["robot_final_error_m"] == pytest.approx(0.5, abs=1e-9)
    errors = 0.005 * np.arange(101)
    assert m["ape_rmse_m"] == pytest.approx(np.sqrt(np.mean(errors**2)), abs=1e-9)
    assert m["ape_rot_rmse_deg"] == pytest.approx(0.0, abs=1e-9)
    assert m["path_length_m"] == pytest.approx(10.5, abs=1e-9) and m["poses_scored"] == 101


def test_start_pose_interpolates_ground_truth(tmp_path: Path) -> None:
    """The estimate starts at the ground truth interpolated at the first odometry time."""
    path = tmp_path / "r.mcap"
    with Recorder(path, source={}) as rec:
        rec.write("/ground_truth/pose", GroundTruthPose(100, 0.0, 0.0, 0.0))
        rec.write("/ground_truth/pose", GroundTruthPose(200, 2.0, 4.0, 0.2))
        rec.write("/odom", OdometryPose(150, 9.0, 9.0, 1.0))
    t0, pose = start_pose(RecordingReader(path), "/odom", None, None)
    assert t0 == 150 and np.allclose(pose, [1.0, 2.0, 0.1])


def test_memory_observer_sees_every_step(tiny_recording: Path) -> None:
    """Replay sets step and sensor time before each message; the pipeline logs robot and trajectories."""
    reader = RecordingReader(tiny_recording)
    cls = get_pipeline("odometry")
    obs = MemoryObserver()
    stats = replay(reader, cls, resolve_config(cls), obs, seed=0, log=lambda s: None)
    robots = [(s, t) for s, t, p, _ in obs.events if p == "world/robot"]
    assert len(robots) == 100 and robots[0][1] == 1_000_000_000
    assert stats.messages == 200
    assert {"world/trajectory/estimate", "world/trajectory/truth", "metrics/robot_position_error_m"} <= obs.paths()


def test_two_runs_are_identical(tiny_recording: Path, tmp_path: Path) -> None:
    """Same recording, config and seed: byte-identical metrics.json and equal .rrd content."""
    a = run_recording(tiny_recording, "odometry", tmp_path / "a", seed=3)
    b = run_recording(tiny_recording, "odometry", tmp_path / "b", seed=3)
    assert (a.run_dir / "metrics.json").read_bytes() == (b.run_dir / "metrics.json").read_bytes()
    proc = subprocess.run([rerun_cli(), "rrd", "compare", str(a.run_dir / "run.rrd"), str(b.run_dir / "run.rrd")],
                          capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr[-2000:]


def test_run_directory_contents(tiny_recording: Path, tmp_path: Path) -> None:
    """A run has run.rrd, metrics.json, manifest.json, log.txt and its trajectories; no temporary files remain."""
    res = run_recording(tiny_recording, "odometry", tmp_path / "run", seed=5, config={})
    names = sorted(p.name for p in res.run_dir.iterdir())
    assert names == ["log.txt", "manifest.json", "metrics.json", "run.rrd", "trajectory.tum", "truth.tum"]
    man = json.loads((res.run_dir / "manifest.json").read_text())
    assert man["status"] == "succeeded" and man["seed"] == 5 and man["pipeline"] == "odometry"
    assert len(man["recording"]["sha256"]) == 64 and len(man["config_hash"]) == 64
    assert {"rerun-sdk", "numpy", "scipy", "opencv-contrib-python-headless"} <= set(man["libraries"])
    assert {"wall_s", "cpu_s", "replay_s", "started_at"} <= set(man["timings"])
    metrics = json.loads((res.run_dir / "metrics.json").read_text())
    assert metrics["metrics"]["ape_rmse_m"]["better"] == "lower"


def test_bad_input_writes_nothing_or_a_failed_manifest(tiny_recording: Path, tmp_path: Path) -> None:
    """Unknown pipeline or key: nothing written. Missing topic: a failed manifest, no metrics, no rrd."""
    with pytest.raises(ReplayError, match="unknown pipeline 'nope'"):
        run_recording(tiny_recording, "nope", tmp_path / "r1")
    with pytest.raises(ReplayError, match="unknown config key 'speed'"):
        run_recording(tiny_recording, "odometry", tmp_path / "r2", config={"speed": "1"})
    assert not (tmp_path / "r1").exists() and not (tmp_path / "r2").exists()
    gt_only = tmp_path / "gt.mcap"
    with Recorder(gt_only, source={}) as rec:
        rec.write("/ground_truth/pose", GroundTruthPose(1, 0, 0, 0))
    with pytest.raises(ReplayError, match="has no /odom topic"):
        run_recording(gt_only, "odometry", tmp_path / "r3")
    assert sorted(p.name for p in (tmp_path / "r3").iterdir()) == ["log.txt", "manifest.json"]
    man = json.loads((tmp_path / "r3" / "manifest.json").read_text())
    assert man["status"] == "failed" and "has no /odom topic" in man["error"]
    retry = run_recording(tiny_recording, "odometry", tmp_path / "r3")  # the fix: a recording with /odom
    assert retry.status == "succeeded"
    assert json.loads((tmp_path / "r3" / "manifest.json").read_text())["status"] == "succeeded"
    with pytest.raises(ReplayError, match="already exists and holds a run with status 'succeeded'"):
        run_recording(tiny_recording, "odometry", tmp_path / "r3")


def test_failed_run_never_blocks_its_retry(tiny_recording: Path, tmp_path: Path) -> None:
    """A failed run's directory is cleared and reused; what it did not write is never deleted."""
    gt_only = tmp_path / "gt.mcap"
    with Recorder(gt_only, source={}) as rec:
        rec.write("/ground_truth/pose", GroundTruthPose(1, 0, 0, 0))
    out = tmp_path / "a" / "b" / "c"  # parents are created
    with pytest.raises(ReplayError, match="has no /odom topic"):
        run_recording(gt_only, "odometry", out)
    (out / ".run.rrd.partial").write_bytes(b"left by a crash")  # a failed run's temporary file is its own
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["status"] == "failed"
    res = run_recording(tiny_recording, "odometry", out)
    assert res.status == "succeeded" and not (out / ".run.rrd.partial").exists()
    assert {p.name for p in out.iterdir()} == {"run.rrd", "metrics.json", "manifest.json", "log.txt", "trajectory.tum",
                                               "truth.tum"}
    assert "has no /odom topic" not in (out / "log.txt").read_text()
    # a failed run beside a user's file: the file is not the run's to delete
    other = tmp_path / "other"
    with pytest.raises(ReplayError, match="has no /odom topic"):
        run_recording(gt_only, "odometry", other)
    (other / "notes.txt").write_text("mine")
    with pytest.raises(ReplayError, match=r"failed run and files it did not write \(notes.txt\)"):
        run_recording(tiny_recording, "odometry", other)
    assert (other / "notes.txt").read_text() == "mine" and (other / "manifest.json").exists()


def test_run_dir_that_is_not_a_failed_run_is_refused(tiny_recording: Path, tmp_path: Path) -> None:
    """Not empty and no manifest, an unfinished run, or a file: refused, and nothing in it is touched."""
    user = tmp_path / "user"
    user.mkdir()
    (user / "data.csv").write_text("1,2")
    with pytest.raises(ReplayError, match="already exists and holds files that are not a run"):
        run_recording(tiny_recording, "odometry", user)
    assert (user / "data.csv").exists()
    killed = tmp_path / "killed"
    killed.mkdir()
    (killed / ".run.rrd.partial").write_bytes(b"")
    with pytest.raises(ReplayError, match="unfinished run"):
        run_recording(tiny_recording, "odometry", killed)
    bad = tmp_path / "bad"
    bad.mkdir()
    (bad / "manifest.json").write_text("{not json")
    with pytest.raises(ReplayError, match="files that are not a run"):
        run_recording(tiny_recording, "odometry", bad)
    a_file = tmp_path / "file"
    a_file.write_text("x")
    with pytest.raises(ReplayError, match="is not a directory"):
        run_recording(tiny_recording, "odometry", a_file)
    (tmp_path / "empty").mkdir()
    assert run_recording(tiny_recording, "odometry", tmp_path / "empty").status == "succeeded"
    blocker = tmp_path / "blocker"
    blocker.write_text("x")
    with pytest.raises(ReplayError, match="cannot create the run directory"):
        run_recording(tiny_recording, "odometry", blocker / "sub" / "run")


def test_window_and_no_ground_truth(tmp_path: Path) -> None:
    """A time window limits the replay; without ground truth the accuracy metrics are absent."""
    path = write_tiny_recording(tmp_path / "t.mcap")
    res = run_recording(path, "odometry", tmp_path / "w", start_ns=1_500_000_000, end_ns=2_000_000_000)
    assert res.metrics["poses_scored"] == 5
    no_gt = tmp_path / "nogt.mcap"
    with Recorder(no_gt, source={}) as rec:
        for k in range(3):
            rec.write("/odom", OdometryPose(k + 1, k, 0, 0))
    res = run_recording(no_gt, "odometry", tmp_path / "n")
    doc = json.loads((res.run_dir / "metrics.json").read_text())
    assert "ape_rmse_m" not in doc["metrics"] and doc["metrics"]["path_length_m"]["value"] == 2.0


def test_ros2_bag_replayed(tmp_path: Path) -> None:
    """A ROS 2 bag written in the test replays through odometry: 10 % long odometry, known error."""
    from ros2_fixtures import write_ros2_bag

    bag = write_ros2_bag(tmp_path / "bag")
    res = run_recording(bag, "odometry", tmp_path / "run")
    assert res.metrics["robot_final_error_m"] == pytest.approx(0.19, abs=1e-9)
    assert res.metrics["poses_scored"] == 20
    man = json.loads((res.run_dir / "manifest.json").read_text())
    assert man["recording"]["sha256"] and man["status"] == "succeeded"


@pytest.mark.parametrize("failing", ["metrics.json", "manifest.json"])
def test_full_disk_fails_the_run_cleanly(tiny_recording: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                         failing: str) -> None:
    """ENOSPC while a run writes its files: a ReplayError saying so, and nothing left that looks finished."""
    import errno

    import slamreplay.replay.runs.run as run_module

    real = run_module.atomic_write

    def full(path: Path, data: str | bytes) -> None:
        if path.name == failing:
            raise OSError(errno.ENOSPC, "No space left on device")
        real(path, data)

    monkeypatch.setattr(run_module, "atomic_write", full)
    out = tmp_path / "run"
    with pytest.raises(ReplayError, match=r"no space left on the device while writing .*run: the run did not finish"):
        run_recording(tiny_recording, "odometry", out)
    left = sorted(p.name for p in out.iterdir())
    assert "run.rrd" not in left and "metrics.json" not in left and not any(n.startswith(".") for n in left)
    if failing == "metrics.json":
        manifest = json.loads((out / "manifest.json").read_text())
        assert manifest["status"] == "failed" and "no space left" in manifest["error"]
    else:
        assert left == ["log.txt"]


def test_the_log_is_followed_live_and_ends_whole(tmp_path: Path) -> None:
    """While a run replays, its log lines are in the live copy (the service's job page tails it); at the end
    log.txt holds them all and the live copy is gone."""
    from slamreplay.replay.runs.run import LIVE_LOG

    rec = write_tiny_recording(tmp_path / "r.mcap")
    seen: list[str] = []

    def progress(done: int, total: int) -> None:
        live = tmp_path / "run" / LIVE_LOG
        if live.exists() and not seen:
            seen.append(live.read_text())

    run_recording(rec, "odometry", tmp_path / "run", progress=progress)
    assert seen and "odometry on r.mcap" in seen[0]
    assert not (tmp_path / "run" / LIVE_LOG).exists()
    log = (tmp_path / "run" / "log.txt").read_text()
    assert log.startswith(seen[0].splitlines()[0]) and "finished:" in log


def test_ctrl_c_is_recorded_as_interrupted(tiny_recording: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
                                           ) -> None:
    """The user's Ctrl-C mid-run: manifest status interrupted (no 'internal error', no traceback in the log),
    nothing finished-looking left, and the same --out works again."""
    from slamreplay.replay.pipelines.odometry import OdometryPipeline

    def interrupt(self: object, env: object) -> None:
        raise KeyboardInterrupt

    with monkeypatch.context() as m:
        m.setattr(OdometryPipeline, "step", interrupt)
        with pytest.raises(KeyboardInterrupt):
            run_recording(tiny_recording, "odometry", tmp_path / "r")
    man = json.loads((tmp_path / "r" / "manifest.json").read_text())
    assert (man["status"], man["error"]) == ("interrupted", "interrupted by the user (Ctrl-C)")
    log = (tmp_path / "r" / "log.txt").read_text()
    assert "INTERRUPTED: by the user (Ctrl-C)" in log and "Traceback" not in log and "internal error" not in log
    assert sorted(p.name for p in (tmp_path / "r").iterdir()) == ["log.txt", "manifest.json"]
    assert run_recording(tiny_recording, "odometry", tmp_path / "r").status == "succeeded"
