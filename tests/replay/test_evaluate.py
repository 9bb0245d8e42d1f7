"""APE with each alignment, RPE per step and per metre, KITTI files, and `slamreplay trajectory` on real runs."""

from __future__ import annotations

import json
import math
import re
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from slamreplay.algorithms.common import se2
from slamreplay.api.cli.command import main
from slamreplay.replay.engine.trajectory import read_tum
from slamreplay.replay.evaluation.evaluate import (
    TRAJECTORY_METRICS,
    alignment_transform,
    ape,
    pairs,
    read_kitti,
    rpe,
    to_kitti,
    trajectory_metrics,
)
from slamreplay.replay.evaluation.metrics import truth_at
from slamreplay.replay.runs.run import run_recording
from slamreplay.replay.runs.trajectory_eval import evaluate_run


def _loop(n: int = 200) -> np.ndarray:
    """A true trajectory: a 4 m circle, heading along the tangent."""
    a = np.linspace(0.0, 2 * np.pi, n)
    return np.column_stack([2 * np.cos(a), 2 * np.sin(a), se2.wrap_angle(a + np.pi / 2)])


def test_ape_of_a_constant_offset_under_each_alignment() -> None:
    """An estimate shifted by (0.3, -0.4) m: 0.5 m with no alignment, 0 with origin or se2 alignment."""
    ref = _loop()
    est = ref + [0.3, -0.4, 0.0]
    assert ape(est, ref, "none")[0].rmse == pytest.approx(0.5, abs=1e-12)
    assert ape(est, ref, "none")[0].max == pytest.approx(0.5, abs=1e-12)
    assert ape(est, ref, "origin")[0].rmse == pytest.approx(0.0, abs=1e-12)
    assert ape(est, ref, "se2")[0].rmse == pytest.approx(0.0, abs=1e-12)
    assert ape(est, ref, "none")[1].rmse == pytest.approx(0.0, abs=1e-12)


@settings(max_examples=40, deadline=None)
@given(st.floats(-3.0, 3.0), st.floats(-5.0, 5.0), st.floats(-5.0, 5.0), st.integers(0, 10_000))
def test_se2_alignment_recovers_a_rigid_motion(theta: float, tx: float, ty: float, seed: int) -> None:
    """est = T^-1 (+) (ref + noise): the se2 alignment finds T to within the noise, the aligned error is the noise."""
    rng = np.random.default_rng(seed)
    ref = _loop(100)
    noise = np.column_stack([rng.normal(0, 0.01, (100, 2)), np.zeros(100)])
    t = np.array([tx, ty, theta])
    est = se2.compose(se2.inverse(t), ref + noise)
    found = alignment_transform(est, ref, "se2")
    assert found[:2] == pytest.approx(t[:2], abs=0.01)
    assert abs(se2.wrap_angle(found[2] - theta)) < 0.01
    err = ape(est, ref, "se2")[0].rmse
    assert 0.3 * 0.01 * math.sqrt(2) < err < 1.2 * 0.01 * math.sqrt(2)  # the noise's 2D RMS (the fit takes 3 dof)


def test_origin_alignment_uses_the_first_pose_only() -> None:
    """A heading error at the start, corrected by origin alignment; an error at the end is not."""
    ref = _loop()
    est = se2.compose(np.array([0.0, 0.0, 0.1]), ref)  # the whole estimate rotated about the world origin
    est = se2.compose(se2.compose(ref[0], se2.inverse(est[0])), est)  # undo the start: origin aligns it exactly
    assert ape(est, ref, "origin")[0].rmse == pytest.approx(0.0, abs=1e-12)
    drift = est.copy()
    drift[-1, :2] += [1.0, 0.0]
    assert ape(drift, ref, "origin")[0].max == pytest.approx(1.0, abs=1e-9)


def test_rpe_is_invariant_to_a_rigid_motion_and_measures_drift() -> None:
    """RPE ignores where the estimate sits (a rigid motion of it: RPE 0, APE not); a 1 % scale drift on a straight
    line is 1 cm of translation error per metre."""
    ref = _loop()
    moved = se2.compose(np.array([5.0, -2.0, 0.7]), ref)
    assert rpe(moved, ref, 1, "step")[0].rmse == pytest.approx(0.0, abs=1e-12)
    assert rpe(moved, ref, 1.0, "m")[1].rmse == pytest.approx(0.0, abs=1e-9)
    assert ape(moved, ref, "none")[0].rmse > 1.0
    x = np.arange(0.0, 20.0001, 0.1)
    line = np.column_stack([x, np.zeros_like(x), np.zeros_like(x)])
    scaled = line * [1.01, 1.0, 1.0]
    trans, rot = rpe(scaled, line, 1.0, "m")
    assert trans.n == 20 and trans.rmse == pytest.approx(0.01, rel=1e-6) and rot.rmse == 0.0
    assert rpe(scaled, line, 5, "step")[0].rmse == pytest.approx(0.005, rel=1e-6)


