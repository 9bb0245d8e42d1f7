"""Diff: what changed, metric verdicts with directions and tolerances, .rrd equality, comparison file."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from conftest import write_tiny_recording
from rerun.chunk import RrdReader

from slamreplay.replay.errors import ReplayError
from slamreplay.replay.runs.diff import diff_runs, format_table, parse_tolerances
from slamreplay.replay.runs.diff_view import write_comparison_rrd
from slamreplay.replay.runs.run import run_recording


@pytest.fixture
def two_runs(tmp_path: Path) -> tuple[Path, Path, Path]:
    """Run A on a recording with 5 % odometry drift, run B on the same with 10 %, and A again."""
    good = write_tiny_recording(tmp_path / "good.mcap", drift=0.05)
    bad = write_tiny_recording(tmp_path / "bad.mcap", drift=0.10)
    a = run_recording(good, "odometry", tmp_path / "a").run_dir
    b = run_recording(bad, "odometry", tmp_path / "b").run_dir
    a2 = run_recording(good, "odometry", tmp_path / "a2").run_dir
    return a, b, a2


def test_identical_runs(two_runs: tuple[Path, Path, Path]) -> None:
    """Same inputs: no changes, every metric the same, rrd content equal."""
    a, _, a2 = two_runs
    d = diff_runs(a, a2)
    assert d.changes == [] and d.worse == [] and d.rrd_equal is True
    assert {m.verdict for m in d.metrics} == {"same"}


def test_regression_is_found_and_explained(two_runs: tuple[Path, Path, Path]) -> None:
    """More drift: ATE is worse, the recording change is named, and the rrd differs."""
    a, b, _ = two_runs
    d = diff_runs(a, b)
    assert "ape_rmse_m" in d.worse and "path_length_m" not in d.worse
    assert any(c["field"] == "recording.sha256" for c in d.changes)
    assert d.rrd_equal is False
    back = diff_runs(b, a, compare_rrd=False)
    assert back.worse == [] and {m.name for m in back.metrics if m.verdict == "better"} >= {"ape_rmse_m"}
    table = format_table(d)
    assert "WORSE" in table and "recording.sha256" in table
    json.dumps(d.to_json())


def test_tolerances(two_runs: tuple[Path, Path, Path]) -> None:
    """An absolute or percentage tolerance larger than the change turns worse into same."""
    a, b, _ = two_runs
    lenient = diff_runs(a, b, parse_tolerances(["*=1000%"]), compare_rrd=False)
    assert lenient.worse == []
    absolute = diff_runs(a, b, {"ape_rmse_m": "100"}, compare_rrd=False)
    assert "ape_rmse_m" not in absolute.worse and "robot_final_error_m" in absolute.worse
    with pytest.raises(ReplayError, match="unknown metrics: nope"):
        diff_runs(a, b, {"nope": "1"})
    with pytest.raises(ReplayError, match="NAME=VALUE"):
        parse_tolerances(["ate"])
    with pytest.raises(ReplayError, match="not a number"):
        parse_tolerances(["ate=abc"])


def test_comparison_rrd(two_runs: tuple[Path, Path, Path], tmp_path: Path) -> None:
    """One recording with both runs re-rooted under runs/A and runs/B, with a blueprint."""
    a, b, _ = two_runs
    out = tmp_path / "cmp.rrd"
    write_comparison_rrd(a, b, out)
    reader = RrdReader(out)
    paths = {c.entity_path for c in reader.stream().to_chunks()}
    assert "/runs/A/world/robot" in paths and "/runs/B/world/robot" in paths
    assert reader.blueprints()
    with pytest.raises(ReplayError, match="already exists"):
        write_comparison_rrd(a, b, out)


def test_bad_run_dirs(two_runs: tuple[Path, Path, Path], tmp_path: Path) -> None:
    """A missing directory, a directory without a manifest, and a failed baseline are refused; a failed B is a
    regression (every metric of A lost, tests/replay/test_lost_metrics.py)."""
    a, _, _ = two_runs
    with pytest.raises(ReplayError, match="does not exist"):
        diff_runs(a, tmp_path / "nope")
    (tmp_path / "empty").mkdir()
    with pytest.raises(ReplayError, match="no manifest.json"):
        diff_runs(a, tmp_path / "empty")
    failed = tmp_path / "failed"
    failed.mkdir()
    (failed / "manifest.json").write_text(json.dumps({"status": "failed", "error": "boom"}))
    with pytest.raises(ReplayError, match="did not succeed"):
        diff_runs(failed, a)
    assert diff_runs(a, failed, compare_rrd=False).lost
