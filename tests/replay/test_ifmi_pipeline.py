"""Pipeline ifmi on a small seeded sim-seabed survey: loop closures, chi2 and ATE drop, determinism."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from slamreplay.recorder.sim.seabed import SeabedSimConfig, simulate_seabed
from slamreplay.replay.runs.run import run_recording

CONFIG = SeabedSimConfig(legs=3, leg_length_m=3.0)


@pytest.fixture(scope="module")
def survey(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A small seeded survey recording."""
    path = tmp_path_factory.mktemp("seabed") / "survey.mcap"
    simulate_seabed(path, CONFIG, seed=2)
    return path


def test_map_improves_and_is_deterministic(survey: Path, tmp_path: Path) -> None:
    """Loop closures are found; optimization cuts chi2 and ATE; two runs give identical metrics."""
    a = run_recording(survey, "ifmi", tmp_path / "a", seed=0)
    b = run_recording(survey, "ifmi", tmp_path / "b", seed=0)
    m = a.metrics
    assert m["loop_closures"] >= 3 and m["registrations_accepted"] >= m["images"] - 1
    assert m["chi2_final"] < 0.2 * m["chi2_initial"]
    assert m["ate_rmse_px"] < m["ate_rmse_px_initial"]
    assert m["rotation_error_deg_median"] < 0.3 and m["translation_error_px_median"] < 1.0
    assert (tmp_path / "a" / "metrics.json").read_bytes() == (tmp_path / "b" / "metrics.json").read_bytes()
    assert json.loads((tmp_path / "a" / "metrics.json").read_text())["pipeline"] == "ifmi"
    assert b.status == "succeeded"


def test_bad_config_is_rejected(survey: Path, tmp_path: Path) -> None:
    """A bad config value fails before anything is written."""
    from slamreplay.replay.errors import ReplayError

    with pytest.raises(ReplayError, match="min_pnr"):
        run_recording(survey, "ifmi", tmp_path / "c", config={"min_pnr": "-1"})
    with pytest.raises(ReplayError, match="covariance must be one of paper, calibrated"):
        run_recording(survey, "ifmi", tmp_path / "d", config={"covariance": "eq10"})


def test_calibrated_covariance_weighs_the_graph_near_chi2_per_dof_one(survey: Path, tmp_path: Path) -> None:
    """``covariance=calibrated``: the optimized chi2 per degree of freedom near 1 (the paper's: ~0.06), ATE drops."""
    m = run_recording(survey, "ifmi", tmp_path / "cal", seed=0, config={"covariance": "calibrated"}).metrics
    assert 0.3 < m["chi2_per_dof"] < 3.0 and m["ate_rmse_px"] < m["ate_rmse_px_initial"]
    assert m["loop_closures"] >= 3 and m["edges_rejected"] <= 0.1 * m["registrations_accepted"]


def test_images_too_small_for_ifmi_are_a_clear_error(tmp_path: Path) -> None:
    """20x20 images: one line naming the size iFMI needs (it was an internal error)."""
    from slamreplay.recorder import Recorder
    from slamreplay.recorder.messages import CameraImage
    from slamreplay.replay.errors import ReplayError
    from slamreplay.replay.runs.run import run_recording

    rng = np.random.default_rng(0)
    with Recorder(tmp_path / "tiny.mcap", source={"test": "tiny images"}) as rec:
        for k in range(3):
            rec.write("/camera/image", CameraImage(1_000_000_000 + k * 100_000_000,
                                                   rng.integers(0, 255, (20, 20), dtype=np.uint8)))
    with pytest.raises(ReplayError, match=r"image 0 at 1000000000 ns is 20x20 pixels; iFMI needs at least 32x32"):
        run_recording(tmp_path / "tiny.mcap", "ifmi", tmp_path / "run")
    manifest = json.loads((tmp_path / "run" / "manifest.json").read_text())
    assert manifest["status"] == "failed" and not (tmp_path / "run" / "run.rrd").exists()