def test_pairs_as_evo_makes_them() -> None:
    """Consecutive, non-overlapping pairs: every delta poses, or once delta metres of path are reached."""
    line = np.column_stack([np.arange(0.0, 2.55, 0.25), np.zeros(11), np.zeros(11)])  # 0 .. 2.5 m
    assert pairs(line, 3, "step") == [(0, 3), (3, 6), (6, 9)]
    assert pairs(line, 1.0, "m") == [(0, 4), (4, 8)]
    assert pairs(line[:1], 1.0, "m") == []
    with pytest.raises(ValueError, match="whole number"):
        pairs(line, 1.5, "step")
    with pytest.raises(ValueError, match="must be > 0"):
        pairs(line, 0.0, "m")
    with pytest.raises(ValueError, match="delta unit"):
        pairs(line, 1.0, "s")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="alignment must be"):
        ape(line, line, "sim3")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="same length"):
        ape(line, line[:3])


def test_per_metre_pairs_follow_the_estimates_path() -> None:
    """As evo_rpe --delta 1 --delta_unit m: pairs where the estimate's own path reaches each metre (an estimate
    that zigzags reaches it sooner); pairs_from_reference measures the truth's path (--pairs_from_reference)."""
    line = np.column_stack([np.arange(0.0, 2.55, 0.25), np.zeros(11), np.zeros(11)])
    zigzag = line + np.column_stack([np.zeros(11), 0.2 * (np.arange(11) % 2), np.zeros(11)])  # 0.32 m a step
    assert pairs(line, 0.9, "m") == [(0, 4), (4, 8)]
    assert pairs(zigzag, 0.9, "m") == [(0, 3), (3, 6), (6, 9)]
    by_est, _ = rpe(zigzag, line, 0.9, "m")
    by_ref, _ = rpe(zigzag, line, 0.9, "m", pairs_from_reference=True)
    assert by_est.n == 3 and by_ref.n == 2  # the truth's 0.25 m steps reach 0.9 m every 4 poses
    assert rpe(zigzag, line, 2, "step") == rpe(zigzag, line, 2, "step", pairs_from_reference=True)


def test_kitti_round_trip_and_errors() -> None:
    """Planar poses survive a KITTI write and read; a malformed line names its number."""
    poses = np.array([[1.0, -2.0, 0.3], [3.5, 4.25, -3.0], [0.0, 0.0, math.pi / 2]])
    text = to_kitti(poses).decode()
    assert len(text.splitlines()) == 3 and all(len(line.split()) == 12 for line in text.splitlines())
    assert read_kitti(text) == pytest.approx(poses, abs=1e-8)
    with pytest.raises(ValueError, match="line 2: expected 12 numbers"):
        read_kitti("1 0 0 0 0 1 0 0 0 0 1 0\n1 2 3\n")
    with pytest.raises(ValueError, match="line 1: not 12 numbers"):
        read_kitti("a b c\n")


def test_trajectory_metrics_only_where_they_apply() -> None:
    """Every name is a declared spec; none without overlap in time; no per-metre RPE before a metre is driven."""
    t = np.arange(50, dtype=np.int64) * 100_000_000
    ref = np.column_stack([np.linspace(0, 5, 50), np.zeros(50), np.zeros(50)])
    mask, at = truth_at(t, t, ref)
    out = trajectory_metrics((ref + [0.0, 0.1, 0.0])[mask], at)
    assert set(out) == set(TRAJECTORY_METRICS)
    assert out["ape_rmse_m"] == pytest.approx(0.1) and out["ape_se2_rmse_m"] == pytest.approx(0.0, abs=1e-9)
    mask, at = truth_at(t + 10**12, t, ref)
    assert not mask.any() and trajectory_metrics(ref[mask], at) == {}
    mask, at = truth_at(t[:5], t, ref)
    short = trajectory_metrics(ref[:5][mask], at)  # 0.4 m driven
    assert "rpe_m_trans_rmse_m" not in short and "rpe_step_trans_rmse_m" in short


@pytest.fixture
def odometry_run(tiny_recording: Path, tmp_path: Path) -> Path:
    return run_recording(tiny_recording, "odometry", tmp_path / "run").run_dir


