"""`slamreplay demo`: what runs on what, and that it never deletes a folder it did not make."""

from __future__ import annotations

from pathlib import Path

import pytest

from slamreplay.api.cli.demo import PIPELINES, run_demo
from slamreplay.replay.engine.pipeline import all_pipelines


def test_every_demo_pipeline_exists() -> None:
    """MRCLAM needs no setting from the demo: its noise travels in the recording (test_config_layers.py)."""
    known = set(all_pipelines())
    assert {p for names in PIPELINES.values() for p in names} <= known


def test_refuses_a_folder_it_did_not_make(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    (tmp_path / "precious.txt").write_text("keep me")
    assert run_demo(tmp_path, None, quiet=True) == 2
    assert "not a demo folder" in capsys.readouterr().err
    assert (tmp_path / "precious.txt").read_text() == "keep me"


def test_next_steps_work_as_printed(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The demo's closing hints name runnable commands: the environment's rerun and slamreplay, and a real diff."""
    import shlex
    import subprocess

    from conftest import write_tiny_recording

    from slamreplay.api.cli.demo import next_steps
    from slamreplay.replay.runs.run import run_recording

    rec = write_tiny_recording(tmp_path / "tiny.mcap")
    ekf = run_recording(rec, "ekfslam", tmp_path / "runs" / "ekf", seed=1)
    dslam = run_recording(rec, "dslam", tmp_path / "runs" / "dslam", seed=1)
    monkeypatch.setenv("PATH", "/usr/bin:/bin")  # not activated
    monkeypatch.setenv("DISPLAY", ":0")
    monkeypatch.chdir(tmp_path)
    lines = next_steps([ekf, dslam], {("sim-landmarks", "ekfslam"): ekf.run_dir,
                                      ("sim-landmarks", "dslam"): dslam.run_dir})
    assert lines[-1].startswith("To type slamreplay and rerun without the path: source ") and "activate" in lines[-1]
    diff = shlex.split(lines[-2].split(": ", 1)[1])
    proc = subprocess.run(diff, capture_output=True, text=True, env={"PATH": "/usr/bin:/bin"}, timeout=300)
    assert proc.returncode in (0, 1) and "What changed" in proc.stdout, proc.stderr
    opener = shlex.split(lines[1])
    assert Path(opener[0]).name == "rerun" and Path(opener[1]).is_file()
    monkeypatch.delenv("DISPLAY")
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_SOCKET", raising=False)
    assert any("--web-viewer" in line for line in next_steps([ekf], {}))
