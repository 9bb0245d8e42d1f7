"""``evaluate``: estimates made elsewhere (TUM, evo's TUM, KITTI) scored into run directories."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from conftest import write_tiny_recording

from slamreplay.recorder import GroundTruthPose, OdometryPose, Recorder
from slamreplay.replay.engine.trajectory import read_tum
from slamreplay.replay.errors import ReplayError
from slamreplay.replay.evaluation.evaluate import TRAJECTORY_METRICS
from slamreplay.replay.runs.diff import diff_runs
from slamreplay.replay.runs.evaluate_run import association_from, evaluate_estimate
from slamreplay.replay.runs.run import run_recording
from slamreplay.replay.runs.trajectory_eval import evaluate_run, export_kitti
from slamreplay.replay.tools.estimates import read_tum_ns, seconds_to_ns


@pytest.fixture(scope="module")
def dslam_run(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """(recording, a dslam run of it): the run whose trajectory.tum the tests evaluate."""
    root = tmp_path_factory.mktemp("evaluate")
    rec = write_tiny_recording(root / "tiny.mcap")
    run_recording(rec, "dslam", root / "dslam")
    return rec, root / "dslam"


def _metrics(run: Path) -> dict[str, float]:
    return {k: v["value"] for k, v in json.loads((run / "metrics.json").read_text())["metrics"].items()}


def test_evaluate_reproduces_a_runs_trajectory_metrics(dslam_run: tuple[Path, Path], tmp_path: Path) -> None:
    """The run's own trajectory.tum, evaluated, gives its seven trajectory metrics to 6 significant digits."""
    rec, run = dslam_run
    result = evaluate_estimate(run / "trajectory.tum", rec, tmp_path / "ev")
    want = _metrics(run)
    got = _metrics(tmp_path / "ev")
    assert set(TRAJECTORY_METRICS) <= set(got)
    for name in TRAJECTORY_METRICS:
        assert got[name] == pytest.approx(want[name], rel=1e-6), name
    assert got["poses_scored"] == 100 and result.manifest["pipeline"] == "estimate"
    assert (tmp_path / "ev" / "truth.tum").read_text() == (run / "truth.tum").read_text()
    origin = result.manifest["pipeline_origin"]
    assert origin["format"] == "tum" and len(origin["sha256"]) == 64
    assert result.manifest["pipeline_run"]["association"]["alignment"] == "none"
    d = diff_runs(run, tmp_path / "ev")  # diff reads it as a run: no trajectory metric is worse
    assert not set(d.worse) & set(TRAJECTORY_METRICS)
    report = evaluate_run(tmp_path / "ev", "se2")  # and `trajectory` too
    assert report.ape_trans.rmse == pytest.approx(want["ape_se2_rmse_m"], rel=1e-6)


def test_evaluate_reads_evo_files_and_kitti(dslam_run: tuple[Path, Path], tmp_path: Path) -> None:
    """evo's TUM (np.savetxt, %.18e, no header) and KITTI with times give the same trajectory metrics."""
    rec, run = dslam_run
    t, est = read_tum((run / "trajectory.tum").read_text())
    half = est[:, 2] / 2
    evo = np.column_stack([t, est[:, 0], est[:, 1], np.zeros(len(t)), np.zeros(len(t)), np.zeros(len(t)),
                           np.sin(half), np.cos(half)])
    np.savetxt(tmp_path / "evo.tum", evo, delimiter=" ")  # what evo's file_interface writes
    evaluate_estimate(tmp_path / "evo.tum", rec, tmp_path / "ev-evo")
    export_kitti(run, tmp_path / "kitti")
    (tmp_path / "times.txt").write_text("".join(f"{ts:.9f}\n" for ts in read_tum((run / "truth.tum").read_text())[0]))
    evaluate_estimate(tmp_path / "kitti" / "estimate.kitti", rec, tmp_path / "ev-kitti", fmt="kitti",
                      times=tmp_path / "times.txt")
    want = _metrics(run)
    for out in ("ev-evo", "ev-kitti"):
        got = _metrics(tmp_path / out)
        for name in TRAJECTORY_METRICS:
            assert got[name] == pytest.approx(want[name], rel=1e-6), (out, name)