def test_run_reports_the_trajectory_metrics_and_pairs_truth(odometry_run: Path) -> None:
    """A run's truth.tum pairs line by line with trajectory.tum; ape_rmse_m is the pipeline's own ATE and what
    recomputing from the two files gives."""
    metrics = json.loads((odometry_run / "metrics.json").read_text())["metrics"]
    assert metrics["ape_rmse_m"]["value"] == pytest.approx(metrics["ape_rmse_m"]["value"], rel=1e-12)
    assert metrics["ape_se2_rmse_m"]["value"] <= metrics["ape_rmse_m"]["value"]
    assert metrics["rpe_step_trans_rmse_m"]["better"] == "lower"
    t_est, est = read_tum((odometry_run / "trajectory.tum").read_text())
    t_truth, truth = read_tum((odometry_run / "truth.tum").read_text())
    assert np.array_equal(t_est, t_truth)
    assert ape(est, truth, "se2")[0].rmse == pytest.approx(metrics["ape_se2_rmse_m"]["value"], rel=1e-6)


def _cli(args: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, str, str]:
    code = main(args)
    out, err = capsys.readouterr()
    return code, out, err


def test_trajectory_command(odometry_run: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """`slamreplay trajectory`: the table, --json with each alignment, and KITTI files that pair line by line."""
    code, out, _ = _cli(["trajectory", str(odometry_run), "--align", "se2"], capsys)
    assert code == 0 and "APE translation (m), align se2" in out
    code, out, _ = _cli(["trajectory", str(odometry_run), "--json", "--delta", "0.5", "--delta-unit", "m"], capsys)
    doc = json.loads(out)
    assert code == 0 and doc["alignment"] == "none" and doc["rpe_delta_unit"] == "m"
    assert doc["rpe_pairs_from"] == "estimate"
    by_truth = evaluate_run(odometry_run, delta=1.0, delta_unit="m", pairs_from_reference=True)
    assert "RPE translation (m), 1 m of truth" in by_truth.table()
    assert by_truth.to_json()["rpe_pairs_from"] == "reference"
    assert doc["rpe"]["translation_m"]["n"] > 0
    metrics = json.loads((odometry_run / "metrics.json").read_text())["metrics"]
    assert doc["ape"]["translation_m"]["rmse"] == pytest.approx(metrics["ape_rmse_m"]["value"], rel=1e-6)
    code, _, err = _cli(["trajectory", str(odometry_run), "--kitti", str(tmp_path / "k")], capsys)
    assert code == 0 and "estimate.kitti" in err
    est, truth = (read_kitti((tmp_path / "k" / f).read_text()) for f in ("estimate.kitti", "truth.kitti"))
    assert est.shape == truth.shape == (100, 3)
    assert ape(est, truth)[0].rmse == pytest.approx(metrics["ape_rmse_m"]["value"], rel=1e-6)


def _bad(args: list[str], capsys: pytest.CaptureFixture[str], pattern: str) -> None:
    code, _, err = _cli(args, capsys)
    lines = [line for line in err.splitlines() if line.strip()]
    assert code == 2 and len(lines) == 1 and "Traceback" not in err, err
    assert re.search(pattern, lines[0]), lines[0]


def test_trajectory_command_errors(odometry_run: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A missing, unfinished or trajectory-less run, no ground truth, a bad delta, a damaged file: one line, exit 2."""
    _bad(["trajectory", str(tmp_path / "none")], capsys, "is not a run directory")
    _bad(["trajectory", str(odometry_run), "--delta", "1.5"], capsys, "whole number")
    (odometry_run / "truth.tum").write_text("1 2 3\n")
    _bad(["trajectory", str(odometry_run)], capsys, r"malformed: line 1: expected 8 fields")
    (odometry_run / "truth.tum").write_text("# timestamp x y z qx qy qz qw\n0.5 0 0 0 0 0 0 1\n")
    _bad(["trajectory", str(odometry_run)], capsys, "holds times that .* does not")
    (odometry_run / "truth.tum").unlink()
    _bad(["trajectory", str(odometry_run)], capsys, "no truth.tum: its recording has no /ground_truth/pose")
    (odometry_run / "trajectory.tum").unlink()
    _bad(["trajectory", str(odometry_run)], capsys, "no trajectory.tum: pipeline odometry exports no trajectory")
    (odometry_run / "manifest.json").unlink()
    _bad(["trajectory", str(odometry_run)], capsys, "not a finished run")
    assert not (tmp_path / "k").exists()
