"""Tests for the MRCLAM importer (recorder/importers/mrclam.py)."""

from __future__ import annotations

import json
import math
import os
import shutil
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader
from numpy.typing import NDArray
from readback import by_topic, poses, read_recording

from slamreplay.recorder.errors import RecorderError
from slamreplay.recorder.importers import import_mrclam
from slamreplay.recorder.messages import (
    TOPIC_GROUND_TRUTH_LANDMARKS,
    TOPIC_GROUND_TRUTH_POSE,
    TOPIC_ODOM,
    TOPIC_RANGE_BEARING,
    LandmarkMap,
    Message,
    RangeBearingScan,
)
from slamreplay.recorder.writer import partial_path

HEADER = "# UTIAS Multi-Robot Cooperative Localization and Mapping Dataset\n# test\n# format\n# columns\n"

def interpolate(tq: NDArray[np.int64], t: NDArray[np.int64], p: NDArray[np.float64]) -> NDArray[np.float64]:
    """Poses (m, 3) linearly interpolated at tq from poses p (n, 3) at t (n,)."""
    ref = t[0]
    tq_s, t_s = (tq - ref) / 1e9, (t - ref) / 1e9
    return np.column_stack([np.interp(tq_s, t_s, p[:, 0]), np.interp(tq_s, t_s, p[:, 1]),
                            np.interp(tq_s, t_s, np.unwrap(p[:, 2]))])


@pytest.fixture(scope="module")
def robot1(tmp_path_factory: pytest.TempPathFactory) -> list[tuple[str, int, Message]]:
    """Robot 1 of MRCLAM Dataset6, imported once and read back."""
    # Module scope cannot use the function-scoped `shared_data` fixture; same lookup as tests/conftest.py.
    root = Path(os.environ.get("SLAMREPLAY_DATA", Path(__file__).resolve().parents[3] / "shared" / "data"))
    if not (root / "mrclam-dataset6").is_dir():
        pytest.skip(f"MRCLAM Dataset6 not found under {root} (set SLAMREPLAY_DATA)")
    out = tmp_path_factory.mktemp("mrclam") / "robot1.mcap"
    summary = import_mrclam(root / "mrclam-dataset6", 1, out)
    assert summary.measurements_kept == 1534
    assert summary.robot_sightings_dropped == 407
    assert summary.unknown_barcodes_dropped == 1
    assert summary.landmarks == 15
    return read_recording(out)


def test_robot1_counts(robot1: list[tuple[str, int, Message]]) -> None:
    """Row counts of the README: 61785 odometry, 49241 ground truth, 1534 landmark measurements, 15 landmarks."""
    assert len(poses(robot1, TOPIC_ODOM)[0]) == 61785
    assert len(poses(robot1, TOPIC_GROUND_TRUTH_POSE)[0]) == 49241
    scans = by_topic(robot1, TOPIC_RANGE_BEARING, RangeBearingScan)
    assert sum(len(s) for s in scans) == 1534
    ids = np.concatenate([s.landmark_ids for s in scans])
    assert set(ids.tolist()) == set(range(6, 21))
    assert all(s.range_sigma_m == 0.0 and s.bearing_sigma_rad == 0.0 for s in scans)
    (lm,) = by_topic(robot1, TOPIC_GROUND_TRUTH_LANDMARKS, LandmarkMap)
    np.testing.assert_array_equal(lm.landmark_ids, np.arange(6, 21))
    np.testing.assert_allclose(lm.positions_m[0], [0.58831396, -4.28264845])


def test_robot1_times(robot1: list[tuple[str, int, Message]]) -> None:
    """Times are exact int ns on whole milliseconds, nondecreasing; the map comes first at the earliest time."""
    assert robot1[0][0] == TOPIC_GROUND_TRUTH_LANDMARKS
    assert robot1[0][1] == 1_248_444_175_103_000_000  # first ground-truth row
    log_times = [lt for _, lt, _ in robot1]
    assert log_times == sorted(log_times)
    assert all(isinstance(m.stamp_ns, int) and m.stamp_ns == lt and lt % 1_000_000 == 0 for _, lt, m in robot1)
    odom_t, odom = poses(robot1, TOPIC_ODOM)
    assert odom_t[0] == 1_248_444_187_156_000_000 and odom_t[-1] == 1_248_445_075_103_000_000
    np.testing.assert_array_equal(odom[0], [0.0, 0.0, 0.0])


