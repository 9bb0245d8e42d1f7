"""Help that says something, "did you mean" for every name a user types, and no run directory for a bad input."""

from __future__ import annotations

import argparse
import json
import os
from pathlib import Path

import pytest
from conftest import write_tiny_recording
from test_cli import assert_bad_input, run_cli

from slamreplay.api.cli.command import build_parser
from slamreplay.recorder.sources import importer_plugins


def _subparser(parser: argparse.ArgumentParser, name: str) -> argparse.ArgumentParser:
    (sub,) = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
    found: argparse.ArgumentParser = sub.choices[name]
    return found


@pytest.mark.parametrize("source", [n for n, p in importer_plugins().items() if p.builtin])
def test_every_record_option_has_a_real_help_line(source: str) -> None:
    """Each option of each built-in simulator and importer says what it is, not just its own name."""
    parser = _subparser(_subparser(build_parser(), "record"), source)
    for action in parser._actions:
        if isinstance(action, argparse._HelpAction) or action.dest == "quiet":
            continue
        text = (action.help or "").split(" (default")[0].strip()
        bare = {action.dest, action.dest.removeprefix("cfg_"), action.dest.removeprefix("pole_"),
                action.dest.removeprefix("cfg_").replace("_", " "), action.dest.removeprefix("pole_").replace("_", " ")}
        assert text and text not in bare and len(text.split()) >= 3, f"record {source} {action.option_strings}: {text}"


def test_sim_landmarks_help_gives_unit_and_default(capsys: pytest.CaptureFixture[str],
                                                   monkeypatch: pytest.MonkeyPatch) -> None:
    """`record sim-landmarks --help`: what, unit and default, e.g. for --duration-s."""
    monkeypatch.setenv("COLUMNS", "250")
    with pytest.raises(SystemExit):
        run_cli(["record", "sim-landmarks", "--help"], capsys)
    out = capsys.readouterr().out
    assert "--duration-s FLOAT simulated time, seconds (the paper drives 30 minutes) (default: 1800.0)" in \
        " ".join(out.split())
    assert "(0.01: odometry reads 1.01 m per metre driven)" in out


def test_pipelines_name_shows_one_pipeline(capsys: pytest.CaptureFixture[str]) -> None:
    """`pipelines NAME`: that pipeline alone, each metric on its own line; --json gives its one object."""
    code, out, _ = run_cli(["pipelines", "odometry"], capsys)
    assert code == 0 and out.startswith("odometry: ") and "\nekfslam:" not in out
    assert "  needs:    /odom" in out and "  metric " in out
    code, out, _ = run_cli(["pipelines", "odometry", "--json"], capsys)
    row = json.loads(out)
    assert code == 0 and row["name"] == "odometry" and row["required_topics"] == ["/odom"] and row["metrics"]


@pytest.mark.parametrize(("args", "pattern"), [
    (["pipelines", "dslm"], r"unknown pipeline 'dslm' \(did you mean 'dslam'\?\); known pipelines: .*odometry"),
    (["run", "{rec}", "--pipeline", "ekfslm", "--out", "{tmp}/r"], r"unknown pipeline 'ekfslm' \(did you mean "
                                                                   r"'ekfslam'\?\)"),
    (["run", "{rec}", "--pipeline", "dslam", "--out", "{tmp}/r", "--set", "rang_sigma_m=0.1"],
     r"unknown config key 'rang_sigma_m' for pipeline dslam \(did you mean 'range_sigma_m'\?\); its keys are: "),
    (["run", "{rec}", "--pipeline", "dslam", "--out", "{tmp}/r", "--preset", "papr"],
     r"has no preset 'papr' \(did you mean 'paper'\?\)"),
    (["run", "{rec}", "--pipeline", "ifmi", "--out", "{tmp}/r"],
     r"has no /camera/image topic.*; or replay it through a pipeline its topics fit: dslam, ekfslam, odometry"),
])
def test_did_you_mean(tmp_path: Path, capsys: pytest.CaptureFixture[str], args: list[str], pattern: str) -> None:
    """A mistyped pipeline, config key or preset is named with the closest known one; a recording without a
    topic the pipeline needs is offered the pipelines its topics fit."""
    rec = write_tiny_recording(tmp_path / "tiny.mcap", n=30)
    code, _, err = run_cli([a.format(rec=rec, tmp=tmp_path) for a in args], capsys)
    assert_bad_input(code, err, pattern)


@pytest.mark.parametrize(("make", "pattern"), [
    (lambda d: d / "tyop.mcap", r"tyop\.mcap: no such file or directory"),
    (lambda d: (d / "notes.mcap").write_text("not a recording") and d / "notes.mcap", r"is not an MCAP file"),
    (lambda d: (d / "empty.mcap").touch() or d / "empty.mcap", r"is empty"),
    (lambda d: d, r"is a directory with no \.mcap file"),
    (lambda d: (d / "bag" / "x.mcap").mkdir(parents=True) or d / "bag", r"x\.mcap is a directory: give an \.mcap"),
    (lambda d: os.mkfifo(d / "fifo.mcap") or d / "fifo.mcap", r"not a regular file \(a pipe, socket or device\)"),
])
def test_a_bad_input_leaves_no_run_directory(tmp_path: Path, capsys: pytest.CaptureFixture[str], make: object,
                                             pattern: str) -> None:
    """An input that does not exist or is not a recording: exit 2, one line, and no run directory under runs/."""
    source = tmp_path / "in"
    source.mkdir()
    path = make(source)  # type: ignore[operator]
    code, _, err = run_cli(["run", str(path), "--pipeline", "odometry", "--out", str(tmp_path / "runs" / "r")],
                           capsys)
    assert_bad_input(code, err, pattern)
    assert not (tmp_path / "runs").exists()
