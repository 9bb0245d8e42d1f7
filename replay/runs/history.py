"""Metric history across commits: a suite run at each selected commit, into one append-only store.

``run_history`` runs every cell of a suite at each commit with that commit's own code (the cached
worktree and environment of ``slamreplay.replay.runs.revisions``, as ``compare rev:`` builds them)
and appends each result as it ends to ``DIR/history.jsonl``, one JSON object a line:

- a *cell* row (``"type": "cell"``): the commit, the cell (recording, recording seed, pipeline,
  variant, seed, config), its cache key, status and error, every metric with its direction, unit
  and tolerance (the row of ``results.jsonl``), and its run directory relative to ``DIR``;
- a *commit* row (``"type": "commit"``), written once all of a commit's cells have ended: its
  date and subject, and ``succeeded``, ``partial`` (some cells failed), ``failed`` (all did) or
  ``build_failed`` (its environment did not build, with the error: the history goes on).

The store is only ever appended to, a line at a time, so a history stopped part-way keeps every
cell it finished (a torn last line is ignored) and a later call runs only what is missing: cells
whose key (inputs and commit) has a row, and commits that did not build, are not run again unless
``retry_failed``. Runs go to ``DIR/commits/<sha>/runs/<cell>-<key>/``, and each finished commit
gets ``DIR/commits/<sha>/results.jsonl``, so that ``slamreplay compare`` reads any two of them;
a run that ``compare rev:`` or ``bisect`` already made for the same key in the cache
(``<cache>/results/<sha>/``) is copied rather than run again.

Cells of all commits share one pool of ``workers``: a commit's environment is built while the
cells of the commits before it run.
"""

from __future__ import annotations

import fcntl
import json
import os
import shutil
import subprocess
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import FIRST_COMPLETED, Future, ThreadPoolExecutor, wait
from contextlib import contextmanager
from dataclasses import dataclass, field, replace
from datetime import datetime
from pathlib import Path
from typing import Any, TextIO

from slamreplay.recorder.files import atomic_write
from slamreplay.replay.errors import ReplayError
from slamreplay.replay.runs.gitorder import order_versions
from slamreplay.replay.runs.revisions import Revision, prepare_revision, resolve, run_cell
from slamreplay.replay.runs.suite import Suite
from slamreplay.replay.runs.suite_run import (
    CellJob,
    cache_dir,
    is_cached,
    materialize,
    normalized_row,
    plan,
    row,
    stamp_run,
    write_results,
)

STORE = "history.jsonl"
RunCell = Callable[[Revision, CellJob], str | None]


@dataclass(frozen=True, slots=True)
class Commit:
    """A commit of the history: full sha, committer date (ISO 8601), subject line, and how many commits its
    history holds (``git rev-list --count``: larger than any of its ancestors', so it orders a line of history
    where dates tie to the second)."""

    sha: str
    date: str
    subject: str
    generation: int = 0
    note: str = ""  # why it stands where it does when git could not place it (``git_order``)

    @property
    def short(self) -> str:
        return self.sha[:10]


@dataclass
class History:
    """What a store holds: its commits in history order, and the cell rows of each."""

    commits: list[Commit]
    status: dict[str, dict[str, Any]]  # sha -> its commit row (absent while its cells are running)
    rows: dict[str, list[dict[str, Any]]] = field(default_factory=dict)  # sha -> cell rows, run_dir absolute

    def cells(self, sha: str) -> list[dict[str, Any]]:
        return self.rows.get(sha, [])


# ---------------------------------------------------------------------------------------
# Commits


def _git(repo: Path, *args: str) -> str:
    done = subprocess.run(["git", *args], cwd=repo, capture_output=True, text=True, timeout=120)
    if done.returncode != 0:
        msg = (done.stderr.strip().splitlines() or ["(no message)"])[-1]
        raise ReplayError(f"git {' '.join(args)}: {msg}")
    return done.stdout


