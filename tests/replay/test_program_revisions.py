"""Revisions of an external program's own repository: compare rev: inside it runs this slamreplay on the program's
worktree at each revision, names the repository, and finds the commit that made the program worse."""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import pytest
from conftest import write_tiny_recording

from slamreplay.api.cli.command import main
from slamreplay.recorder.plugins import refresh
from slamreplay.replay.engine.declared import DECLARATIONS_ENV
from slamreplay.replay.errors import ReplayError
from slamreplay.replay.runs.revisions import is_slamreplay_checkout, repository_of_revisions
from tests.replay.test_external import DEAD_RECKONING
from tests.replay.test_named_changes import EDITED

DECLARATION = """[pipelines.ext]
command = ["{python}", "prog.py", "{out}/trajectory.tum"]
exports = ["odometry_csv"]
stdin = "{exports}/odometry.csv"
"""


def git(repo: Path, *args: str) -> str:
    return subprocess.run(["git", "-c", "user.name=t", "-c", "user.email=t@t", *args], cwd=repo, check=True,
                          capture_output=True, text=True).stdout


@pytest.fixture
def program_repo(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """A program's repository with two commits: dead reckoning, then the same with a heading drift."""
    repo = tmp_path / "prog"
    repo.mkdir()
    git(repo, "init", "-q", "-b", "main")
    (repo / "ext.toml").write_text(DECLARATION)
    (repo / "prog.py").write_text(DEAD_RECKONING)
    git(repo, "add", ".")
    git(repo, "commit", "-q", "-m", "dead reckoning")
    (repo / "prog.py").write_text(EDITED)
    git(repo, "commit", "-q", "-am", "heading drift")
    monkeypatch.setenv(DECLARATIONS_ENV, str(repo / "ext.toml"))
    monkeypatch.setenv("SLAMREPLAY_CACHE", str(tmp_path / "cache"))
    monkeypatch.chdir(repo)
    refresh()
    return repo


def test_compare_two_revisions_of_a_program(program_repo: Path, tmp_path: Path,
                                            capsys: pytest.CaptureFixture[str]) -> None:
    """rev:HEAD~1 against rev:HEAD of the program's repository: the note names the repository, the program's file
    hash is a change, the worse heading is a regression (exit 1); slamreplay itself is the same on both sides."""
    assert not is_slamreplay_checkout(program_repo)
    assert "the program repository" in repository_of_revisions(program_repo)
    rec = write_tiny_recording(tmp_path / "tiny.mcap")
    suite = tmp_path / "s.toml"
    suite.write_text(f'seeds = [0]\n[recordings.r]\npath = "{rec}"\n[pipelines.ext]\n')
    code = main(["compare", "rev:HEAD~1", "rev:HEAD", "--suite", str(suite), "--json"])
    captured = capsys.readouterr()
    doc = json.loads(captured.out)
    assert code == 1, captured.err
    assert "is a revision of the program repository" in captured.err
    assert any(c["field"].endswith("pipeline_origin.files_sha256.prog.py") for c in doc["changes"])
    assert any(r.endswith("ape_rmse_m") for r in doc["regressions"])
    assert len(doc["commits"]) == 1 and "heading drift" in doc["commits"][0]


def test_a_repository_with_no_declaration_is_refused(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                    capsys: pytest.CaptureFixture[str]) -> None:
    """rev: in a git repository that is neither slamreplay's nor holds a declaration: one line, exit 2, no build."""
    repo = tmp_path / "other"
    repo.mkdir()
    git(repo, "init", "-q")
    (repo / "README").write_text("x")
    git(repo, "add", ".")
    git(repo, "commit", "-q", "-m", "x")
    monkeypatch.chdir(repo)
    monkeypatch.delenv(DECLARATIONS_ENV, raising=False)
    monkeypatch.setenv("SLAMREPLAY_CACHE", str(tmp_path / "cache"))
    with pytest.raises(ReplayError, match="neither slamreplay's repository nor holds a pipeline declaration"):
        repository_of_revisions(repo)
    suite = tmp_path / "s.toml"
    suite.write_text(f'seeds = [0]\n[recordings.r]\npath = "{write_tiny_recording(tmp_path / "t.mcap")}"\n'
                     f'[pipelines.odometry]\n')
    assert main(["compare", "rev:HEAD", "rev:HEAD", "--suite", str(suite)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "neither slamreplay's repository" in err[0]
    assert not (tmp_path / "cache" / "revs").exists() or not any((tmp_path / "cache" / "revs").iterdir())