def test_association_and_alignment_known_answers(tmp_path: Path) -> None:
    """An estimate 0.5 s late and turned by 90 degrees about a far point: --t-offset-s -0.5 puts it back in
    time, --align se2 removes the rotation (APE 0), --align none sees the whole offset."""
    rec = tmp_path / "line.mcap"
    with Recorder(rec, source={}) as r:
        for k in range(50):
            t = 10**9 + k * 10**8
            r.write("/ground_truth/pose", GroundTruthPose(t, 0.1 * k, 0.0, 0.0))
            r.write("/odom", OdometryPose(t, 0.1 * k, 0.0, 0.0))
    t_s = 1.0 + 0.1 * np.arange(50) + 0.5
    xy = np.column_stack([np.full(50, 10.0), 0.1 * np.arange(50)])  # (x, y) -> (10 - y, x): turned 90 deg
    yaw = np.full(50, np.pi / 2)
    rows = [f"{ts:.9f} {x:.17g} {y:.17g} 0 0 0 {np.sin(a / 2):.17g} {np.cos(a / 2):.17g}"
            for ts, (x, y), a in zip(t_s, xy, yaw, strict=True)]
    (tmp_path / "est.tum").write_text("\n".join(rows) + "\n")
    aligned = evaluate_estimate(tmp_path / "est.tum", rec, tmp_path / "se2",
                                association=association_from(-0.5, None, "se2"))
    assert aligned.metrics["poses_scored"] == 50
    assert aligned.metrics["ape_rmse_m"] == pytest.approx(0.0, abs=1e-9)
    assert aligned.metrics["ape_rot_rmse_deg"] == pytest.approx(0.0, abs=1e-7)
    plain = evaluate_estimate(tmp_path / "est.tum", rec, tmp_path / "none",
                              association=association_from(-0.5, None, "none"))
    assert plain.metrics["ape_rot_rmse_deg"] == pytest.approx(90.0, abs=1e-7)
    late = evaluate_estimate(tmp_path / "est.tum", rec, tmp_path / "late",
                             association=association_from(0.0, 0.01, "none"))
    assert late.metrics["poses_scored"] == 45  # the last 5 (4.6..4.9 s + 0.5) fall after the truth ends


def test_exact_times_and_bad_input(tmp_path: Path) -> None:
    """Times are read to the ns without float rounding; bad files and recordings are one-line errors."""
    assert seconds_to_ns("1700000000.123456789") == 1_700_000_000_123_456_789
    assert seconds_to_ns("1.5e-3") == 1_500_000 and seconds_to_ns("2") == 2_000_000_000
    with pytest.raises(ReplayError, match=r"line 2: expected 8 fields"):
        read_tum_ns("# t x y z qx qy qz qw\n1.0 2 3\n")
    with pytest.raises(ReplayError, match="share a timestamp"):
        read_tum_ns("1 0 0 0 0 0 0 1\n1.0 1 0 0 0 0 0 1\n")
    rec = write_tiny_recording(tmp_path / "tiny.mcap", n=10)
    (tmp_path / "e.tum").write_text("1 0 0 0 0 0 0 1\n")
    with pytest.raises(ReplayError, match="no such file"):
        evaluate_estimate(tmp_path / "missing.tum", rec, tmp_path / "a")
    with pytest.raises(ReplayError, match="give --times"):
        evaluate_estimate(tmp_path / "e.tum", rec, tmp_path / "b", fmt="kitti")
    with pytest.raises(ReplayError, match="--t-max-diff-s must be >= 0"):
        association_from(0.0, -1.0)
    no_truth = tmp_path / "no-truth.mcap"
    with Recorder(no_truth, source={}) as r:
        r.write("/odom", OdometryPose(10**9, 0.0, 0.0, 0.0))
    with pytest.raises(ReplayError, match="has no /ground_truth/pose"):
        evaluate_estimate(tmp_path / "e.tum", no_truth, tmp_path / "c")
    assert not (tmp_path / "a").exists() and not (tmp_path / "c").exists()


