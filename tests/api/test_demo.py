"""`slamreplay demo`: what runs on what, and that it never deletes a folder it did not make."""

from __future__ import annotations

from pathlib import Path

import pytest

from api.demo import PIPELINES, _config, run_demo
from replay.pipeline import all_pipelines, get_pipeline, resolve_config


def test_every_demo_pipeline_exists_and_mrclam_gets_its_noise_settings() -> None:
    known = set(all_pipelines())
    assert {p for names in PIPELINES.values() for p in names} <= known
    for pipeline in ("dslam", "ekfslam"):
        cfg = _config("mrclam6-robot1", pipeline)
        assert cfg is not None
        resolve_config(get_pipeline(pipeline), cfg)  # every key is a real config key
        assert _config("sim-landmarks", pipeline) is None


def test_refuses_a_folder_it_did_not_make(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    (tmp_path / "precious.txt").write_text("keep me")
    assert run_demo(tmp_path, None, quiet=True) == 2
    assert "not a demo folder" in capsys.readouterr().err
    assert (tmp_path / "precious.txt").read_text() == "keep me"
