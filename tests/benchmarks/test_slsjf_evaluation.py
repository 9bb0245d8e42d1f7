"""The SLSJF evaluation's batch optima (benchmarks/slsjf_evaluation.py) on a short paper-scenario recording."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import pytest

from slamreplay.recorder.sim import LandmarkSimConfig, simulate_landmarks

BENCH = Path(__file__).resolve().parents[2] / "benchmarks" / "slsjf_evaluation.py"


@pytest.fixture(scope="module")
def evaluation():  # type: ignore[no-untyped-def]
    spec = importlib.util.spec_from_file_location("slsjf_evaluation", BENCH)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules["slsjf_evaluation"] = module
    spec.loader.exec_module(module)
    return module


def test_batch_optimum_from_the_filter_is_the_one_grown_from_dead_reckoning(  # type: ignore[no-untyped-def]
        evaluation, tmp_path: Path) -> None:
    """Levenberg-Marquardt started from EKF-SLAM's estimate and the incremental solve grown from dead reckoning
    reach the same optimum (landmark RMSE to 10 micrometres, chi2 to 1e-6); the causal optimum, EKF-SLAM and SLSJF
    are scored at the same scans, each within a few centimetres of the truth on this 120 s world."""
    rec = tmp_path / "sim.mcap"
    simulate_landmarks(rec, LandmarkSimConfig(duration_s=120.0), seed=5)
    fast = evaluation.batch_optimum(rec, tmp_path / "fast", causal_every=100)
    slow = evaluation.batch_optimum(rec, tmp_path / "slow", incremental=True)
    assert fast["converged"] and slow["converged"] and fast["poses"] == slow["poses"] == 601
    assert abs(fast["landmark_rmse_m"] - slow["landmark_rmse_m"]) < 1e-5
    assert abs(fast["chi2"] - slow["chi2"]) < 1e-6 * slow["chi2"]
    assert fast["landmark_rmse_m"] < 0.1
    causal = fast["causal"]
    assert causal["scans"] == 6
    for name in ("causal_optimum", "ekfslam", "slsjf"):
        assert 0.0 < causal[name] < 0.1, name