def test_pose_topics_of_a_ros2_bag(tmp_path: Path) -> None:
    """A bag's PoseStamped topic equal to the truth scores 0; its Odometry topic, 10 % long in x, scores the
    known APE 0.01 * rms(k)."""
    from ros2_fixtures import write_ros2_bag

    bag = write_ros2_bag(tmp_path / "bag")
    rec = tmp_path / "truth.mcap"
    with Recorder(rec, source={}) as r:
        for k in range(20):
            r.write("/ground_truth/pose", GroundTruthPose(2_000_000_000 + k * 100_000_000, 0.1 * k, 0.0, 0.05 * k))
    same = evaluate_estimate(bag, rec, tmp_path / "same", topic="/mocap/pose")
    assert same.metrics["poses_scored"] == 20 and same.metrics["ape_rmse_m"] == pytest.approx(0.0, abs=1e-12)
    assert same.manifest["pipeline_origin"]["topic"] == "/mocap/pose"
    odom = evaluate_estimate(bag, rec, tmp_path / "odom", topic="/wheel/odom")
    assert odom.metrics["ape_rmse_m"] == pytest.approx(0.01 * np.sqrt(np.mean(np.arange(20.0) ** 2)), rel=1e-9)
    assert odom.metrics["ape_rot_rmse_deg"] == pytest.approx(0.0, abs=1e-9)
    with pytest.raises(ReplayError, match=r"has no topic /slam/pose \(its topics: /camera/color, /mocap/pose"):
        evaluate_estimate(bag, rec, tmp_path / "x", topic="/slam/pose")
    with pytest.raises(ReplayError, match="is sensor_msgs/msg/Image, not a pose"):
        evaluate_estimate(bag, rec, tmp_path / "y", topic="/camera/color")


def _line_recording(path: Path, n: int = 101, odom_from_s: float = 1.0) -> Path:
    """Ground truth on a straight line, 10 Hz from t = 1 s to 11 s; odometry from ``odom_from_s`` (earlier: the
    recording spans more than its ground truth)."""
    with Recorder(path, source={}) as r:
        for k in range(n):
            t = 10**9 + k * 10**8
            r.write("/ground_truth/pose", GroundTruthPose(t, 0.1 * k, 0.0, 0.0))
        r.write("/odom", OdometryPose(round(odom_from_s * 1e9), 0.0, 0.0, 0.0))
    return path


def _write_tum(path: Path, t_s: np.ndarray) -> Path:
    path.write_text("".join(f"{t:.9f} {0.1 * k:.9f} 0 0 0 0 0 1\n" for k, t in enumerate(t_s)))
    return path


def test_an_estimate_beside_the_recording_in_time_is_refused(tmp_path: Path, capsys: pytest.CaptureFixture[str]
                                                             ) -> None:
    """A clock offset that puts every pose outside the recording: refused before anything is written, one line,
    exit 2 (evo refuses such a pair too); --t-offset-s puts it back."""
    from slamreplay.api.cli.command import main

    rec = _line_recording(tmp_path / "line.mcap")
    est = _write_tum(tmp_path / "late.tum", 1001.0 + 0.1 * np.arange(101))
    with pytest.raises(ReplayError, match=r"late.tum: no estimate time falls inside the recording's time span: the "
                                          r"estimate runs from t=1001.000 to 1011.000 s, line.mcap from t=1.000 to "
                                          r"11.000 s: a clock offset\? --t-offset-s S"):
        evaluate_estimate(est, rec, tmp_path / "a")
    assert not (tmp_path / "a").exists()
    code = main(["evaluate", str(est), "--recording", str(rec), "--out", str(tmp_path / "b"), "-q"])
    err = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert code == 2 and len(err) == 1 and "no estimate time falls inside" in err[0]
    back = evaluate_estimate(est, rec, tmp_path / "c", association=association_from(-1000.0))
    assert back.metrics["poses_scored"] == 101 and back.metrics["ape_rmse_m"] == pytest.approx(0.0, abs=1e-9)


