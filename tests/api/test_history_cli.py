"""`slamreplay history`: a throwaway history of the project whose commit 3 degrades D-SLAM and commit 6 undoes it."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
from conftest import REPO, write_tiny_recording
from test_cli import assert_bad_input, run_cli

from slamreplay.replay.runs.history import read_store

DEGRADE = ("msg.ranges_m[keep], msg.bearings_rad[keep]", "msg.ranges_m[keep] * 1.03, msg.bearings_rad[keep]")


def git(repo: Path, *args: str) -> str:
    return subprocess.run(["git", "-c", "user.name=t", "-c", "user.email=t@t", "-C", str(repo), *args],
                          check=True, capture_output=True, text=True).stdout.strip()


def throwaway_history(tmp_path: Path, n: int) -> tuple[Path, list[str]]:
    """A clone of the project with n commits on top: 3 reads ranges 3 % long, 6 undoes it, the others touch
    comments only; their shas, oldest first."""
    clone = tmp_path / "clone"
    subprocess.run(["git", "clone", "-q", "--no-hardlinks", str(REPO), str(clone)], check=True)
    slam = clone / "replay" / "pipelines" / "landmark_slam.py"
    shas = []
    for i in range(1, n + 1):
        text = slam.read_text()
        if i == 3:
            assert DEGRADE[0] in text
            slam.write_text(text.replace(*DEGRADE))
            msg = "degrade: ranges read 3% long"
        elif i == 6:
            slam.write_text(text.replace(DEGRADE[1], DEGRADE[0]))
            msg = "undo the range scale"
        else:
            slam.write_text(text + f"# a comment of commit {i}\n")
            msg = f"comment {i}"
        git(clone, "commit", "-qam", msg)
        shas.append(git(clone, "rev-parse", "HEAD"))
    return clone, shas


@pytest.fixture(autouse=True)
def cache(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    monkeypatch.setenv("SLAMREPLAY_CACHE", str(tmp_path / "cache"))
    monkeypatch.setenv("SLAMREPLAY_REV_PYTHON", sys.executable)  # no venv built: still each worktree's code
    monkeypatch.setenv("SLAMREPLAY_PROGRESS_INTERVAL_S", "0")
    return tmp_path / "cache"


@pytest.mark.slow
def test_history_flags_the_degrading_and_the_undoing_commit(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                                            monkeypatch: pytest.MonkeyPatch) -> None:
    """8 commits: landmark_rmse_m worse at commit 3, better at 6, nothing else anywhere; 2 more commits run only
    their own cells; the report and the markdown link the compare reports."""
    clone, shas = throwaway_history(tmp_path, 10)
    monkeypatch.chdir(clone)
    write_tiny_recording(tmp_path / "tiny.mcap", n=60)
    suite = tmp_path / "s.toml"
    suite.write_text('[recordings.tiny]\npath = "tiny.mcap"\n[pipelines.dslam]\n')
    out, md = tmp_path / "hist", tmp_path / "summary.md"
    code, stdout, err = run_cli(["history", str(suite), "--revs", f"{shas[0]}..{shas[7]}", "--out", str(out),
                                 "--jobs", "2", "--markdown", str(md)], capsys)
    assert code == 0, err
    assert "REGRESSION  tiny/dslam/default landmark_rmse_m" in stdout, stdout
    history = read_store(out)
    assert [c.sha for c in history.commits] == shas[:8]
    assert all(s["status"] == "succeeded" for s in history.status.values())
    changes = json.loads((out / "changes.json").read_text())
    at = {(ch["commit"], ch["metric"]): ch["verdict"] for ch in changes}
    assert at[(shas[2], "landmark_rmse_m")] == "regression" and at[(shas[5], "landmark_rmse_m")] == "improvement"
    assert {ch["commit"] for ch in changes} == {shas[2], shas[5]}, changes
    assert "history s: done (8/8 cells" in err and "commit 8/8 done" in err  # plain lines: not a terminal
    page = (out / "index.html").read_text()
    assert "http" not in page.replace("http://www.w3.org", "") and "<script" not in page
    assert page.count("stroke-dasharray") == len(changes)
    rrd = next(line for line in page.splitlines() if "run.rrd" in line)
    assert "href='commits/" in rrd
    summary = md.read_text()
    assert "landmark_rmse_m" in summary and "](hist/compare/" in summary and "🔴 regression" in summary
    report = next(ch["report"] for ch in changes if ch["commit"] == shas[2])
    assert "landmark_rmse_m" in (out / report).read_text()

    lines = (out / "history.jsonl").read_text().splitlines()
    code, _out, err = run_cli(["history", str(suite), "--revs", f"{shas[0]}..{shas[9]}", "--out", str(out),
                                 "--jobs", "2"], capsys)
    assert code == 0, err
    added = (out / "history.jsonl").read_text().splitlines()
    assert added[:len(lines)] == lines  # appended, never rewritten
    new = [json.loads(x) for x in added[len(lines):]]
    assert {r["commit"] for r in new} == set(shas[8:]) and sum(r["type"] == "cell" for r in new) == 2
    assert [c.sha for c in read_store(out).commits] == shas


@pytest.mark.parametrize(("args", "pattern"), [
    (["--revs", "no-such-rev..HEAD"], r"unknown revision 'no-such-rev'"),
    (["--revs", "HEAD", "--every", "0"], r"--every must be >= 1"),
    (["--revs", "HEAD", "--jobs", "0"], r"--jobs must be >= 1"),
    (["--commits", "{tmp}/none.txt"], r"--commits .*none\.txt: cannot read it"),
])
def test_bad_input_exits_2_with_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str], args: list[str],
                                         pattern: str) -> None:
    """Every bad input: exit 2, one line, nothing written."""
    (tmp_path / "ok.toml").write_text('[recordings.x]\nsim = "sim-landmarks"\n[pipelines.odometry]\n')
    argv = ["history", str(tmp_path / "ok.toml"), "--out", str(tmp_path / "h"), "-q",
            *[a.format(tmp=tmp_path) for a in args]]
    code, _out, err = run_cli(argv, capsys)
    assert_bad_input(code, err, pattern)
    assert not (tmp_path / "h" / "history.jsonl").exists()


@pytest.mark.ray
def test_history_on_ray(tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch) -> None:
    """--executor ray: each cell a Ray task running its commit's `slamreplay run`; the same store and changes."""
    pytest.importorskip("ray")
    clone, shas = throwaway_history(tmp_path, 3)
    monkeypatch.chdir(clone)
    write_tiny_recording(tmp_path / "tiny.mcap", n=40)
    suite = tmp_path / "s.toml"
    suite.write_text('[recordings.tiny]\npath = "tiny.mcap"\n[pipelines.dslam]\n')
    code, _out, err = run_cli(["history", str(suite), "--revs", f"{shas[0]}..{shas[2]}", "--out",
                               str(tmp_path / "h"), "--executor", "ray", "--jobs", "2", "-q"], capsys)
    assert code == 0, err
    history = read_store(tmp_path / "h")
    assert [history.status[s]["status"] for s in shas] == ["succeeded"] * 3
    changes = json.loads((tmp_path / "h" / "changes.json").read_text())
    assert {ch["commit"] for ch in changes} == {shas[2]}
