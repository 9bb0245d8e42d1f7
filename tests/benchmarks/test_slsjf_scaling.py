"""The SLSJF scaling benchmark (benchmarks/slsjf_scaling.py) end to end on tiny worlds."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

BENCH = Path(__file__).resolve().parents[2] / "benchmarks"


def test_tiny_sizes_give_every_figure_and_the_exponents(tmp_path: Path) -> None:
    """Two tiny sizes: per-step and per-join figures for both linearizations and both state recoveries, memory (no
    factor held with PCG), the split of a local map's cost, D-SLAM beside, the fits."""
    out = tmp_path / "slsjf.json"
    cmd = [sys.executable, str(BENCH / "slsjf_scaling.py"), "--sizes", "80", "160", "--steps", "65", "--settle", "10",
           "--compare-max", "80", "--ekf-budget-s", "1", "--json", str(out)]
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    doc = json.loads(out.read_text())
    small, large = doc["rows"]
    for row in (small, large):
        assert row["mapped"] > 0 and row["local_maps"] > 0
        for name in ("once", "once_joined", "once_pcg", "once_pcg_composed", "iterated"):
            assert row[f"{name}_step_count"] == 65 and row[f"{name}_join_count"] >= 2
            assert row[f"{name}_step_p95_ms"] > 0 and row[f"{name}_join_mean_ms"] > 0
            assert row[f"{name}_global_join_per_local_map_ms"] > 0
            assert row[f"{name}_start_covariance_per_local_map_ms"] > 0
        assert row["once_pcg_composed_columns_per_local_map_ms"] == 0  # the composed robot asks for no columns
        assert row["arrays_pcg_factor_mb"] == 0 < row["arrays_pcg_pcg_mb"] and row["arrays_factor_mb"] > 0
        assert row["once_pcg_fallbacks"] == 0 and 0 < row["once_pcg_state_iterations"] < 400
        assert row["arrays_after_local_maps_mb"] > row["arrays_local_maps_mb"]  # local maps added, map unchanged
    assert small["dslam_mean_ms"] > 0 and small["compare_source"] == "this run" and "dslam_mean_ms" not in large
    assert doc["exponents"]["once_join_mean_ms"] is not None
    assert "once_step_mean_ms ~ N^" in done.stdout and "| N | mapped |" in done.stdout