def test_an_estimate_covering_too_little_of_the_truth_fails_its_run(tmp_path: Path) -> None:
    """Inside the recording but beside its ground truth: the run fails (no overlap); covering 20 % of the truth's
    10 s fails at the default min_coverage 0.5 and passes with min_coverage 0.2; a bad value is refused."""
    rec = _line_recording(tmp_path / "line.mcap", odom_from_s=0.0)
    before = _write_tum(tmp_path / "before.tum", 0.1 + 0.05 * np.arange(10))  # 0.1 .. 0.55 s: before the truth
    with pytest.raises(ReplayError, match=r"no estimate time falls inside the ground truth's time span \(the estimate "
                                          r"runs from t=0.100 to 0.550 s, the truth from t=1.000 to 11.000 s\): a clock"
                                          r" offset\? --t-offset-s S"):
        evaluate_estimate(before, rec, tmp_path / "a")
    assert json.loads((tmp_path / "a" / "manifest.json").read_text())["status"] == "failed"
    assert not (tmp_path / "a" / "metrics.json").exists()
    part = _write_tum(tmp_path / "part.tum", 1.0 + 0.1 * np.arange(21))  # 1 .. 3 s of the truth's 1 .. 11 s
    with pytest.raises(ReplayError, match=r"the estimate covers 20 % of the ground truth's 10.0 s \(2.0 s, from "
                                          r"t=1.000 to 3.000 s; the truth from t=1.000 to 11.000 s\); min_coverage = "
                                          r"0.5: a clock offset\?"):
        evaluate_estimate(part, rec, tmp_path / "b")
    ok = evaluate_estimate(part, rec, tmp_path / "c", min_coverage=0.2)
    assert ok.metrics["poses_scored"] == 21 and ok.manifest["config"] == {"min_coverage": 0.2}
    assert ok.manifest["config_sources"]["min_coverage"] == "user"
    assert "covers 20 % of the ground truth's time span" in (tmp_path / "c" / "log.txt").read_text()
    with pytest.raises(ReplayError, match=r"min_coverage must be a fraction in \[0, 1\], got 1.5"):
        evaluate_estimate(part, rec, tmp_path / "d", min_coverage=1.5)
    assert not (tmp_path / "d").exists()


def test_evaluate_bounds_what_it_reads(tmp_path: Path) -> None:
    """max_bytes refuses a larger estimate (and times file) before reading it; a value <= 0 is refused."""
    rec = _line_recording(tmp_path / "line.mcap")
    est = _write_tum(tmp_path / "est.tum", 1.0 + 0.1 * np.arange(101))
    with pytest.raises(ReplayError, match=r"est.tum is 3,\d{3} bytes, more than the 1,000 an estimate may have"):
        evaluate_estimate(est, rec, tmp_path / "a", max_bytes=1000)
    with pytest.raises(ReplayError, match=r"--max-bytes must be > 0, got 0"):
        evaluate_estimate(est, rec, tmp_path / "a", max_bytes=0)
    kitti = tmp_path / "est.kitti"
    kitti.write_text("1 0 0 0 0 1 0 0 0 0 1 0\n")
    times = tmp_path / "times.txt"
    times.write_text("1.0\n" + "#" * 2000 + "\n")
    with pytest.raises(ReplayError, match=r"times file .*times.txt is 2,005 bytes, more than the 1,000"):
        evaluate_estimate(kitti, rec, tmp_path / "a", times=times, max_bytes=1000)
    assert not (tmp_path / "a").exists()


def test_unreadable_estimates_and_formats_are_one_line(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """An unknown format, and a file that fails while it is read (TUM or KITTI), are one-line errors."""
    from slamreplay.replay.runs.evaluate_run import read_estimate

    est = _write_tum(tmp_path / "est.tum", 1.0 + 0.1 * np.arange(3))
    with pytest.raises(ReplayError, match=r"--format must be one of tum, kitti, topic, got 'csv'"):
        read_estimate(est, "csv")  # type: ignore[arg-type]
    (tmp_path / "times.txt").write_text("1\n")

    def refuse(self: Path, *args: object, **kwargs: object) -> None:
        raise PermissionError(13, "Permission denied")

    monkeypatch.setattr(Path, "open", refuse)
    with pytest.raises(ReplayError, match=r"estimate .*est.tum cannot be read: Permission denied"):
        read_estimate(est)
    with pytest.raises(ReplayError, match=r"estimate .*est.tum cannot be read: Permission denied"):
        read_estimate(est, "kitti", times=tmp_path / "times.txt")