def select_commits(repo: Path, revs: str | None = None, commits_file: str | Path | None = None,
                   every: int = 1) -> list[str]:
    """The commits a history runs at, oldest first.

    ``revs`` ``A..B``: A and every commit after it up to B along B's first parents (the line a
    main branch's history is read along); a single revision: that commit. ``commits_file``: one
    revision a line (``#`` starts a comment), in the file's order. ``every`` N keeps every Nth
    commit counted back from the newest, and the oldest (the baseline) always.
    """
    if every < 1:
        raise ReplayError(f"--every must be >= 1, got {every}")
    if (revs is None) == (commits_file is None):
        raise ReplayError("give the commits with either --revs A..B or --commits FILE")
    if commits_file is not None:
        try:
            lines = Path(commits_file).read_text().splitlines()
        except OSError as err:
            raise ReplayError(f"--commits {commits_file}: cannot read it: {err.strerror or err}") from None
        wanted = [line.split("#", 1)[0].strip() for line in lines]
        shas = [resolve(repo, w) for w in wanted if w]
        if not shas:
            raise ReplayError(f"--commits {commits_file} names no commit (one revision a line)")
    else:
        assert revs is not None
        if ".." in revs:
            a, _, b = revs.partition("..")
            if not a or not b or b.startswith("."):
                raise ReplayError(f"--revs {revs!r}: give A..B (two revisions) or one revision")
            first, last = resolve(repo, a), resolve(repo, b)
            try:
                _git(repo, "merge-base", "--is-ancestor", first, last)
            except ReplayError:
                raise ReplayError(f"--revs {revs}: {a} is not an ancestor of {b}") from None
            shas = [first, *_git(repo, "rev-list", "--reverse", "--first-parent", f"{first}..{last}").split()]
        else:
            shas = [resolve(repo, revs)]
    shas = list(dict.fromkeys(shas))
    if every > 1:
        keep = {shas[0]} | {s for i, s in enumerate(reversed(shas)) if i % every == 0}
        shas = [s for s in shas if s in keep]
    return shas


def commit_info(repo: Path, shas: Sequence[str]) -> dict[str, Commit]:
    """Date and subject of each commit, by sha."""
    if not shas:
        return {}
    out = _git(repo, "log", "--no-walk=unsorted", "--format=%H%x1f%cI%x1f%s", *shas)
    commits = [line.split("\x1f", 2) for line in out.splitlines() if line.count("\x1f") == 2]
    return {sha: Commit(sha, date, subject, int(_git(repo, "rev-list", "--count", sha).strip()))
            for sha, date, subject in commits}


def git_order(repo: Path | None, commits: Sequence[Commit]) -> list[Commit]:
    """``commits`` in ``repo``'s order (``gitorder.order_versions``), whenever they ran; those git cannot place
    at the end by date, their ``note`` saying so."""
    order = order_versions(repo, [(c.sha, c.date) for c in commits])
    return [replace(commits[i], note=note) for i, note in order]


def in_git_order(history: History, repo: Path | None) -> History:
    """The same history with its commits in ``repo``'s order (:func:`git_order`)."""
    return History(git_order(repo, history.commits), history.status, history.rows)


# ---------------------------------------------------------------------------------------
# The store


