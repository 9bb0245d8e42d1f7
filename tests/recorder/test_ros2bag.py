"""ROS 2 bags of both storages, written with rosbags, imported and checked against what was written."""

from __future__ import annotations

import math
import sqlite3
from pathlib import Path

import numpy as np
import pytest
from ros2bag_fixtures import LASER_X_M, BagTruth, write_bag

from slamreplay.api.cli.command import main
from slamreplay.recorder.errors import RecorderError
from slamreplay.recorder.importers.ros2bag import ImportSummary, import_ros2_bag, plan_bag, sensor_model
from slamreplay.recorder.messages import (
    CameraCalibration,
    CameraImage,
    GroundTruthPose,
    ImuYawRate,
    OdometryPose,
    RangeBearingScan,
)
from slamreplay.replay.engine.reader import RecordingReader
from slamreplay.replay.runs.run import run_recording

STORAGES = ("sqlite3", "mcap")


@pytest.fixture(scope="module", params=STORAGES)
def imported(request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory
             ) -> tuple[str, Path, Path, BagTruth, ImportSummary]:
    """A 40 s bag in each storage and its import with ground truth from tf (map frame)."""
    base = tmp_path_factory.mktemp(f"bag_{request.param}")
    truth = write_bag(base / "bag", request.param, seconds=40.0)
    summary = import_ros2_bag(base / "bag", base / "rec.mcap", ground_truth_frame="map")
    return request.param, base / "bag", base / "rec.mcap", truth, summary


def _read(path: Path, topic: str) -> list:  # type: ignore[type-arg]
    return [e.msg for e in RecordingReader(path).messages([topic])]


def _wrap(a: np.ndarray) -> np.ndarray:
    return (a + np.pi) % (2 * np.pi) - np.pi


def test_import_matches_written(imported: tuple[str, Path, Path, BagTruth, ImportSummary]) -> None:
    """Odometry, tf ground truth, IMU, images and camera info come back as written."""
    storage, _, rec, truth, summary = imported
    assert summary.plan.storage == storage
    n = len(truth.stamps_ns)
    assert summary.counts == {"/odom": n, "/ground_truth/pose": n, "/imu/yaw_rate": n,
                              "/landmarks/range_bearing": len(truth.scan_stamps_ns),
                              "/camera/image": 8, "/camera/calibration": 8}
    odom = _read(rec, "/odom")
    assert all(isinstance(m, OdometryPose) for m in odom)
    got = np.array([m.xy_yaw for m in odom])
    assert np.array([m.stamp_ns for m in odom]).tolist() == truth.stamps_ns.tolist()
    np.testing.assert_allclose(got[:, :2], truth.odom[:, :2], atol=1e-9)
    np.testing.assert_allclose(_wrap(got[:, 2] - truth.odom[:, 2]), 0, atol=1e-9)
    gt = _read(rec, "/ground_truth/pose")  # composed map -> odom -> base_link
    assert all(isinstance(m, GroundTruthPose) for m in gt)
    got = np.array([m.xy_yaw for m in gt])
    np.testing.assert_allclose(got[:, :2], truth.truth[:, :2], atol=1e-6)
    np.testing.assert_allclose(_wrap(got[:, 2] - truth.truth[:, 2]), 0, atol=1e-6)
    imu = _read(rec, "/imu/yaw_rate")
    assert isinstance(imu[0], ImuYawRate) and imu[0].yaw_rate_sigma_radps == pytest.approx(0.002)
    np.testing.assert_allclose([m.yaw_rate_radps for m in imu], truth.yaw_rate, atol=1e-12)
    images = _read(rec, "/camera/image")
    assert isinstance(images[0], CameraImage) and images[0].compression == "png"
    np.testing.assert_array_equal(images[0].pixels, truth.image)
    cal = _read(rec, "/camera/calibration")[0]
    assert isinstance(cal, CameraCalibration) and (cal.width_px, cal.height_px) == (64, 48)
    np.testing.assert_allclose(cal.K, truth.K)


