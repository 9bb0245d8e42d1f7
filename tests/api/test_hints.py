"""Commands the CLI prints work exactly as printed: from the current directory, with or without a display."""

from __future__ import annotations

import os
import shlex
import subprocess
import sys
from pathlib import Path

import pytest
from conftest import write_tiny_recording

from slamreplay.api.cli.hints import has_display, rerun_sdk_version, tool, view_hint

BIN = Path(sys.executable).parent


def _run_as_printed(command: str, cwd: Path, path: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(shlex.split(command), cwd=cwd, capture_output=True, text=True, timeout=120,
                          env={**os.environ, "PATH": path})


@pytest.mark.parametrize("name", ["rerun", "slamreplay"])
def test_tool_without_activation_names_the_path(name: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Environment not activated: the hint names the executable by a path that runs from the current directory."""
    monkeypatch.setenv("PATH", "/usr/bin:/bin")
    monkeypatch.chdir(tmp_path)
    spelled = tool(name)
    assert spelled != name and Path(spelled).name == name
    assert _run_as_printed(f"{spelled} --help", tmp_path, "/usr/bin:/bin").returncode == 0


def test_tool_relative_inside_the_project(monkeypatch: pytest.MonkeyPatch) -> None:
    """From the folder holding the environment, the hint is short: .venv/bin/rerun, not an absolute path."""
    monkeypatch.setenv("PATH", "/usr/bin:/bin")
    monkeypatch.chdir(BIN.parent.parent)
    assert tool("rerun") == os.path.join(BIN.parent.name, "bin", "rerun")


def test_tool_activated_is_bare(monkeypatch: pytest.MonkeyPatch) -> None:
    """Activated (the environment's bin first on PATH): the bare name, as users type it."""
    monkeypatch.setenv("PATH", f"{BIN}:/usr/bin:/bin")
    assert tool("rerun") == "rerun" and tool("slamreplay") == "slamreplay"
    assert tool("no-such-tool-here") == "no-such-tool-here"


def test_view_hint_with_a_display(monkeypatch: pytest.MonkeyPatch) -> None:
    """With a display: one line, the native viewer."""
    monkeypatch.setenv("DISPLAY", ":0")
    assert has_display() or not sys.platform.startswith("linux")
    assert view_hint("runs/a/run.rrd") == [f"open it with: {tool('rerun')} runs/a/run.rrd"]


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="headless detection is for Linux")
def test_view_hint_headless(monkeypatch: pytest.MonkeyPatch) -> None:
    """No display: says so, and gives the web viewer (an option this rerun really has) and the copy-to-a-laptop way."""
    for var in ("DISPLAY", "WAYLAND_DISPLAY", "WAYLAND_SOCKET"):
        monkeypatch.delenv(var, raising=False)
    assert not has_display()
    text = "\n".join(view_hint("runs/a/run.rrd"))
    assert "no display here" in text
    assert f"{tool('rerun')} --web-viewer --bind 127.0.0.1 runs/a/run.rrd" in text and "http://127.0.0.1:9090" in text
    assert f"rerun-sdk {rerun_sdk_version()} " in text and rerun_sdk_version().startswith("0.")
    helptext = _run_as_printed(f"{tool('rerun')} --help", Path.cwd(), os.environ["PATH"]).stdout
    assert "--web-viewer" in helptext and "[default: 9090]" in helptext and "--bind <BIND>" in helptext


def test_error_messages_suggest_commands_that_run(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                   capsys: pytest.CaptureFixture[str]) -> None:
    """A library error suggesting `slamreplay recover ...` is printed with the command as it runs here."""
    from slamreplay.api.cli.command import main
    from slamreplay.api.cli.hints import spell_commands

    monkeypatch.setenv("PATH", "/usr/bin:/bin")
    monkeypatch.chdir(tmp_path)
    assert spell_commands("salvage it with `slamreplay recover a.mcap --out b.mcap`") == (
        f"salvage it with `{tool('slamreplay')} recover a.mcap --out b.mcap`")
    assert spell_commands("`pip install -e '.[ray]'`").startswith(f"`{tool('pip')} install")
    prose = "slamreplay reads MCAP storage; ~/slamreplay run"
    assert spell_commands(prose) == prose
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(write_tiny_recording(tmp_path / "tiny.mcap").read_bytes()[:3000])
    assert main(["run", str(cut), "--pipeline", "odometry", "--out", str(tmp_path / "r")]) == 2
    err = capsys.readouterr().err
    suggested = err.split("`")[1]
    assert suggested.startswith(tool("slamreplay") + " recover"), err
    fixed = suggested.replace("FIXED.mcap", str(tmp_path / "fixed.mcap"))
    proc = _run_as_printed(fixed, tmp_path, "/usr/bin:/bin")
    assert "Traceback" not in proc.stderr and (proc.returncode == 0 or "slamreplay: error:" in proc.stderr)