def read_store(out: Path) -> History:
    """The history in ``out/history.jsonl``; empty when there is none. Commits in history order: by
    generation (``Commit``), committer date, then the order they were first recorded."""
    path = out / STORE
    commits: dict[str, Commit] = {}
    seen: dict[str, int] = {}
    status: dict[str, dict[str, Any]] = {}
    cells: dict[str, dict[str, dict[str, Any]]] = {}
    try:
        lines = path.read_text().splitlines()
    except FileNotFoundError:
        lines = []
    for i, line in enumerate(lines, 1):
        try:
            r = json.loads(line)
        except json.JSONDecodeError:
            if i == len(lines):
                continue  # torn by a stop mid-write: the cell is simply run again
            raise ReplayError(f"{path}:{i}: not a JSON row") from None
        sha = r.get("commit")
        if not isinstance(r, dict) or not isinstance(sha, str):
            raise ReplayError(f"{path}:{i}: not a history row (no commit)")
        seen.setdefault(sha, len(seen))
        if r.get("type") == "commit":
            status[sha] = r
            commits[sha] = _commit_of(r)
        elif r.get("type") == "cell":
            rr = normalized_row(r)
            rr["run_dir"] = str((out / rr["run_dir"]).resolve()) if rr.get("run_dir") else None
            cells.setdefault(sha, {})[str(r.get("key"))] = rr
            commits.setdefault(sha, _commit_of(r))

    def order(c: Commit) -> tuple[int, float, int]:
        try:
            stamp = datetime.fromisoformat(c.date).timestamp()
        except ValueError:
            stamp = float("inf")
        return (c.generation, stamp, seen[c.sha])

    ordered = sorted(commits.values(), key=order)
    return History(ordered, status, {sha: list(rows.values()) for sha, rows in cells.items()})


def _commit_of(r: dict[str, Any]) -> Commit:
    return Commit(str(r["commit"]), str(r.get("date", "")), str(r.get("subject", "")), int(r.get("generation") or 0))


class _Store:
    """Appends rows to ``history.jsonl``, each line whole and flushed before the next."""

    def __init__(self, f: TextIO) -> None:
        self.f = f

    def append(self, r: dict[str, Any]) -> None:
        self.f.write(json.dumps(r, sort_keys=True, default=str) + "\n")
        self.f.flush()


def _drop_torn_line(path: Path) -> None:
    """Cut a last line left unfinished by a stop mid-write (its cell runs again), so that appending goes on whole."""
    if not path.is_file():
        return
    with open(path, "rb+") as f:
        data = f.read()
        if data and not data.endswith(b"\n"):
            f.truncate(data.rfind(b"\n") + 1)


@contextmanager
def _exclusive(out: Path) -> Iterator[None]:
    """One history writes to a store at a time."""
    with open(out / ".history.lock", "w") as f:
        try:
            fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise ReplayError(f"another `slamreplay history` is writing to {out}: wait for it to end") from None
        try:
            yield
        finally:
            fcntl.flock(f, fcntl.LOCK_UN)


# ---------------------------------------------------------------------------------------
# Running


@dataclass
class _Pending:
    commit: Commit
    jobs: list[CellJob]
    left: int
    rows: dict[str, dict[str, Any]]


def _cell_row(job: CellJob, commit: Commit, out: Path, error: str | None = None, cached: bool = False
              ) -> dict[str, Any]:
    r = row(job, commit.sha, error, cached=cached)
    r.update(type="cell", commit=commit.sha, date=commit.date, subject=commit.subject, generation=commit.generation,
             run_dir=os.path.relpath(job.run_dir, out))
    return r


def _from_cache(job: CellJob, sha: str, cache: Path) -> bool:
    """Copy a run ``compare rev:`` made for the same key into the job's place; True if there was one."""
    there = cache / "results" / sha / "runs" / job.run_dir.name
    if there == job.run_dir or not is_cached(CellJob(job.cell, job.recording, there, job.key)):
        return False
    if job.run_dir.exists():
        shutil.rmtree(job.run_dir)
    shutil.copytree(there, job.run_dir)
    return True


def _commit_row(p: _Pending, suite: Suite, error: str | None = None) -> dict[str, Any]:
    rows = list(p.rows.values())
    failed = sum(1 for r in rows if r["status"] != "succeeded")
    status = ("build_failed" if error else "succeeded" if failed == 0 else "failed" if failed == len(rows)
              else "partial")
    return {"type": "commit", "commit": p.commit.sha, "date": p.commit.date, "subject": p.commit.subject,
            "generation": p.commit.generation, "status": status, "error": error, "cells": len(p.jobs),
            "failed": failed if not error else len(p.jobs), "suite": suite.name, "suite_sha256": suite.sha256}


