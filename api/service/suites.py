"""Suites in the service: a suite file's cells as jobs of the job store, and comparisons of them.

A suite sent to the service (TOML or JSON, the form of ``slamreplay.replay.runs.suite``) names uploaded
recordings by id. Each cell becomes a job in the existing store, run by the existing
scheduler and executor; a cell whose inputs (recording, pipeline, config values, seed) already
have a queued, running or succeeded job of the same code is served by that job instead. Which
jobs make up which suite is kept in two tables of the same SQLite database (``suites``,
``suite_cells``), so a suite, like its jobs, survives a restart.
"""

from __future__ import annotations

import json
import sqlite3
import time
import uuid
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

from slamreplay.api.service.errors import ConflictError, NotFoundError
from slamreplay.api.service.jobs import JobService
from slamreplay.api.service.people import Tombstone
from slamreplay.api.service.store import JobRow
from slamreplay.api.service.store_runs import Labels
from slamreplay.recorder.version import git_commit
from slamreplay.replay.errors import ReplayError
from slamreplay.replay.runs.compare import Side, run_row, side_of_rows
from slamreplay.replay.runs.diff import determinism_of
from slamreplay.replay.runs.suite import Suite, canonical, parse_suite
from slamreplay.replay.runs.suite_run import add_metrics

SCHEMA = """
CREATE TABLE IF NOT EXISTS suites (
    id TEXT PRIMARY KEY,
    name TEXT NOT NULL,
    format TEXT NOT NULL,           -- toml | json: how it was sent
    text TEXT NOT NULL,             -- as sent
    created REAL NOT NULL
);
CREATE TABLE IF NOT EXISTS suite_cells (
    suite_id TEXT NOT NULL,
    idx INTEGER NOT NULL,           -- the cell's place in the suite's order
    cell TEXT NOT NULL,             -- JSON: recording, recording_seed, pipeline, variant, seed, config
    job_id TEXT NOT NULL,
    reused INTEGER NOT NULL,        -- 1: an existing job with the same inputs serves this cell
    PRIMARY KEY (suite_id, idx)
);
CREATE INDEX IF NOT EXISTS suite_cells_job ON suite_cells (job_id);
"""
ENDED = ("succeeded", "failed", "cancelled", "interrupted", "deleted")


@dataclass(frozen=True, slots=True)
class SuiteRow:
    id: str
    name: str
    format: str
    created: float


@dataclass(frozen=True, slots=True)
class SuiteCell:
    """A cell and its job; a job deleted since is a stand-in row of the cell's inputs, with its tombstone."""

    cell: dict[str, Any]
    job: JobRow
    reused: bool
    deleted: Tombstone | None = None

    @property
    def status(self) -> str:
        """The job's status, or ``deleted``: a suite shows a deleted run as deleted, never leaves it out."""
        return "deleted" if self.deleted is not None else self.job.status


def _stand_in(job_id: str, cell: dict[str, Any], stone: Tombstone) -> JobRow:
    """The row a deleted job of a suite cell is shown as: its inputs, ended when it was deleted."""
    return JobRow(job_id, stone.recording_id, stone.pipeline, dict(cell.get("config") or {}), stone.seed, "cancelled",
                  0.0, stone.text, None, 0, stone.at, None, stone.at, stone.name)


def _take_topic_maps(text: str, fmt: str) -> tuple[dict[str, dict[str, str]], dict[str, Any]]:
    """({recording name: its topic_map}, the suite document without them); ({}, {}) when there is none or the text
    does not parse (the suite parser then says why)."""
    from slamreplay.api.service.submit_checks import parse_topic_map
    from slamreplay.replay.runs.suite import tomllib  # tomllib, or tomli on Python 3.10: the suite parser's own

    try:
        doc = json.loads(text) if fmt == "json" else tomllib.loads(text)
    except (ValueError, tomllib.TOMLDecodeError):
        return {}, {}
    recs = doc.get("recordings") if isinstance(doc, dict) else None
    if not isinstance(recs, dict):
        return {}, {}
    maps = {}
    for name, spec in recs.items():
        if isinstance(spec, dict) and "topic_map" in spec:
            try:
                maps[name] = parse_topic_map(spec.pop("topic_map"))
            except ReplayError as err:
                raise ReplayError(f"recordings.{name}.{err}") from None
    return maps, doc


