"""Estimates made elsewhere, validated: increasing times, unit rotations, finite values, bounded input, coverage."""

from __future__ import annotations

import dataclasses
import math
import os
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from ros2_fixtures import POSE_STAMPED, _pose, _stamp

from slamreplay.replay.engine.pipeline import config_schema
from slamreplay.replay.errors import ReplayError
from slamreplay.replay.evaluation.evaluate import ROTATION_TOL, read_kitti, to_kitti
from slamreplay.replay.evaluation.metrics import time_coverage
from slamreplay.replay.runs.evaluate_run import EstimateConfig
from slamreplay.replay.tools.estimates import (
    MAX_ESTIMATE_BYTES,
    MAX_LINE_BYTES,
    MIN_COVERAGE,
    CoverageConfig,
    EstimateReplay,
    coverage_field,
    coverage_problem,
    read_kitti_ns,
    read_pose_topic,
    read_tum_ns,
    seconds_to_ns,
    text_lines,
)


def _tum(*rows: str) -> str:
    return "# timestamp x y z qx qy qz qw\n" + "\n".join(rows) + "\n"


def test_tum_times_must_increase_strictly() -> None:
    """An unsorted file is refused at the first line out of order (not sorted: evo keeps a file's order), a
    repeated time at its second line; line numbers count the comment."""
    with pytest.raises(ReplayError, match=r"est.tum, line 4: time 1.050000000 s is before line 3's \(1.100000000 s\): "
                                          r"times must increase"):
        read_tum_ns(_tum("1.0 0 0 0 0 0 0 1", "1.1 0 0 0 0 0 0 1", "1.05 0 0 0 0 0 0 1"), "est.tum")
    with pytest.raises(ReplayError, match=r"line 3: time 1.000000000 s repeats line 2's: two poses share a timestamp"):
        read_tum_ns(_tum("1 0 0 0 0 0 0 1", "1.0 1 0 0 0 0 0 1"))


def test_tum_quaternions_must_be_unit_within_the_tolerance() -> None:
    """An all-zero quaternion (evo: the identity, silently) and one off by more than ROTATION_TOL are refused; one
    rounded to 3 decimals is read, with the yaw of the normalised quaternion."""
    with pytest.raises(ReplayError, match=r"line 2: the quaternion's norm is 0, not 1 \(within 0.001\)"):
        read_tum_ns(_tum("1 0 0 0 0 0 0 0"))
    with pytest.raises(ReplayError, match=r"line 3: the quaternion's norm is 1.01, not 1"):
        read_tum_ns(_tum("1 0 0 0 0 0 0 1", "2 0 0 0 0 0 0 1.01"))
    yaw = 2.5
    rounded = [round(v, 3) for v in (math.sin(yaw / 2), math.cos(yaw / 2))]
    assert abs(math.hypot(*rounded) - 1) <= ROTATION_TOL
    _, poses = read_tum_ns(_tum(f"1 0 0 0 0 0 {rounded[0]} {rounded[1]}"))
    assert poses[0, 2] == pytest.approx(math.atan2(rounded[0], rounded[1]) * 2, abs=1e-12)
    _, scaled = read_tum_ns(_tum(f"1 0 0 0 0 0 {0.9995 * math.sin(0.4)} {0.9995 * math.cos(0.4)}"))
    assert scaled[0, 2] == pytest.approx(0.8, abs=1e-12)  # the yaw does not depend on the norm


def test_tum_values_finite_and_times_in_range() -> None:
    """A value that is not finite and a time beyond int64 nanoseconds name their line."""
    with pytest.raises(ReplayError, match=r"line 2: a value is not finite"):
        read_tum_ns(_tum("1 nan 0 0 0 0 0 1"))
    with pytest.raises(ReplayError, match=r"line 2: a value is not finite"):
        read_tum_ns(_tum("1 0 0 inf 0 0 0 1"))
    with pytest.raises(ReplayError, match=r"line 2: time 1e10 s is out of range"):
        read_tum_ns(_tum("1e10 0 0 0 0 0 0 1"))
    with pytest.raises(ReplayError, match=r"holds no pose"):
        read_tum_ns(_tum())