def _write_commit_results(p: _Pending, suite: Suite, results: Path) -> None:
    """``DIR/commits/<sha>/results.jsonl`` and ``suite.json``: a finished suite results directory."""
    rows = [{**p.rows[j.key], "run_dir": str(j.run_dir.resolve())} for j in p.jobs if j.key in p.rows]
    results.mkdir(parents=True, exist_ok=True)
    write_results(results, rows)
    about = {"format": 1, "suite": str(suite.path), "suite_name": suite.name, "suite_sha256": suite.sha256,
             "code_version": p.commit.sha, "rev": p.commit.sha, "cells": len(rows), "finished": True}
    atomic_write(results / "suite.json", json.dumps(about, indent=2, sort_keys=True) + "\n")


def run_history(suite: Suite, out: Path, shas: Sequence[str], repo: Path, *, workers: int = 1,
                run: RunCell = run_cell, retry_failed: bool = False,
                note: Callable[[str], None] | None = None,
                progress: Callable[[int, int], None] | None = None) -> History:
    """Run ``suite`` at each commit of ``shas`` (oldest first) into the store in ``out``; the whole store after.

    ``run(revision, job)`` runs one cell with the revision's code (default: its ``slamreplay run``) and
    returns an error message or None; ``note`` is told of builds and of each commit done;
    ``progress(done, total)`` counts the cells of this call (those already in the store are not counted).
    The store's commits come back in ``repo``'s order (:func:`git_order`), whatever order they ran in.
    """
    note = note or (lambda text: None)
    if workers < 1:
        raise ReplayError(f"--jobs must be >= 1, got {workers}")
    if out.exists() and not out.is_dir():
        raise ReplayError(f"--out {out} is a file: give a history directory (new, or one a history wrote)")
    if out.is_dir() and any(out.iterdir()) and not (out / STORE).is_file():
        raise ReplayError(f"--out {out} holds other files: give a new directory or one a history wrote")
    out.mkdir(parents=True, exist_ok=True)
    out = out.resolve()  # cells run in their worktree: every path they get is absolute
    cache = cache_dir()
    with _exclusive(out):
        before = read_store(out)
        recordings = materialize(suite, cache)
        info = commit_info(repo, shas)
        _drop_torn_line(out / STORE)
        with open(out / STORE, "a") as f:
            store = _Store(f)
            pending: list[_Pending] = []
            for sha in shas:
                commit = info.get(sha, Commit(sha, "", ""))
                known = {r["key"]: r for r in before.cells(sha)}
                if before.status.get(sha, {}).get("status") == "build_failed" and not retry_failed:
                    continue
                jobs, cached = plan(suite, recordings, out / "commits" / sha, sha)
                p = _Pending(commit, jobs, 0, {})
                for job in jobs:
                    old = known.get(job.key)
                    if old is not None and (old["status"] == "succeeded" or not retry_failed):
                        p.rows[job.key] = old
                    elif job.key in cached or _from_cache(job, sha, cache):
                        p.rows[job.key] = _cell_row(job, commit, out, cached=True)
                        store.append(p.rows[job.key])
                p.left = len(jobs) - len(p.rows)
                if p.left or sha not in before.status:
                    pending.append(p)
            _run_pending(pending, suite, out, repo, cache, store, workers, run, note, progress)
    return in_git_order(read_store(out), repo)