def test_robot1_dead_reckoning_matches_readme(robot1: list[tuple[str, int, Message]]) -> None:
    """/odom composed onto the true start pose gives the README's errors: RMSE 2.62 m, final 8.34 m."""
    gt_t, gt = poses(robot1, TOPIC_GROUND_TRUTH_POSE)
    odom_t, odom = poses(robot1, TOPIC_ODOM)
    start = interpolate(odom_t[:1], gt_t, gt)[0]
    c, s = math.cos(start[2]), math.sin(start[2])
    dr = np.column_stack([start[0] + c * odom[:, 0] - s * odom[:, 1], start[1] + s * odom[:, 0] + c * odom[:, 1]])
    within = odom_t <= gt_t[-1]  # ground truth ends ~128 s before the odometry
    err = np.hypot(*(dr[within] - interpolate(odom_t[within], gt_t, gt)[:, :2]).T)
    rmse = float(np.sqrt(np.mean(err**2)))
    print(f"robot 1 dead reckoning: RMSE {rmse:.3f} m, final {err[-1]:.3f} m, max {err.max():.3f} m")
    assert rmse == pytest.approx(2.62, abs=0.05)
    assert err[-1] == pytest.approx(8.34, abs=0.05)


def test_robot1_measurements_agree_with_ground_truth(robot1: list[tuple[str, int, Message]]) -> None:
    """Median range and bearing residuals against ground truth are about the README's (+0.038 m, -0.0003 rad)."""
    gt_t, gt = poses(robot1, TOPIC_GROUND_TRUTH_POSE)
    (lm,) = by_topic(robot1, TOPIC_GROUND_TRUTH_LANDMARKS, LandmarkMap)
    where = dict(zip(lm.landmark_ids.tolist(), lm.positions_m, strict=True))
    scans = [s for s in by_topic(robot1, TOPIC_RANGE_BEARING, RangeBearingScan) if s.stamp_ns <= gt_t[-1]]
    at = interpolate(np.array([s.stamp_ns for s in scans]), gt_t, gt)
    dr, db = [], []
    for scan, p in zip(scans, at, strict=True):
        q = np.array([where[i] for i in scan.landmark_ids.tolist()]) - p[:2]
        dr.append(scan.ranges_m - np.hypot(q[:, 0], q[:, 1]))
        db.append(np.angle(np.exp(1j * (scan.bearings_rad - np.arctan2(q[:, 1], q[:, 0]) + p[2]))))
    assert np.median(np.concatenate(dr)) == pytest.approx(0.038, abs=0.01)
    assert np.median(np.concatenate(db)) == pytest.approx(0.0, abs=0.005)


def write_dataset(root: Path, *, odometry: str, measurement: str, groundtruth: str) -> Path:
    """A tiny MRCLAM-format folder with robot 1 only: barcodes 5 (robot 1), 63 (landmark 6), 81 (landmark 7)."""
    root.mkdir()
    (root / "Barcodes.dat").write_text(HEADER + "  1 \t 5\n  6 \t 63\n  7 \t 81\n")
    (root / "Landmark_Groundtruth.dat").write_text(HEADER + "6 1.0 2.0 0.0 0.0\n7 -1.0 0.5 0.0 0.0\n")
    (root / "Robot1_Odometry.dat").write_text(HEADER + odometry)
    (root / "Robot1_Measurement.dat").write_text(HEADER + measurement)
    (root / "Robot1_Groundtruth.dat").write_text(HEADER + groundtruth)
    return root


def test_tiny_dataset(tmp_path: Path) -> None:
    """Euler integration, repeated stamps, barcode mapping, grouping by stamp and exact ms -> ns on a known input."""
    data = write_dataset(
        tmp_path / "d",
        odometry="100.000 1.0 0.0\n100.500 1.0 0.0\n100.500 0.0 1.0\n101.000 0.5 0.0\n102.999 0.0 0.0\n",
        measurement="100.000 63 1.5 0.1\n100.000 5 2.0 0.2\n100.000 63 1.6 0.15\n100.500 99 3.0 0.0\n"
                    "100.600 81 2.5 -0.3\n100.600 63 1.0 0.3\n",
        groundtruth="99.999 0.0 0.0 0.0\n103.000 1.0 0.0 0.0\n",
    )
    calls: list[tuple[int, int]] = []
    summary = import_mrclam(data, 1, tmp_path / "r.mcap", progress=lambda d, t: calls.append((d, t)))
    msgs = read_recording(tmp_path / "r.mcap")
    assert (summary.measurements_kept, summary.robot_sightings_dropped, summary.unknown_barcodes_dropped) == (4, 1, 1)
    assert calls[-1] == (summary.messages, summary.messages) == (len(msgs), len(msgs))
    assert [t for t, _, _ in msgs[:2]] == [TOPIC_GROUND_TRUTH_LANDMARKS, TOPIC_GROUND_TRUTH_POSE]
    assert msgs[0][1] == 99_999_000_000
    odom_t, odom = poses(msgs, TOPIC_ODOM)
    np.testing.assert_array_equal(odom_t, [100_000_000_000, 100_500_000_000, 101_000_000_000, 102_999_000_000])
    # 0.5 s at 1 m/s; the repeated stamp adds nothing; then 0.5 s turning at 1 rad/s in place; then 1.999 s at 0.5 m/s
    expected = np.array([[0, 0, 0], [0.5, 0, 0], [0.5, 0, 0.5],
                         [0.5 + 0.9995 * math.cos(0.5), 0.9995 * math.sin(0.5), 0.5]], dtype=np.float64)
    np.testing.assert_allclose(odom, expected, atol=1e-12)
    scans = by_topic(msgs, TOPIC_RANGE_BEARING, RangeBearingScan)
    assert [s.stamp_ns for s in scans] == [100_000_000_000, 100_600_000_000]
    first, second = scans
    np.testing.assert_array_equal(first.landmark_ids, [6, 6])
    np.testing.assert_array_equal(first.ranges_m, [1.5, 1.6])
    np.testing.assert_array_equal(second.landmark_ids, [7, 6])
    np.testing.assert_array_equal(second.bearings_rad, [-0.3, 0.3])
    with open(tmp_path / "r.mcap", "rb") as f:
        meta = next(m for m in make_reader(f).iter_metadata() if m.name == "slamreplay.recording").metadata
    # four odometry samples and four measurements are too few to measure noise: the model says so, states nothing
    model = json.loads(meta["sensor_model"])
    assert set(model) == {"source"} and "too little motion" in model["source"] and "too few" in model["source"]
    assert json.loads(meta["source"]) == {"importer": "mrclam", "dataset": "MRCLAM Dataset6", "robot": 1}