def test_scan_poles_land_on_the_true_poles(imported: tuple[str, Path, Path, BagTruth, ImportSummary]) -> None:
    """Every extracted pole, placed through the true pose, lies on a true pole centre; most visible poles are found."""
    _, _, rec, truth, _ = imported
    scans = _read(rec, "/landmarks/range_bearing")
    assert all(isinstance(s, RangeBearingScan) and np.all(s.landmark_ids == -1) for s in scans)
    index = {int(s): k for k, s in enumerate(truth.stamps_ns)}
    errors, found, visible = [], 0, 0
    floor = sensor_model()
    for s in scans:
        x, y, yaw = truth.truth[index[s.stamp_ns]]
        wx = x + s.ranges_m * np.cos(yaw + s.bearings_rad)
        wy = y + s.ranges_m * np.sin(yaw + s.bearings_rad)
        d = np.hypot(wx[:, None] - truth.poles[None, :, 0], wy[:, None] - truth.poles[None, :, 1])
        errors.extend(d.min(axis=1).tolist())
        found += len(s)
        lx, ly = x + LASER_X_M * math.cos(yaw), y + LASER_X_M * math.sin(yaw)
        rel = np.arctan2(truth.poles[:, 1] - ly, truth.poles[:, 0] - lx) - yaw
        dist = np.hypot(truth.poles[:, 0] - lx, truth.poles[:, 1] - ly)
        visible += int(np.sum((np.abs(_wrap(rel)) < 2.2) & (dist < 12.0)))
        assert floor["range_sigma_m"] <= s.range_sigma_m < 0.2
        assert floor["bearing_sigma_rad"] <= s.bearing_sigma_rad < 0.05
    # the laser's 0.3 m mounting is applied: without it the errors are about 0.3 m; the worst few are poles
    # standing close behind one another, fitted as one
    assert np.median(errors) < 0.03 and np.quantile(errors, 0.95) < 0.08 and max(errors) < 0.5
    assert found >= 0.8 * visible  # poles within 12 m, not hidden behind others, are nearly all found


def test_imports_and_replays_through_odometry_scored_against_tf(
        imported: tuple[str, Path, Path, BagTruth, ImportSummary], tmp_path: Path) -> None:
    """The odometry pipeline's ATE equals the odometry's error against the tf truth, computed here."""
    _, _, rec, truth, _ = imported
    res = run_recording(rec, "odometry", tmp_path / "run")
    # the pipeline scores in the world frame through the first true pose (landmark_slam.py's convention)
    c, s = math.cos(truth.truth[0, 2]), math.sin(truth.truth[0, 2])
    o = truth.odom[:, :2] - truth.odom[0, :2]
    x0 = truth.truth[0, :2] + o @ np.array([[c, s], [-s, c]])
    ate = float(np.sqrt(np.mean(np.sum((x0 - truth.truth[:, :2]) ** 2, axis=1))))
    assert res.metrics["poses_scored"] == len(truth.stamps_ns)
    assert res.metrics["ape_rmse_m"] == pytest.approx(ate, rel=1e-3)
    assert 1.0 < ate < 10.0


def test_laser_poles_through_dslam_beat_dead_reckoning(tmp_path: Path) -> None:
    """The scan's poles with unknown ids through D-SLAM: trajectory error well under dead reckoning's."""
    write_bag(tmp_path / "bag", "sqlite3", seed=3, seconds=30.0, scan_every=4,
              skip=("/camera/image_raw", "/camera/compressed"))
    import_ros2_bag(tmp_path / "bag", tmp_path / "rec.mcap", ground_truth_frame="map")
    dr = run_recording(tmp_path / "rec.mcap", "odometry", tmp_path / "dr").metrics["ape_rmse_m"]
    ds = run_recording(tmp_path / "rec.mcap", "dslam", tmp_path / "ds", config={"association": "unknown"}).metrics
    assert dr > 2.0
    assert 0.005 < ds["ape_rmse_m"] < 0.1 * dr
    assert ds["landmarks_mapped"] >= 20