def _run_pending(pending: list[_Pending], suite: Suite, out: Path, repo: Path, cache: Path, store: _Store,
                 workers: int, run: RunCell, note: Callable[[str], None],
                 progress: Callable[[int, int], None] | None) -> None:
    """Build each pending commit in turn and run its cells in one shared pool (see the module docstring)."""
    total = sum(p.left for p in pending)
    done, commits_done = 0, 0
    if progress:
        progress(0, total)
    futures: dict[Future[str | None], tuple[_Pending, CellJob]] = {}

    def finish_commit(p: _Pending, error: str | None = None) -> None:
        nonlocal commits_done
        r = _commit_row(p, suite, error)
        store.append(r)
        if error is None:
            _write_commit_results(p, suite, out / "commits" / p.commit.sha)
        commits_done += 1
        what = f"build failed: {error}" if error else f"{r['cells'] - r['failed']}/{r['cells']} cells succeeded"
        note(f"commit {commits_done}/{len(pending)} done: {p.commit.short} {p.commit.subject[:60]} ({what}); "
             f"{total - done} cell(s) left")

    def drain(block: bool) -> None:
        nonlocal done
        if not futures:
            return
        ended, _ = wait(list(futures), timeout=None if block else 0, return_when=FIRST_COMPLETED)
        for fut in ended:
            p, job = futures.pop(fut)
            error = fut.result()
            stamp_run(job)
            p.rows[job.key] = _cell_row(job, p.commit, out, error)
            store.append(p.rows[job.key])
            p.left -= 1
            done += 1
            if progress:
                progress(done, total)
            if p.left == 0:
                finish_commit(p)

    with ThreadPoolExecutor(max_workers=workers) as pool:
        for p in pending:
            todo = [j for j in p.jobs if j.key not in p.rows]
            if not todo:
                finish_commit(p)
                continue
            try:
                revision = prepare_revision(repo, p.commit.sha, cache, note=note)
            except ReplayError as err:
                done += len(todo)
                if progress:
                    progress(done, total)
                finish_commit(p, str(err))
                drain(False)
                continue
            for job in todo:
                if job.run_dir.exists():
                    shutil.rmtree(job.run_dir)
                job.run_dir.parent.mkdir(parents=True, exist_ok=True)
                futures[pool.submit(run, revision, job)] = (p, job)
            drain(False)
        while futures:
            drain(True)


def series(history: History) -> dict[tuple[str, str, str], dict[str, list[dict[int, float]]]]:
    """Per group (recording, pipeline, variant) and metric, one mapping a commit (in history order):
    replicate index -> value, of the cells that succeeded. Replicates are (recording seed, run seed)
    pairs, numbered in sorted order. Rows marked ``alone`` (``history_dates``) are in no series of their own."""
    reps: dict[tuple[str, str, str], list[tuple[int, int]]] = {}
    for sha in (c.sha for c in history.commits):
        for r in history.cells(sha):
            if r.get("alone"):
                continue
            g = (str(r["recording"]), str(r["pipeline"]), str(r["variant"]))
            rep = (-1 if r.get("recording_seed") is None else int(r["recording_seed"]), int(r.get("seed") or 0))
            if rep not in reps.setdefault(g, []):
                reps[g].append(rep)
    out: dict[tuple[str, str, str], dict[str, list[dict[int, float]]]] = {}
    for g, rs in reps.items():
        index = {rep: i for i, rep in enumerate(sorted(rs))}
        by_metric: dict[str, list[dict[int, float]]] = {}
        for k, c in enumerate(history.commits):
            for r in history.cells(c.sha):
                if (str(r["recording"]), str(r["pipeline"]), str(r["variant"])) != g or r["status"] != "succeeded" \
                        or r.get("alone"):
                    continue
                rep = (-1 if r.get("recording_seed") is None else int(r["recording_seed"]), int(r.get("seed") or 0))
                for name, v in r.get("metrics", {}).items():
                    if isinstance(v, (int, float)):
                        col = by_metric.setdefault(name, [{} for _ in history.commits])
                        col[k][index[rep]] = float(v)
        out[g] = by_metric
    return out


def history_of_versions(versions: Sequence[tuple[Commit, list[dict[str, Any]]]]) -> History:
    """A history from results rows grouped by the code version they ran on (oldest first), e.g. the suites a
    service ran under one name: each version a point, its rows (``results.jsonl`` form, normalized here)."""
    commits = [c for c, _ in versions]
    rows = {c.sha: [normalized_row(r) for r in rs] for c, rs in versions}
    status = {c.sha: {"type": "commit", "commit": c.sha, "date": c.date, "subject": c.subject,
                      "status": "succeeded" if all(r.get("status") == "succeeded" for r in rs) else "partial"}
              for c, rs in versions}
    return History(commits, status, rows)