GOOD = {"odometry": "100.0 1.0 0.0\n101.0 1.0 0.0\n", "measurement": "100.5 63 1.5 0.1\n",
        "groundtruth": "100.0 0.0 0.0 0.0\n101.0 1.0 0.0 0.0\n"}


def test_missing_folder_and_bad_robot(tmp_path: Path) -> None:
    """A missing folder and robot numbers outside 1..5 are refused with a message saying what to pass."""
    with pytest.raises(RecorderError, match="does not exist"):
        import_mrclam(tmp_path / "nowhere", 1, tmp_path / "r.mcap")
    data = write_dataset(tmp_path / "d", **GOOD)
    for robot in (0, 9, True):
        with pytest.raises(RecorderError, match="robot must be one of 1..5"):
            import_mrclam(data, robot, tmp_path / "r.mcap")
    with pytest.raises(RecorderError, match=r"Robot2_Odometry\.dat is missing"):
        import_mrclam(data, 2, tmp_path / "r.mcap")
    assert not (tmp_path / "r.mcap").exists() and not partial_path(tmp_path / "r.mcap").exists()


@pytest.mark.parametrize("name", ["Barcodes.dat", "Landmark_Groundtruth.dat", "Robot1_Measurement.dat",
                                  "Robot1_Groundtruth.dat"])
def test_missing_file(tmp_path: Path, name: str) -> None:
    """Each missing file is named."""
    data = write_dataset(tmp_path / "d", **GOOD)
    (data / name).unlink()
    with pytest.raises(RecorderError, match=rf"{name} is missing"):
        import_mrclam(data, 1, tmp_path / "r.mcap")


@pytest.mark.parametrize(("field", "text", "match"), [
    ("odometry", "100.0 1.0\n", r"Robot1_Odometry\.dat:5: expected 3 columns"),
    ("odometry", "100.0 1.0 abc\n", r"Robot1_Odometry\.dat:5: column 3 \(angular velocity"),
    ("odometry", "100.0 1.0 nan\n", r"Robot1_Odometry\.dat:5: column 3"),
    ("odometry", "101.0 1.0 0.0\n100.0 1.0 0.0\n", r"Robot1_Odometry\.dat:6: time goes backwards"),
    ("measurement", "100.5 6x3 1.5 0.1\n", r"Robot1_Measurement\.dat:5: column 2 \(barcode\)"),
    ("measurement", "100.5 63 -1.5 0.1\n", r"Robot1_Measurement\.dat:5: column 3 \(range"),
    ("groundtruth", "", r"Robot1_Groundtruth\.dat holds no data rows"),
])
def test_malformed_lines(tmp_path: Path, field: str, text: str, match: str) -> None:
    """A malformed line is reported by file and line number, and no recording is left behind."""
    data = write_dataset(tmp_path / "d", **{**GOOD, field: text})
    out = tmp_path / "r.mcap"
    with pytest.raises(RecorderError, match=match):
        import_mrclam(data, 1, out)
    assert not out.exists() and not partial_path(out).exists()