def test_plan_lists_unknown_types_and_follows_topic_map(imported: tuple[str, Path, Path, BagTruth, ImportSummary]
                                                        ) -> None:
    """A custom type is listed and skipped; --topic-map picks the raw image instead of the compressed one."""
    _, bag, _, _, _ = imported
    plan = {t.topic: t for t in plan_bag(bag, {"/camera/image_raw": "/camera/image"}).topics}
    assert plan["/diagnostics_blob"].maps_to is None and "skipped" in plan["/diagnostics_blob"].note
    assert plan["/camera/image_raw"].maps_to == "/camera/image"
    assert plan["/camera/compressed"].maps_to is None
    assert plan["/tf"].maps_to is None  # /odom comes from the Odometry topic and no ground-truth frame was asked
    with pytest.raises(RecorderError, match="can become /camera/calibration"):
        plan_bag(bag, {"/camera/camera_info": "/odom"})
    with pytest.raises(RecorderError, match="does not hold"):
        plan_bag(bag, {"/nope": "/odom"})


def test_tf_gives_odometry_when_no_odometry_topic(tmp_path: Path) -> None:
    """Without an Odometry topic, /odom is the base frame's pose in the odom frame from /tf; a bag without stored
    definitions (rosbag2 v8) is read with the Humble type store."""
    truth = write_bag(tmp_path / "bag", "sqlite3", seconds=5.0, with_definitions=False,
                      skip=("/odom", "/diagnostics_blob"))
    db3 = next((tmp_path / "bag").glob("*.db3"))  # the storage file alone, without metadata.yaml
    summary = import_ros2_bag(db3, tmp_path / "rec.mcap")
    assert "/ground_truth/pose" not in summary.counts and summary.plan.storage == "sqlite3"
    got = np.array([m.xy_yaw for m in _read(tmp_path / "rec.mcap", "/odom")])
    np.testing.assert_allclose(got[:, :2], truth.odom[:, :2], atol=1e-9)


def _one_line_exit_2(argv: list[str], capsys: pytest.CaptureFixture[str], match: str) -> None:
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    # the error is one line; a progress line may come before it (the tf tree is known after the bag was read)
    problems = [line for line in err.splitlines() if not line.startswith("record ros2: ")]
    assert len(problems) == 1 and "Traceback" not in err, err
    assert match in problems[0], err


