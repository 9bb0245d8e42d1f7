"""Long commands talk when stderr is not a terminal: plain progress lines, as pytest and asv print them."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest
from conftest import write_tiny_recording

from slamreplay.api.cli import demo
from slamreplay.api.cli.command import main
from slamreplay.api.cli.progress import PlainProgress, duration
from slamreplay.replay.runs import suite_run

SLAMREPLAY = str(Path(sys.executable).parent / "slamreplay")


def cli(*args: str, interval_s: float = 0.0) -> subprocess.CompletedProcess[str]:
    """Run slamreplay with stderr to a pipe (not a terminal), a progress line allowed every ``interval_s``."""
    env = {**os.environ, "SLAMREPLAY_PROGRESS_INTERVAL_S": str(interval_s)}
    return subprocess.run([SLAMREPLAY, *args], capture_output=True, text=True, env=env, timeout=600)


def test_plain_lines_start_every_interval_and_end(capsys: pytest.CaptureFixture[str]) -> None:
    """A line at the first count, then at most one per interval with percent, counts, elapsed time and an ETA from
    the rate since the first count after it (1,140 messages in 7 s: 1,800 more take 11 s)."""
    now = [0.0]
    p = PlainProgress("run dslam on s.mcap", "messages", clock=lambda: now[0], every_s=10.0)
    for done, t in ((30, 1.0), (60, 5.0), (1200, 12.0), (1300, 13.0), (3000, 30.0)):
        now[0] = t
        p.update(done, 3000)
    p.finished()
    assert capsys.readouterr().err.splitlines() == [
        "run dslam on s.mcap: started (3,000 messages)",
        "run dslam on s.mcap: 40% (1,200/3,000 messages, 12 s, ETA 11 s)",
        "run dslam on s.mcap: done (3,000/3,000 messages in 30 s)",
    ]


def test_the_eta_leaves_out_the_work_before_the_first_count(capsys: pytest.CaptureFixture[str]) -> None:
    """A step that computes for 51 s before its first count (Victoria Park's reference) gets an ETA from the
    rate of its counts, not 97 hours."""
    now = [0.0]
    p = PlainProgress("record victoria-park", "steps", clock=lambda: now[0], every_s=10.0)
    now[0] = 51.0
    p.update(1, 6969)
    now[0] = 62.0
    p.update(3485, 6969)  # 3,484 steps in 11 s: 3,484 more take 11 s
    lines = capsys.readouterr().err.splitlines()
    assert lines[1] == "record victoria-park: 0% (1/6,969 steps, 51 s)"  # no rate yet: no ETA
    assert lines[2] == "record victoria-park: 50% (3,485/6,969 steps, 62 s, ETA 11 s)"


def test_the_eta_leaves_out_a_first_item_that_paid_a_one_off_cost(capsys: pytest.CaptureFixture[str]) -> None:
    """`history` over 60 commits: the first cell waits 180 s for the shared environment, the next take 2 s each.
    Once a second cell is done the ETA comes from the cells after the first (2 s each: 58 more take about 2
    minutes), not from the first's 3 minutes (once 2.3 hours for a 13-minute job, issue 38)."""
    now = [0.0]
    p = PlainProgress("history s", "cells", clock=lambda: now[0], every_s=1.0)
    p.update(0, 60)
    now[0] = 180.0
    p.update(1, 60)  # only the first is done: its own rate is all there is
    for k in range(2, 7):
        now[0] = 180.0 + 2.0 * (k - 1)
        p.update(k, 60)
    lines = capsys.readouterr().err.splitlines()
    assert lines[1] == "history s: 2% (1/60 cells, 3.0 min, ETA 3.0 h)"
    assert lines[2] == "history s: 3% (2/60 cells, 3.0 min, ETA 1.9 min)"
    assert lines[-1] == "history s: 10% (6/60 cells, 3.2 min, ETA 1.8 min)"  # 54 more at 2 s


def test_reused_cells_are_named_and_left_out_of_the_eta(capsys: pytest.CaptureFixture[str]) -> None:
    """suite run: cells served from the cache are counted apart; the ETA comes from the cells that ran."""
    now = [0.0]
    p = PlainProgress("suite s", "cells", reused="reused", clock=lambda: now[0], every_s=5.0)
    p.update(2, 24)
    now[0] = 50.0
    p.update(7, 24)  # 5 cells in 50 s: 17 more take 170 s
    assert capsys.readouterr().err.splitlines() == [
        "suite s: started (24 cells, 2 reused)",
        "suite s: 29% (7/24 cells, 2 reused, 50 s, ETA 2.8 min)",
    ]
    assert (duration(3), duration(600), duration(7200)) == ("3 s", "10.0 min", "2.0 h")


def test_run_prints_progress_lines_to_a_pipe_and_nothing_with_quiet(tmp_path: Path) -> None:
    """`run` with stderr to a pipe: a start line, percent lines, an end line; `-q`: no line at all."""
    rec = write_tiny_recording(tmp_path / "tiny.mcap", n=200)
    done = cli("run", str(rec), "--pipeline", "odometry", "--out", str(tmp_path / "r"))
    assert done.returncode == 0, done.stderr
    lines = done.stderr.splitlines()
    assert re.fullmatch(r"run odometry on tiny\.mcap: started \([\d,]+ messages\)", lines[0]), lines
    assert any(re.fullmatch(r"run odometry on tiny\.mcap: \d+% \([\d,]+/[\d,]+ messages, \d+ s(, ETA .+)?\)", x)
               for x in lines), lines
    assert re.fullmatch(r"run odometry on tiny\.mcap: done \(([\d,]+)/\1 messages in \d+ s\)", lines[-1]), lines
    quiet = cli("run", str(rec), "--pipeline", "odometry", "--out", str(tmp_path / "q"), "-q")
    assert quiet.returncode == 0 and quiet.stderr == ""


def test_record_and_suite_run_talk(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                   monkeypatch: pytest.MonkeyPatch) -> None:
    """`record sim-landmarks` and `suite run` print start and end lines; the second suite run says its cells
    were reused."""
    done = cli("record", "sim-landmarks", "--duration-s", "20", "--out", str(tmp_path / "s.mcap"))
    assert done.returncode == 0, done.stderr
    assert done.stderr.startswith("record sim-landmarks: started (") and "record sim-landmarks: done (" in done.stderr
    write_tiny_recording(tmp_path / "tiny.mcap", n=40)
    suite = tmp_path / "s.toml"
    suite.write_text('name = "talk"\nseeds = [0, 1]\n[recordings.tiny]\npath = "tiny.mcap"\n[pipelines.odometry]\n')
    monkeypatch.setenv("SLAMREPLAY_CACHE", str(tmp_path / "cache"))
    # in this process, with the code version fixed: edits to the checkout between the two runs would change it
    monkeypatch.setattr(suite_run, "code_version", lambda: "fixed")
    errs = []
    for _ in range(2):
        assert main(["suite", "run", str(suite), "--out", str(tmp_path / "res")]) == 0
        errs.append(capsys.readouterr().err)
    assert "suite talk: started (2 cells)" in errs[0] and "suite talk: done (2/2 cells in " in errs[0], errs[0]
    assert "suite talk: started (2 cells, 2 reused)" in errs[1], errs[1]


def test_demo_talks(tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch) -> None:
    """`demo` (here on one tiny recording instead of the simulations) prints each replay's progress lines."""
    rec = write_tiny_recording(tmp_path / "tiny.mcap", n=60)
    monkeypatch.setattr(demo, "_recordings", lambda out, data, quiet: [rec])
    monkeypatch.setitem(demo.PIPELINES, "tiny", ("odometry",))
    assert demo.run_demo(tmp_path / "demo", None) == 0
    err = capsys.readouterr().err
    assert "run odometry on tiny.mcap: started (" in err and "run odometry on tiny.mcap: done (" in err, err