def test_the_first_bad_line_is_named_whatever_is_wrong_with_it() -> None:
    """Several problems: the error names the earliest line, whichever check refuses it."""
    rows = ["1 0 0 0 0 0 0 1", "2 0 0 0 0 0 0 1", "3 0 0 0 0 0 0 2", "2.5 0 0 0 0 0 0 1", "4 nan 0 0 0 0 0 1"]
    with pytest.raises(ReplayError, match=r"line 4: the quaternion's norm is 2"):
        read_tum_ns(_tum(*rows))
    rows[2] = "3 0 0 0 0 0 0 1"
    with pytest.raises(ReplayError, match=r"line 5: time 2.500000000 s is before line 4's"):
        read_tum_ns(_tum(*rows))
    rows[3] = "3.5 0 0 0 0 0 0 1"
    with pytest.raises(ReplayError, match=r"line 6: a value is not finite"):
        read_tum_ns(_tum(*rows))


@given(st.integers(0, 10**12), st.integers(0, 10**12), st.integers(0, 12))
def test_seconds_exact_on_both_paths(whole: int, frac: int, decimals: int) -> None:
    """The fast path of plain decimals and the general one (a sign forces it) give the same ns; an exponent too
    large to expand is out of range (or 0) at once, not after minutes."""
    text = f"{whole}.{str(frac).zfill(decimals)[:decimals]}" if decimals else str(whole)
    assert seconds_to_ns(text) == seconds_to_ns("+" + text)
    if decimals <= 9:
        assert seconds_to_ns(text) == whole * 10**9 + int((str(frac).zfill(decimals)[:decimals] + "0" * 9)[:9])


def test_huge_exponents_are_decided_without_expanding_them() -> None:
    """``1e999999999`` is out of range and ``1e-999999999`` is 0 ns, at once."""
    with pytest.raises(ValueError, match=r"time 1e999999999 s is out of range"):
        seconds_to_ns("1e999999999")
    assert seconds_to_ns("1e-999999999") == 0 and seconds_to_ns("0e999999999") == 0
    with pytest.raises(ReplayError, match=r"line 2: time 1e999999999 s is out of range"):
        read_tum_ns(_tum("1e999999999 0 0 0 0 0 0 1"))


def test_kitti_rotations_and_times_checked() -> None:
    """KITTI: a matrix that is not orthonormal, a reflection, a value not finite, times out of order or two on a
    line: each names the file and the line."""
    good = to_kitti(np.array([[0.0, 0.0, 0.3], [1.0, 0.5, -2.0]])).decode().splitlines()
    assert read_kitti("\n".join(good)) == pytest.approx(np.array([[0.0, 0.0, 0.3], [1.0, 0.5, -2.0]]), abs=1e-8)
    scaled = " ".join(str(1.01 * float(v)) if k in (0, 1, 4, 5) else v for k, v in enumerate(good[1].split()))
    with pytest.raises(ValueError, match=r"line 2: the rotation part is not orthonormal \(R\^T R differs from the "
                                         r"identity by 0.0201 > 0.001\)"):
        read_kitti("\n".join([good[0], scaled]))
    with pytest.raises(ValueError, match=r"line 1: the rotation part is a reflection"):
        read_kitti("1 0 0 0 0 1 0 0 0 0 -1 0\n")
    with pytest.raises(ValueError, match=r"line 1: a value is not finite"):
        read_kitti("1 0 0 nan 0 1 0 0 0 0 1 0\n")
    with pytest.raises(ReplayError, match=r"est.kitti, line 1: the rotation part is not orthonormal"):
        read_kitti_ns("0 0 0 0 0 0 0 0 0 0 0 0\n", "1\n", "est.kitti")
    with pytest.raises(ReplayError, match=r"times.txt, line 2: time 0.5 s is before line 1's"):
        read_kitti_ns("\n".join(good), "1.0\n0.5\n", "est.kitti", "times.txt")
    with pytest.raises(ReplayError, match=r"times.txt, line 1: expected one time in seconds, got 2 fields"):
        read_kitti_ns("\n".join(good), "1.0 2.0\n", "est.kitti", "times.txt")
    with pytest.raises(ReplayError, match=r"times file, line 2: not a time in seconds"):
        read_kitti_ns("\n".join(good), "1.0\nx\n")
    t, poses = read_kitti_ns("\n".join(good), "1.0\n\n2.5\n")
    assert t.tolist() == [1_000_000_000, 2_500_000_000] and poses.shape == (2, 3)