def test_bag_with_nothing_usable(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Only a custom type: one line naming what a pipeline needs, exit 2, no recording."""
    keep = ("/diagnostics_blob",)
    write_bag(tmp_path / "bag", "mcap", seconds=2.0,
              skip=tuple(t for t in ("/odom", "/tf", "/tf_static", "/imu", "/scan", "/camera/image_raw",
                                     "/camera/compressed", "/camera/camera_info") if t not in keep))
    _one_line_exit_2(["record", "ros2", str(tmp_path / "bag"), "--out", str(tmp_path / "r.mcap")], capsys,
                     "a pipeline needs odometry")
    assert not (tmp_path / "r.mcap").exists() and not (tmp_path / "r.mcap.partial").exists()


def test_corrupted_db3(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A .db3 with damaged bytes: one line, exit 2."""
    write_bag(tmp_path / "bag", "sqlite3", seconds=2.0)
    db3 = next((tmp_path / "bag").glob("*.db3"))
    data = bytearray(db3.read_bytes())
    data[0:100] = b"\x00" * 100  # the SQLite header
    broken = tmp_path / "broken.db3"
    broken.write_bytes(bytes(data))
    _one_line_exit_2(["record", "ros2", str(broken), "--out", str(tmp_path / "r.mcap")], capsys,
                     "broken.db3 is not a sqlite3 database")
    _one_line_exit_2(["inspect", str(broken)], capsys, "broken.db3 is not a sqlite3 database")
    assert not (tmp_path / "r.mcap").exists()
    with sqlite3.connect(db3) as con:  # the intact one still reads: the damage, not the file, was the cause
        assert con.execute("select count(*) from messages").fetchone()[0] > 0


def test_tf_tree_without_the_named_frame(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """--ground-truth-frame naming a frame /tf lacks: one line naming the frames there are, exit 2."""
    write_bag(tmp_path / "bag", "mcap", seconds=2.0)
    _one_line_exit_2(["record", "ros2", str(tmp_path / "bag"), "--out", str(tmp_path / "r.mcap"),
                      "--ground-truth-frame", "world"], capsys,
                     "no frame 'world' (frames: base_link, laser, map, odom)")
    assert not (tmp_path / "r.mcap").exists() and not (tmp_path / "r.mcap.partial").exists()


def test_missing_bag(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A path that does not exist: one line, exit 2."""
    _one_line_exit_2(["record", "ros2", str(tmp_path / "nope"), "--out", str(tmp_path / "r.mcap")], capsys,
                     "does not exist")


def test_inspect_bag_checks_the_frames_record_would_compose(imported: tuple[str, Path, Path, BagTruth, ImportSummary],
                                                            capsys: pytest.CaptureFixture[str]) -> None:
    """`inspect BAG` lists the tf tree and checks each frame option against it, as `record ros2` would use them."""
    _, bag, _, _, _ = imported
    assert main(["inspect", str(bag), "--ground-truth-frame", "map"]) == 0
    out = capsys.readouterr().out
    assert "map -> odom" in out and "odom -> base_link" in out and "base_link -> laser" in out
    assert "--ground-truth-frame map: found" in out and "--base-frame base_link: found" in out
    assert main(["inspect", str(bag), "--ground-truth-frame", "world", "--base-frame", "chassis", "--json"]) == 0
    doc = __import__("json").loads(capsys.readouterr().out)
    plan = doc.get("ros2_import", doc)  # an MCAP-storage bag is also inspected as MCAP: the plan is a part
    assert ["map", "odom"] in plan["tf_edges"]
    assert plan["frame_checks"]["--ground-truth-frame"].startswith("world: not in the tf tree read (frames: "
                                                                     "base_link, laser, map, odom)")
    assert plan["frame_checks"]["--base-frame"].startswith("chassis: not in the tf tree")


def test_inspect_recording_refuses_bag_options(imported: tuple[str, Path, Path, BagTruth, ImportSummary],
                                               capsys: pytest.CaptureFixture[str]) -> None:
    """A frame option given for a slamreplay recording cannot apply: one line, exit 2 (not silently ignored)."""
    _, _, rec, _, _ = imported
    _one_line_exit_2(["inspect", str(rec), "--base-frame", "chassis"], capsys,
                     "--base-frame apply to ROS 2 bags, and rec.mcap is a slamreplay recording")


def test_record_sim_ros2_bag_writes_a_bag_record_ros2_reads(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """`record sim-ros2-bag` writes a whole bag folder (storage file named after it, nothing else left beside it)
    that `record ros2` imports, and refuses a folder that exists."""
    bag = tmp_path / "bag"
    assert main(["record", "sim-ros2-bag", "--out", str(bag), "--duration-s", "5", "-q"]) == 0
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bag"]
    assert sorted(p.name for p in bag.iterdir()) == ["bag.db3", "metadata.yaml"]
    assert main(["record", "ros2", str(bag), "--ground-truth-frame", "map", "--out", str(tmp_path / "r.mcap"),
                 "-q"]) == 0
    odom = _read(tmp_path / "r.mcap", "/odom")
    assert len(odom) == 50
    capsys.readouterr()
    assert main(["record", "sim-ros2-bag", "--out", str(bag), "-q"]) == 2
    assert "exists" in capsys.readouterr().err
    assert main(["record", "sim-ros2-bag", "--out", str(tmp_path / "m"), "--storage", "mcap", "-q"]) == 0
    assert [p.suffix for p in (tmp_path / "m").iterdir() if p.name != "metadata.yaml"] == [".mcap"]
