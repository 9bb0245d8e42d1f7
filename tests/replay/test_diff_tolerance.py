"""Default diff tolerances: numerical noise between environments is "same", a real 1 % regression is not."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from conftest import write_tiny_recording

from slamreplay.api.cli.command import main
from slamreplay.replay.engine.pipeline import MEASURED_ABS_TOLERANCE, MEASURED_REL_TOLERANCE, MetricSpec
from slamreplay.replay.pipelines.ifmi import IfmiPipeline
from slamreplay.replay.pipelines.landmark_slam import METRICS as LANDMARK_METRICS
from slamreplay.replay.runs.diff import diff_runs, metric_tolerance
from slamreplay.replay.runs.run import run_recording

MEASURED = {"tolerance": MEASURED_ABS_TOLERANCE, "rel_tolerance": MEASURED_REL_TOLERANCE}


def test_metric_tolerance_is_relative_with_a_floor() -> None:
    """max(floor, rel * |A|); an override (absolute or N %) replaces it; old runs without rel_tolerance: the floor."""
    assert metric_tolerance(MEASURED, 22.2) == pytest.approx(0.0222)
    assert metric_tolerance(MEASURED, -500.0) == pytest.approx(0.5)
    assert metric_tolerance(MEASURED, 0.0) == MEASURED_ABS_TOLERANCE
    assert metric_tolerance(MEASURED, None) == MEASURED_ABS_TOLERANCE
    assert metric_tolerance({"tolerance": 1e-9}, 1000.0) == 1e-9
    assert metric_tolerance({"tolerance": 0.0, "rel_tolerance": 0.0}, 7.0) == 0.0
    assert metric_tolerance(MEASURED, 2.0, "0.5") == 0.5
    assert metric_tolerance(MEASURED, 2.0, "10%") == pytest.approx(0.2)


def test_measured_metrics_catch_one_percent_and_counts_are_exact() -> None:
    """Every float metric of the pipelines absorbs 1e-6 relative noise and reports a 1 % change; counts are exact."""
    spec = MetricSpec.measured("lower", "m", "x")
    assert (spec.tolerance, spec.rel_tolerance) == (MEASURED_ABS_TOLERANCE, MEASURED_REL_TOLERANCE)
    entry = {"tolerance": spec.tolerance, "rel_tolerance": spec.rel_tolerance}
    for a in (1e-3, 0.4, 22.2, 3549.04):
        tol = metric_tolerance(entry, a)
        assert abs(a * 1e-6) <= tol < abs(a * 0.01)
    # the reported case: chi2_final +6.231e-06 between Python 3.11 and 3.12 is noise now
    chi2 = IfmiPipeline.metrics["chi2_final"]
    assert metric_tolerance({"tolerance": chi2.tolerance, "rel_tolerance": chi2.rel_tolerance}, 22.2) >= 6.231e-06
    for name in ("landmarks_mapped", "false_landmarks", "data_association_errors"):
        assert (LANDMARK_METRICS[name].tolerance, LANDMARK_METRICS[name].rel_tolerance) == (0.0, 0.0)


def _cell(tmp_path: Path, name: str, **recording: float) -> Path:
    """The same cell (recording, pipeline, seed) as a run: ekfslam, seed 1."""
    rec = write_tiny_recording(tmp_path / f"{name}.mcap", **recording)
    return run_recording(rec, "ekfslam", tmp_path / name, seed=1).run_dir


def test_numerical_noise_passes_the_gate(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Inputs perturbed by 1e-12 relative (another numerical path): the metrics differ, yet diff exits 0."""
    a = _cell(tmp_path, "a")
    b = _cell(tmp_path, "b", perturb=1e-12)
    ma = json.loads((a / "metrics.json").read_text())["metrics"]
    mb = json.loads((b / "metrics.json").read_text())["metrics"]
    assert any(ma[k]["value"] != mb[k]["value"] for k in ma), "the perturbation should reach the metrics"
    assert ma["ape_rmse_m"]["rel_tolerance"] == MEASURED_REL_TOLERANCE
    assert main(["diff", str(a), str(b)]) == 0
    out = capsys.readouterr().out
    assert "WORSE" not in out and "0 metric(s) worse" in out


def test_one_percent_regression_fails_the_gate(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A real regression (odometry drift 5 % -> 5.5 %, robot error up by a few %) still exits 1."""
    a = _cell(tmp_path, "a")
    b = _cell(tmp_path, "b", drift=0.055)
    d = diff_runs(a, b, compare_rrd=False)
    ate = next(m for m in d.metrics if m.name == "robot_final_error_m")
    assert ate.b is not None and ate.a is not None and ate.b > ate.a * 1.01
    assert main(["diff", str(a), str(b)]) == 1
    assert "WORSE" in capsys.readouterr().out