def _bag(path: Path, poses: list[tuple[int, tuple[float, float, float], float]]) -> Path:
    """A ROS 2 bag of PoseStamped on /slam/pose: (stamp ns, (x, y, yaw), quaternion scale) each."""
    from mcap_ros2.writer import Writer

    path.mkdir()
    with open(path / f"{path.name}_0.mcap", "wb") as f:
        w = Writer(f)
        schema = w.register_msgdef("geometry_msgs/msg/PoseStamped", POSE_STAMPED)
        for k, (t, xyyaw, scale) in enumerate(poses):
            pose = _pose(*xyyaw)
            pose["orientation"] = {key: scale * v for key, v in pose["orientation"].items()}  # type: ignore[attr-defined]
            w.write_message("/slam/pose", schema, {"header": {"stamp": _stamp(t), "frame_id": "map"}, "pose": pose},
                            log_time=10**9 + k, publish_time=10**9 + k)
        w.finish()
    (path / "metadata.yaml").write_text("rosbag2_bagfile_information:\n  storage_identifier: mcap\n")
    return path


def test_pose_topic_checked_as_files_are(tmp_path: Path) -> None:
    """A bag's pose topic: header stamps out of order and a zero quaternion name the message; a good one reads."""
    ok = _bag(tmp_path / "ok", [(2 * 10**9, (0.0, 0.0, 0.1), 1.0), (3 * 10**9, (1.0, 0.0, 0.2), 1.0)])
    t, poses = read_pose_topic(ok, "/slam/pose")
    assert t.tolist() == [2 * 10**9, 3 * 10**9] and poses[:, 2] == pytest.approx([0.1, 0.2])
    late = _bag(tmp_path / "late", [(3 * 10**9, (0.0, 0.0, 0.0), 1.0), (2 * 10**9, (1.0, 0.0, 0.0), 1.0)])
    with pytest.raises(ReplayError, match=r"/slam/pose, message 2 \(stamp 2.000000000 s\): time 2.000000000 s is "
                                          r"before message 1's"):
        read_pose_topic(late, "/slam/pose")
    zero = _bag(tmp_path / "zero", [(2 * 10**9, (0.0, 0.0, 0.0), 1.0), (3 * 10**9, (1.0, 0.0, 0.0), 0.0)])
    with pytest.raises(ReplayError, match=r"message 2 \(stamp 3.000000000 s\): the quaternion's norm is 0"):
        read_pose_topic(zero, "/slam/pose")


def test_files_are_bounded_and_read_line_by_line(tmp_path: Path) -> None:
    """A file over the limit is refused before it is read (a sparse file of the default limit's size + 1 too);
    an overlong line and bytes that are not UTF-8 name their line; a missing file is one line."""
    f = tmp_path / "est.tum"
    f.write_text(_tum(*(f"{k + 1} 0 0 0 0 0 0 1" for k in range(50))))
    with pytest.raises(ReplayError, match=rf"est.tum is {f.stat().st_size:,} bytes, more than the 500 an estimate "
                                          r"may have \(MAX_ESTIMATE_BYTES; --max-bytes N reads a larger one\)"):
        text_lines(f, "est.tum", 500)
    assert len(read_tum_ns(text_lines(f, "est.tum"), "est.tum")[0]) == 50
    sparse = tmp_path / "sparse.tum"
    with open(sparse, "wb") as out:
        out.truncate(MAX_ESTIMATE_BYTES + 1)
    with pytest.raises(ReplayError, match=rf"is {MAX_ESTIMATE_BYTES + 1:,} bytes, more than the "
                                          rf"{MAX_ESTIMATE_BYTES:,}"):
        text_lines(sparse, "sparse.tum")
    os.truncate(sparse, 10 * MAX_LINE_BYTES)  # NULs and no line break: one endless "line"
    with pytest.raises(ReplayError, match=r"sparse.tum, line 1: longer than 4,096 bytes: not a pose file"):
        read_tum_ns(text_lines(sparse, "sparse.tum"), "sparse.tum")
    binary = tmp_path / "bin.tum"
    binary.write_bytes(b"1 0 0 0 0 0 0 1\n\xff\xfe\n")
    with pytest.raises(ReplayError, match=r"bin.tum, line 2: not UTF-8 text"):
        read_tum_ns(text_lines(binary, "bin.tum"), "bin.tum")
    with pytest.raises(ReplayError, match=r"gone.tum cannot be read: No such file"):
        text_lines(tmp_path / "gone.tum", "gone.tum")


