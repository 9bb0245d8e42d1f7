"""Code versions in git's order: what a history of commits is read along, whenever each commit ran.

A history (``slamreplay history``, the service's suite history) is judged point after point, so its
points must stand in the order the code was written, not the order it happened to be run in: a
commit backfilled after a newer one still comes before it. :func:`order_versions` places each code
version (a commit sha, or ``<sha>-dirty...`` for uncommitted changes on it) by
``git rev-list --topo-order``: every commit after its ancestors, so a first-parent line keeps its
order and a branch's commits stay together between its fork and its merge. What the repository
does not know (another clone's commit, a version string that names no commit, or everything when
there is no repository) goes after all of that, by date, with a note saying so.
"""

from __future__ import annotations

import re
import subprocess
from collections.abc import Sequence
from datetime import datetime
from pathlib import Path

SHA = re.compile(r"([0-9a-f]{40})(-dirty.*)?")
TIMEOUT_S = 120


def _git(repo: Path, *args: str, stdin: str | None = None) -> str | None:
    """Git's output, or None when it fails (a history is still drawn without git's help)."""
    try:
        done = subprocess.run(["git", *args], cwd=repo, input=stdin, capture_output=True, text=True,
                              timeout=TIMEOUT_S)
    except (OSError, subprocess.SubprocessError):
        return None
    return done.stdout if done.returncode == 0 else None


def known_commits(repo: Path, shas: Sequence[str]) -> set[str]:
    """The shas of ``shas`` (full, 40 hex digits) that name a commit of ``repo``."""
    if not shas:
        return set()
    out = _git(repo, "cat-file", "--batch-check=%(objectname) %(objecttype)", stdin="".join(f"{s}\n" for s in shas))
    return {line.split()[0] for line in (out or "").splitlines() if line.endswith(" commit")} & set(shas)


def topo_order(repo: Path, shas: Sequence[str]) -> list[str]:
    """``shas`` (commits of ``repo``) in git's order, oldest first (``git rev-list --topo-order --reverse``)."""
    if len(shas) < 2:
        return list(shas)
    base = (_git(repo, "merge-base", "--octopus", *shas) or "").split()
    stop = ["--not", f"{base[0]}^@"] if base else []  # walk from their common ancestor, not the whole repository
    listed = (_git(repo, "rev-list", "--topo-order", "--reverse", *shas, *stop) or "").split()
    wanted = set(shas)
    return [s for s in listed if s in wanted]


def stamp(date: str) -> float:
    """Seconds since the epoch of an ISO 8601 date; inf when it is not one (such a date sorts last)."""
    try:
        return datetime.fromisoformat(date).timestamp()
    except ValueError:
        return float("inf")


def order_versions(repo: Path | None, versions: Sequence[tuple[str, str]]) -> list[tuple[int, str]]:
    """The order of ``versions`` ((code version, ISO date) pairs) in ``repo``: (index into ``versions``, note).

    Commits ``repo`` knows come first, in :func:`topo_order`, each ``<sha>-dirty...`` right after its ``<sha>``;
    the note is "". The others follow by date, then their place in ``versions``, each with a note saying why git
    did not place it.
    """
    base = {v: m.group(1) for v, _ in versions if (m := SHA.fullmatch(v))}
    rank: dict[str, int] = {}
    if repo is not None:
        known = known_commits(repo, sorted(set(base.values())))
        rank = {s: i for i, s in enumerate(topo_order(repo, sorted(known)))}
        if len(rank) < len(known):  # git could not order them after all: place none rather than some wrongly
            rank = {}
    placed, unplaced = [], []
    for i, (version, date) in enumerate(versions):
        b = base.get(version)
        if b is not None and b in rank:
            placed.append(((rank[b], version != b, stamp(date), i), (i, "")))
            continue
        why = ("no git repository to place it" if repo is None else "not a commit sha" if b is None
               else "not a commit of the repository at " + str(repo))
        unplaced.append(((stamp(date), i), (i, f"{why}: placed by date, after the commits git orders")))
    return [x for _, x in sorted(placed)] + [x for _, x in sorted(unplaced)]
