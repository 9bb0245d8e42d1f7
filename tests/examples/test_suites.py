"""The example suites (examples/suites/*.toml) parse, and each runs more than one cell."""

from __future__ import annotations

from pathlib import Path

import pytest

from slamreplay.replay.runs.suite import load_suite

SUITES = sorted((Path(__file__).resolve().parents[2] / "examples" / "suites").glob("*.toml"))


@pytest.mark.parametrize("path", SUITES, ids=[p.stem for p in SUITES])
def test_example_suite_parses(path: Path) -> None:
    suite = load_suite(path)
    assert len(suite.cells()) > 1


def test_presets_example_writes_the_paper_preset_out() -> None:
    from slamreplay.replay.engine.pipeline import get_pipeline

    suite = load_suite(next(p for p in SUITES if p.stem == "presets"))
    assert suite.pipelines["dslam"] == {"default": {}, "paper": get_pipeline("dslam").presets["paper"]}