def test_bad_line_in_copied_dataset(tmp_path: Path, shared_data: Path) -> None:
    """One bad line written into a copy of the real robot 1 files is named by file and line."""
    src = shared_data / "mrclam-dataset6"
    data = tmp_path / "copy"
    data.mkdir()
    for name in ("Barcodes.dat", "Landmark_Groundtruth.dat", "Robot1_Odometry.dat", "Robot1_Measurement.dat"):
        shutil.copy(src / name, data / name)
    lines = (src / "Robot1_Groundtruth.dat").read_text().splitlines(keepends=True)
    lines[1000] = "1248444190.000 \t 1.0 \t oops \t 0.0\n"
    (data / "Robot1_Groundtruth.dat").write_text("".join(lines))
    with pytest.raises(RecorderError, match=r"Robot1_Groundtruth\.dat:1001: column 3 \(y \[m\]\)"):
        import_mrclam(data, 1, tmp_path / "r.mcap")


def test_refuses_to_overwrite(tmp_path: Path) -> None:
    """An existing output file is never overwritten."""
    data = write_dataset(tmp_path / "d", **GOOD)
    out = tmp_path / "r.mcap"
    out.write_bytes(b"keep me")
    with pytest.raises(RecorderError, match="already exists"):
        import_mrclam(data, 1, out)
    assert out.read_bytes() == b"keep me"


def test_all_robots_in_one_recording(tmp_path: Path) -> None:
    """`--robot all`: each robot's topics under /robotN/, the map once, in one time order; `run --robot N` picks one."""
    from slamreplay.replay.errors import ReplayError
    from slamreplay.replay.runs.run import run_recording

    data = write_dataset(tmp_path / "d", odometry="100.000 1.0 0.0\n101.000 1.0 0.0\n102.000 0.0 0.0\n",
                         measurement="100.500 63 1.5 0.1\n", groundtruth="99.999 0.0 0.0 0.0\n103.000 2.0 0.0 0.0\n")
    for k in range(2, 6):  # the other four robots: robot k drives at k/10 m/s and sees landmark 7
        (data / f"Robot{k}_Odometry.dat").write_text(HEADER + f"100.000 {k / 10} 0.0\n102.000 0.0 0.0\n")
        (data / f"Robot{k}_Measurement.dat").write_text(HEADER + "101.000 81 2.0 0.2\n")
        (data / f"Robot{k}_Groundtruth.dat").write_text(HEADER + "99.000 0.0 0.0 0.0\n104.000 1.0 0.0 0.0\n")
    summary = import_mrclam(data, "all", tmp_path / "all.mcap")
    from slamreplay.replay.engine.pipeline import robot_topic_map
    from slamreplay.replay.engine.reader import RecordingReader

    info = RecordingReader(tmp_path / "all.mcap").info
    msgs = read_recording(tmp_path / "all.mcap")  # the map; each robot's topics below, read as that robot's
    for k in range(1, 6):
        mapping = robot_topic_map(info, str(k))
        msgs += [(e.topic if e.topic == TOPIC_GROUND_TRUTH_LANDMARKS else f"/robot{k}{e.topic}", e.log_time_ns, e.msg)
                 for e in RecordingReader(tmp_path / "all.mcap", mapping).messages(list(mapping.values()))]
    assert summary.robot == "all" and summary.messages == len(msgs) == 1 + 5 * 2 + (3 + 4 * 2) + 5
    topics = {t for t, _, _ in msgs}
    assert topics == {TOPIC_GROUND_TRUTH_LANDMARKS} | {f"/robot{k}{t}" for k in range(1, 6)
                                                       for t in (TOPIC_GROUND_TRUTH_POSE, TOPIC_ODOM,
                                                                 TOPIC_RANGE_BEARING)}
    stamps = [s for _, s, _ in msgs]
    assert msgs[0][0] == TOPIC_GROUND_TRUTH_LANDMARKS and stamps[0] == min(stamps) == 99_000_000_000
    _, odom3 = poses(msgs, "/robot3" + TOPIC_ODOM)
    np.testing.assert_allclose(odom3[-1], [0.6, 0.0, 0.0])  # 2 s at 0.3 m/s
    with pytest.raises(ReplayError, match=r"holds 5 robots \(topics under /robotN/: 1, 2, 3, 4, 5\); pipeline "
                                          r"odometry replays one: choose it with --robot N"):
        run_recording(tmp_path / "all.mcap", "odometry", tmp_path / "none")
    with pytest.raises(ReplayError, match="has no robot '7'"):
        run_recording(tmp_path / "all.mcap", "odometry", tmp_path / "seven", robot="7")
    res = run_recording(tmp_path / "all.mcap", "odometry", tmp_path / "r3", robot="3")
    assert res.manifest["recording"]["robot"] == "3"
    assert res.manifest["recording"]["topic_map"]["/robot3/odom"] == TOPIC_ODOM
    assert res.metrics["ape_rmse_m"] < 1.0  # robot 3's own ground truth, not robot 1's (2 m away at the end)