class SuiteService:
    """Submit suites as jobs; report their progress and results; compare suites and jobs."""

    def __init__(self, jobs: JobService) -> None:
        self.jobs = jobs
        self.db = jobs.settings.db_path
        self._code = git_commit()
        with self._conn() as conn:
            conn.executescript(SCHEMA)

    @contextmanager
    def _conn(self) -> Iterator[sqlite3.Connection]:
        conn = sqlite3.connect(self.db, timeout=30.0, isolation_level=None)
        conn.row_factory = sqlite3.Row
        conn.execute("PRAGMA busy_timeout = 30000")
        try:
            yield conn
        finally:
            conn.close()

    # -- submitting ----------------------------------------------------------------------------

    def _full_id(self, rid: str) -> str:
        """The recording id that ``rid`` (a whole id or an unambiguous prefix) names; ReplayError saying how to get
        one otherwise."""
        from slamreplay.api.service.errors import ApiError
        from slamreplay.api.service.ids import HEX, resolve_id

        try:
            return resolve_id(self.jobs.store, rid, ("recording",))
        except ApiError as err:
            if not HEX.fullmatch(rid) or len(rid) > 64:
                raise ReplayError(f"{rid!r} is not a recording id (64 hex digits, as POST /recordings answers, or "
                                  "the first 8 of them)") from None
            raise ReplayError(f"{err}; upload it with POST /recordings first") from None

    def _recording(self, rid: str) -> Path:
        """The stored file of recording ``rid`` (a prefix will do); ReplayError saying how to get one otherwise."""
        full = self._full_id(rid)
        if self.jobs.store.get_recording(full) is None:
            raise ReplayError(f"recording {full} not found; upload it with POST /recordings first")
        return self.jobs.recording_path(full)

    def parse(self, text: str, fmt: str) -> Suite:
        """Validate a suite; ReplayError (422) naming the key (and, for TOML, the line) at fault.

        A recording may carry ``topic_map`` (file topic -> slamreplay topic), as in ``suite run``; the
        suite parser refuses local-file keys for a service suite, so the maps are taken out first and
        put back on the parsed recordings (the rest is then parsed as JSON: without TOML line numbers)."""
        maps, rest = _take_topic_maps(text, fmt)
        if not maps:
            return parse_suite(text, Path(f"suite.{fmt}"), ids=self._recording, fmt=fmt)
        suite = parse_suite(json.dumps(rest, default=str), Path("suite.json"), ids=self._recording, fmt="json")
        for name, topic_map in maps.items():
            if name in suite.recordings:
                suite.recordings[name] = replace(suite.recordings[name], topic_map=topic_map)
        return replace(suite, text=text)

    def _reusable(self, rid: str, pipeline: str, config: dict[str, Any], seed: int,
                  topic_map: dict[str, str], rev: str | None = None) -> JobRow | None:
        """A job with these inputs that is queued or running with the same code (``rev``, else the code running
        now), or succeeded with it (its manifest says so)."""
        want, code = canonical(config), rev or self._code
        for job in self.jobs.store.list_jobs(recording_id=rid, pipeline=pipeline, limit=1000):
            if job.seed != seed or canonical(job.config) != want or (job.topic_map or {}) != topic_map:
                continue
            if job.status in ("queued", "running") and (job.rev or self._code) == code:
                return job
            if job.status == "succeeded" and not code.endswith("-dirty") and code != "unknown":
                try:
                    manifest = json.loads((self.jobs.run_dir(job.id) / "manifest.json").read_text())
                except (OSError, json.JSONDecodeError):
                    continue
                if manifest.get("slamreplay", {}).get("git_commit") == code:
                    return job
        return None

    def _check_cells(self, suite: Suite) -> None:
        """ReplayError for the first (recording, pipeline) whose pipeline needs topics the recording lacks."""
        from slamreplay.api.service.submit_checks import check_fit
        from slamreplay.replay.engine.pipeline import get_pipeline

        for rec_name, pipeline in dict.fromkeys((c.recording, c.pipeline) for c in suite.cells()):
            spec = suite.recordings[rec_name]
            rec = self.jobs.store.get_recording(self._full_id(spec.id or ""))
            if rec is not None:
                check_fit(rec, get_pipeline(pipeline), dict(spec.topic_map))

    def submit(self, text: str, fmt: str, rev: str | None = None, made_by: str | None = None,
               labels: Labels | None = None) -> SuiteRow:
        """Validate the suite, queue a job per cell (or reuse one of the same code), and record the suite.

        ``rev``: a full commit sha whose code runs the cells (resolved by the caller), None for the service's own;
        ``made_by``: who sends it; ``labels``: the tags and note of each job it queues (a reused job keeps its own).
        """
        suite = self.parse(text, fmt)
        cells = suite.cells()
        suite_id = uuid.uuid4().hex
        self._check_cells(suite)  # before queueing any: a suite with a cell that cannot run queues nothing
        rows = []
        for i, cell in enumerate(cells):
            spec = suite.recordings[cell.recording]
            rid = self._full_id(spec.id or "")
            topic_map = dict(spec.topic_map)  # the suite's `topic_map` of this recording, as `suite run` uses it
            job = self._reusable(rid, cell.pipeline, cell.config, cell.seed, topic_map, rev)
            reused = job is not None
            if job is None:
                job = self.jobs.submit(rid, cell.pipeline, dict(cell.config), cell.seed, topic_map, rev, made_by,
                                       labels)
            rows.append((suite_id, i, json.dumps(cell.to_json(), sort_keys=True), job.id, int(reused)))
        created = time.time()
        with self._conn() as conn:
            conn.execute("BEGIN IMMEDIATE")
            conn.execute("INSERT INTO suites (id, name, format, text, created) VALUES (?, ?, ?, ?, ?)",
                         (suite_id, suite.name, fmt, text, created))
            conn.executemany("INSERT INTO suite_cells (suite_id, idx, cell, job_id, reused) VALUES (?, ?, ?, ?, ?)",
                             rows)
            conn.execute("COMMIT")
        return SuiteRow(suite_id, suite.name, fmt, created)

    def add_pushed(self, name: str, text: str, cells: list[tuple[dict[str, Any], str]]) -> SuiteRow:
        """Record a suite that ran elsewhere (``slamreplay push`` of a ``suite run`` folder): its name, its file's
        text and each cell with the job its pushed run became, so that its page, comparisons and the history of
        its name count it. NotFoundError names a job the server does not hold."""
        for _, job_id in cells:
            if self.jobs.store.get_job(job_id) is None:
                raise NotFoundError(f"job {job_id} not found: push the suite's runs first (slamreplay push does)")
        suite_id, created = uuid.uuid4().hex, time.time()
        with self._conn() as conn:
            conn.execute("BEGIN IMMEDIATE")
            same = conn.execute(  # the same suite pushed again: the one recorded then
                "SELECT s.id, s.created FROM suites s WHERE s.name = ? AND (SELECT group_concat(job_id, ',') FROM "
                "(SELECT job_id FROM suite_cells c WHERE c.suite_id = s.id ORDER BY idx)) = ?",
                (name, ",".join(job for _, job in cells))).fetchone()
            if same is not None:
                conn.execute("ROLLBACK")
                return SuiteRow(same["id"], name, "toml", same["created"])
            conn.execute("INSERT INTO suites (id, name, format, text, created) VALUES (?, ?, 'toml', ?, ?)",
                         (suite_id, name, text, created))
            conn.executemany("INSERT INTO suite_cells (suite_id, idx, cell, job_id, reused) VALUES (?, ?, ?, ?, 1)",
                             [(suite_id, i, json.dumps(cell, sort_keys=True), job_id)
                              for i, (cell, job_id) in enumerate(cells)])
            conn.execute("COMMIT")
        return SuiteRow(suite_id, name, "toml", created)

    # -- reading --------------------------------------------------------------------------------

    def recent(self, limit: int = 100) -> list[SuiteRow]:
        with self._conn() as conn:
            rows = conn.execute("SELECT id, name, format, created FROM suites ORDER BY created DESC LIMIT ?",
                                (limit,)).fetchall()
        return [SuiteRow(r["id"], r["name"], r["format"], r["created"]) for r in rows]

    def get(self, suite_id: str) -> tuple[SuiteRow, str, list[SuiteCell]]:
        """The suite, its text and its cells with their jobs' current state; NotFoundError for an unknown id."""
        with self._conn() as conn:
            r = conn.execute("SELECT * FROM suites WHERE id = ?", (suite_id,)).fetchone()
            if r is None:
                raise NotFoundError(f"suite {suite_id} not found")
            cells = conn.execute("SELECT cell, job_id, reused FROM suite_cells WHERE suite_id = ? ORDER BY idx",
                                 (suite_id,)).fetchall()
        out = []
        for c in cells:
            cell, job = json.loads(c["cell"]), self.jobs.store.get_job(c["job_id"])
            if job is not None:
                out.append(SuiteCell(cell, job, bool(c["reused"])))
            elif (stone := self.jobs.store.tombstone(c["job_id"])) is not None:
                out.append(SuiteCell(cell, _stand_in(c["job_id"], cell, stone), bool(c["reused"]), stone))
        return SuiteRow(r["id"], r["name"], r["format"], r["created"]), r["text"], out

    def exists(self, suite_id: str) -> bool:
        with self._conn() as conn:
            return conn.execute("SELECT 1 FROM suites WHERE id = ?", (suite_id,)).fetchone() is not None

    def result_row(self, c: SuiteCell) -> dict[str, Any]:
        """A cell as a ``results.jsonl`` row (what ``slamreplay.replay.runs.compare`` reads), with its job id."""
        run_dir = self.jobs.run_dir(c.job.id)
        row: dict[str, Any] = {**c.cell, "job_id": c.job.id, "reused": c.reused, "run_dir": str(run_dir),
                               "recording_sha256": c.job.recording_id, "status": c.status,
                               "error": c.deleted.text if c.deleted is not None else c.job.error,
                               "progress": c.job.progress, "code_version": None,
                               "metrics": {}, "better": {}, "tolerance": {}, "rel_tolerance": {}, "units": {}}
        try:
            manifest = json.loads((run_dir / "manifest.json").read_text())
            row["code_version"] = manifest.get("slamreplay", {}).get("git_commit")
            row["config_hash"] = manifest.get("config_hash")
            if (deterministic := determinism_of(manifest)) is not None:  # an external program's (external.md)
                row["deterministic"] = deterministic
        except (OSError, json.JSONDecodeError):
            pass
        if c.status == "succeeded":
            try:
                add_metrics(row, json.loads((run_dir / "metrics.json").read_text())["metrics"])
            except (OSError, json.JSONDecodeError, KeyError) as err:
                row.update(status="failed", error=f"unreadable metrics.json: {err}")
        return row

    def progress(self, cells: list[SuiteCell]) -> dict[str, Any]:
        """Counts by status, cells ended, and the fraction done (running jobs count by their own progress)."""
        counts: dict[str, int] = {}
        done = 0.0
        for c in cells:
            counts[c.status] = counts.get(c.status, 0) + 1
            done += 1.0 if c.status in ENDED else c.job.progress
        ended = sum(n for s, n in counts.items() if s in ENDED)
        status = "running" if ended < len(cells) else ("succeeded" if counts.get("succeeded", 0) == len(cells)
                                                        else "finished with failures")
        return {"status": status, "cells": len(cells), "ended": ended, "counts": counts,
                "fraction": done / len(cells) if cells else 1.0}

    # -- comparing ------------------------------------------------------------------------------

    def side(self, ref: str) -> Side:
        """A suite id or a job id as one side of a comparison; 404 unknown, 409 not finished."""
        if self.exists(ref):
            row, _, cells = self.get(ref)
            p = self.progress(cells)
            if p["ended"] < p["cells"]:
                raise ConflictError(f"suite {ref} is still running ({p['ended']} of {p['cells']} cells ended); "
                                    f"compare it when GET /suites/{ref} says it has ended")
            return side_of_rows(f"suite {row.name} ({ref[:8]})", [self.result_row(c) for c in cells], "results")
        if self.jobs.store.get_job(ref) is None:
            if self.jobs.store.tombstone(ref) is not None:
                raise self.jobs.missing(ref)
            raise NotFoundError(f"{ref} is neither a suite nor a job id")
        run = run_row(self.jobs.finished_run(ref))
        job = self.jobs.get(ref)
        rec = self.jobs.store.get_recording(job.recording_id)
        run.update(job_id=ref, recording=rec.filename if rec is not None else run["recording"])
        return side_of_rows(f"job {ref[:8]}", [run], "run")
