"""Code versions in git's order: topological, a branch with its line, dirty after its commit, the unknown last."""

from __future__ import annotations

import subprocess
from pathlib import Path

from slamreplay.replay.runs.gitorder import order_versions, topo_order


def git(repo: Path, *args: str) -> str:
    return subprocess.run(["git", "-c", "user.name=t", "-c", "user.email=t@t", "-C", str(repo), *args],
                          check=True, capture_output=True, text=True).stdout.strip()


def commit(repo: Path, msg: str) -> str:
    git(repo, "commit", "-q", "--allow-empty", "-m", msg)
    return git(repo, "rev-parse", "HEAD")


def test_order_versions(tmp_path: Path) -> None:
    """main m0 m1 m2(merge of b0 b1 forked at m0) m3: run newest first, read back oldest first; a branch's commits
    between their fork and their merge; a dirty version right after its commit; what git lacks last, by date."""
    r = tmp_path / "r"
    r.mkdir()
    git(r, "init", "-q", "-b", "main")
    m0 = commit(r, "m0")
    git(r, "checkout", "-q", "-b", "side")
    b0, b1 = commit(r, "b0"), commit(r, "b1")
    git(r, "checkout", "-q", "main")
    m1 = commit(r, "m1")
    git(r, "merge", "-q", "--no-ff", "-m", "m2", "side")
    m2 = git(r, "rev-parse", "HEAD")
    m3 = commit(r, "m3")
    stranger = "f" * 40
    # as a service might have run them: the tip first, then backfills, a stranger, a dirty tree
    versions = [(m3, "2024-05-01T00:00:00+00:00"), (stranger, "2024-04-01T00:00:00+00:00"),
                (m1, "2024-05-02T00:00:00+00:00"), ("unknown", "2024-03-01T00:00:00+00:00"),
                (f"{m0}-dirty+abc", "2024-05-03T00:00:00+00:00"), (b1, "2024-05-04T00:00:00+00:00"),
                (m0, "2024-05-05T00:00:00+00:00"), (m2, "2024-05-06T00:00:00+00:00"),
                (b0, "2024-05-07T00:00:00+00:00")]
    order = order_versions(r, versions)
    got = [versions[i][0] for i, _ in order]
    assert got[:2] == [m0, f"{m0}-dirty+abc"]  # uncommitted changes on m0 right after it
    main = [v for v in got if v in (m0, m1, m2, m3)]
    assert main == [m0, m1, m2, m3]  # the first-parent line in its order
    assert got.index(b0) < got.index(b1) < got.index(m2) and got.index(b0) > got.index(m0)
    assert got[-2:] == ["unknown", stranger]  # unknown to git: after the rest, by date
    notes = dict(order)
    assert all(notes[versions.index(v)] == "" for v in versions if v[0] not in ("unknown", stranger))
    assert "not a commit sha: placed by date" in notes[3] and "not a commit of the repository" in notes[1]
    assert topo_order(r, [m3, m0]) == [m0, m3]
    nogit = order_versions(None, versions[:3])
    assert [i for i, _ in nogit] == [1, 0, 2] and all("no git repository" in n for _, n in nogit)