def test_time_coverage_and_its_one_line_verdicts() -> None:
    """The fraction of the truth's span between the first and last estimate inside it; no overlap and too little
    coverage are one line each, with the times that say why."""
    t_gt = np.arange(0, 101, dtype=np.int64) * 10**9  # 0 .. 100 s
    assert time_coverage(t_gt, t_gt) == (1.0, 0, 100 * 10**9)
    assert time_coverage(np.array([40, 52], np.int64) * 10**9, t_gt) == (pytest.approx(0.12), 40 * 10**9, 52 * 10**9)
    assert time_coverage(np.array([200], np.int64) * 10**9, t_gt) == (0.0, 0, 0)
    assert time_coverage(np.array([5], np.int64), np.array([5], np.int64))[0] == 1.0  # a truth of one instant
    late = np.arange(1000, 1101, dtype=np.int64) * 10**9
    msg = coverage_problem(late, t_gt, 0.5, "a clock offset?")
    assert msg == ("no estimate time falls inside the ground truth's time span (the estimate runs from t=1000.000 "
                   "to 1100.000 s, the truth from t=0.000 to 100.000 s): a clock offset?")
    assert coverage_problem(late, t_gt, 0.0, "") is not None  # no overlap fails whatever min_coverage says
    part = np.arange(40, 53, dtype=np.int64) * 10**9
    msg = coverage_problem(part, t_gt, 0.5, "a clock offset?")
    assert msg == ("the estimate covers 12 % of the ground truth's 100.0 s (12.0 s, from t=40.000 to 52.000 s; the "
                   "truth from t=0.000 to 100.000 s); min_coverage = 0.5: a clock offset?")
    assert coverage_problem(part, t_gt, 0.12, "") is None
    assert "covers 49.9 %" in str(coverage_problem(np.array([0, 49_999_999_999], np.int64), t_gt, 0.5, ""))


def test_min_coverage_is_a_config_key_with_help() -> None:
    """min_coverage is a field with help (what `slamreplay pipelines NAME` lists), checked in [0, 1], and a Config
    made at run time gets it from CoverageConfig as a base or coverage_field()."""
    rows = {r["key"]: r for r in config_schema(EstimateConfig)}
    assert rows["min_coverage"]["default"] == MIN_COVERAGE == 0.5 and rows["min_coverage"]["type"] == "float"
    assert "fraction of the ground truth's time span" in rows["min_coverage"]["help"]
    with pytest.raises(ValueError, match=r"min_coverage must be a fraction in \[0, 1\], got 1.5"):
        EstimateConfig(min_coverage=1.5)
    based = dataclasses.make_dataclass("x_config", [("check_determinism", bool, dataclasses.field(default=False))],
                                       bases=(CoverageConfig,), frozen=True)
    assert [r["key"] for r in config_schema(based)] == ["min_coverage", "check_determinism"]
    with pytest.raises(ValueError, match="min_coverage must be a fraction"):
        based(min_coverage=-0.1)
    made = dataclasses.make_dataclass("y_config", [coverage_field()], frozen=True)
    assert {r["key"]: r["help"] for r in config_schema(made)}["min_coverage"] == rows["min_coverage"]["help"]

    class Probe(EstimateReplay):
        def estimate(self, t_gt: np.ndarray, gt: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            raise NotImplementedError

    class Ctx:
        observer = None

    with pytest.raises(ReplayError, match=r"min_coverage must be a fraction in \[0, 1\], got 2.0"):
        Probe(made(min_coverage=2.0), Ctx())  # type: ignore[arg-type]
