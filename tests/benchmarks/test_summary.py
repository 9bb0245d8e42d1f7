"""The benchmark summary table (benchmarks/summary.py) and the benchmarks' --json writer (bench_io.py)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

BENCH = Path(__file__).resolve().parents[2] / "benchmarks"
sys.path.insert(0, str(BENCH))

import bench_io  # noqa: E402
import summary  # noqa: E402


def test_table_rows_targets_and_missing_files(tmp_path: Path) -> None:
    """Ratios are checked against their targets; a benchmark not run is said so, not left out."""
    bench_io.write_json(tmp_path / "replay_throughput.json", {
        "reader_over_raw": 1.1, "noop_over_raw": 1.4, "odometry_null_over_raw": 1.3, "rrd_over_raw": float("nan"),
        "rrd_bytes": 2_000_000, "messages": 42})
    bench_io.write_json(tmp_path / "posegraph.json", {"linear_solver": "cvxopt", "plain_linear_solver": "qdldl",
                                                      "datasets": {"m3500": {"ours_over_g2o_gn": 0.75,
                                                                             "ours_plain_over_g2o_gn": 0.85}}})
    lines = summary.table(tmp_path)
    row = {line.split(" | ")[0].lstrip("| "): line for line in lines if line.startswith("| ")}
    assert row["RecordingReader / raw mcap decode"].endswith("| 1.10x | 1.20x | yes |")
    assert row["engine, no-op pipeline / raw decode"].endswith("| 1.40x | 1.30x | no |")
    assert "not run" in row["odometry pipeline + Rerun .rrd / raw decode"]  # NaN is written as null
    assert row["pose graph GN / g2o GN, M3500"].endswith("| 0.75x | 0.80x | yes |")
    assert "not run" in row["pose graph GN / g2o GN, intel"]
    assert "not run" in row["loop closure per 320x240 image, simulator"]
    assert row["pose graph GN / g2o GN, M3500, plain install"].endswith("| 0.85x | 0.80x | no |")
    assert "pose-graph linear solver: cvxopt; plain install (no `solver` extra): qdldl" in lines
    doc = json.loads((tmp_path / "replay_throughput.json").read_text())
    assert doc["rrd_over_raw"] is None and doc["machine"]["cpus"] >= 1
    assert not list(tmp_path.glob("*.tmp"))


def test_bad_input_exits_2_with_one_line(tmp_path: Path) -> None:
    """A missing folder and a file that is not JSON: one line naming it, exit 2, no traceback."""
    run = [sys.executable, str(BENCH / "summary.py")]
    proc = subprocess.run([*run, str(tmp_path / "nope")], capture_output=True, text=True)
    assert proc.returncode == 2 and "is not a directory" in proc.stderr and "Traceback" not in proc.stderr
    (tmp_path / "posegraph.json").write_text("{not json")
    proc = subprocess.run([*run, str(tmp_path)], capture_output=True, text=True)
    assert proc.returncode == 2
    assert "posegraph.json is not JSON" in proc.stderr and "Traceback" not in proc.stderr
    with pytest.raises(SystemExit):
        summary.table(tmp_path)
