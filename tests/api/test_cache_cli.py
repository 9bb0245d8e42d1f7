"""`slamreplay cache`: the revision cache listed and pruned least recently used first, never what is in use."""

from __future__ import annotations

import os
import sys
import time
from pathlib import Path

import pytest
from test_cli import assert_bad_input, run_cli

from slamreplay.replay.runs import rev_cache
from slamreplay.replay.runs.revisions import prepare_revision

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "replay"))
from test_rev_envs import git, make_project


@pytest.fixture
def project(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> tuple[Path, list[str]]:
    """A throwaway slamreplay-named repository of 4 commits (tests/replay/test_rev_envs.py), and its shas."""
    return make_project(tmp_path, monkeypatch)


def age(entry: Path, seconds_ago: float) -> None:
    """Make ``entry``'s last use ``seconds_ago``."""
    t = time.time() - seconds_ago
    os.utime(entry / "used", (t, t))


def test_prune_least_recently_used_first_never_one_in_use(project: tuple[Path, list[str]], tmp_path: Path,
                                                          capsys: pytest.CaptureFixture[str]) -> None:
    """Oldest first down to --limit, skipping the revision whose use-lock a running job holds; --all then
    leaves only that one (and its environment); git forgets the removed worktrees."""
    repo, shas = project
    cache = tmp_path / "cache"
    for sha in shas[:3]:
        prepare_revision(repo, sha, cache)  # released at once
    held = prepare_revision(repo, shas[1], cache)  # in use, as while a compare runs its cells
    env = cache / "envs" / Path(held.command[0]).parents[1].name
    for i, sha in enumerate(shas[:3]):
        age(cache / "revs" / sha, 300 - 100 * i)  # shas[0] least recently used, then shas[1], shas[2]
    age(env, 0)
    sizes = {e.name: e.size for e in rev_cache.entries(cache)}
    total = sum(sizes.values())
    limit = total - sizes[shas[0]] - 1  # removing shas[0] is not enough; shas[1] is in use: shas[2] goes too
    code, out, err = run_cli(["cache", "prune", "--limit", f"{limit}b"], capsys)
    assert code == 0, err
    assert f"removed revision {shas[0][:16]}" in out and f"removed revision {shas[2][:16]}" in out, out
    assert out.index(shas[0][:16]) < out.index(shas[2][:16]) and "removed 2; kept 1 in use" in out, out
    assert sorted(p.name for p in (cache / "revs").iterdir() if p.is_dir()) == [shas[1]]
    assert len(git(repo, "worktree", "list").splitlines()) == 2
    code, out, err = run_cli(["cache", "prune", "--all"], capsys)
    assert code == 0 and "still over: the rest is in use" in out, out
    assert (cache / "revs" / shas[1] / "src").is_dir() and env.is_dir()
    del held  # the job ended: nothing is in use
    code, out, err = run_cli(["cache", "prune", "--all", "-q"], capsys)
    assert code == 0 and out == ""
    assert [p for p in (cache / "revs").iterdir() if p.is_dir()] == [] and not env.exists()
    assert len(git(repo, "worktree", "list").splitlines()) == 1


def test_cache_list(project: tuple[Path, list[str]], tmp_path: Path, capsys: pytest.CaptureFixture[str],
                    monkeypatch: pytest.MonkeyPatch) -> None:
    """One header, then each revision (sha, subject) and environment (dependencies, revisions using it) with
    size, last use and whether it is in use; `cache` alone lists; --json for scripts."""
    repo, shas = project
    cache = tmp_path / "cache"
    prepare_revision(repo, shas[1], cache)
    held = prepare_revision(repo, shas[2], cache)
    monkeypatch.setenv("SLAMREPLAY_CACHE_LIMIT_GB", "2.5")
    code, out, err = run_cli(["cache", "list"], capsys)
    assert code == 0, err
    lines = out.splitlines()
    assert lines[0].startswith(f"revision cache {cache}: 2 revision(s), 1 environment(s), ")
    assert lines[0].endswith("of its 2.5 GiB limit ($SLAMREPLAY_CACHE_LIMIT_GB)") and "LAST USE" in lines[1]
    rows = {line.split()[1]: line for line in lines[2:]}
    assert set(rows) == {shas[1][:10], shas[2][:10], Path(held.command[0]).parents[1].name}
    assert "commit 1" in rows[shas[1][:10]] and " - " in rows[shas[1][:10]]
    assert "in use" in rows[shas[2][:10]] and ("MiB" in rows[shas[2][:10]] or "KiB" in rows[shas[2][:10]])
    assert rows[Path(held.command[0]).parents[1].name].split()[0] == "environment"
    assert "0 dependencies, 2 revision(s)" in rows[Path(held.command[0]).parents[1].name]
    assert run_cli(["cache"], capsys)[1] == out
    code, out, _ = run_cli(["cache", "list", "--json"], capsys)
    assert code == 0 and '"kind": "environment"' in out and '"in_use": true' in out


def test_bad_limits_are_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                 monkeypatch: pytest.MonkeyPatch) -> None:
    """A --limit or $SLAMREPLAY_CACHE_LIMIT_GB that is not a size: exit 2, one line saying what a size is."""
    monkeypatch.setenv("SLAMREPLAY_CACHE", str(tmp_path / "cache"))
    for bad in ("12X", "-1", "lots"):
        code, _, err = run_cli(["cache", "prune", "--limit", bad], capsys)
        assert_bad_input(code, err, rf"--limit '{bad}': give a size such as 10G, 500M or 2.5 \(GB\)")
    monkeypatch.setenv("SLAMREPLAY_CACHE_LIMIT_GB", "ten")
    code, _, err = run_cli(["cache"], capsys)
    assert_bad_input(code, err, r"\$SLAMREPLAY_CACHE_LIMIT_GB 'ten': give a size")
