"""The job store: recordings and jobs in SQLite (WAL), shared by the server and its worker processes.

The database is the queue: a job is ``queued`` until a worker slot claims it (one atomic
UPDATE), so nothing queued lives only in memory and a restart loses nothing. Each call
opens its own short connection, so the store is safe to use from any thread or process.

Job states: ``queued`` -> ``running`` -> ``succeeded`` | ``failed`` | ``cancelled``; a job
found ``running`` at start-up was cut off by a server stop: it is re-queued once, and
marked ``interrupted`` when that happens a second time.

Besides what ran, a job carries what people say of it (``name``, ``note``, tags in
``job_tags``) and its metric values (``metrics``, copied from ``metrics.json`` when it ends),
so the runs table sorts and filters by them without opening a file. An older database is
upgraded in place when a store opens it (``_migrate``).
"""

from __future__ import annotations

import json
import sqlite3
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

from slamreplay.api.service.people import SCHEMA as PEOPLE_SCHEMA
from slamreplay.api.service.people import PeopleMixin, TokenCache

# JobRow and the job statuses live with the runs-table queries; imported from here as they always were.
from slamreplay.api.service.store_runs import ACTIVE as ACTIVE
from slamreplay.api.service.store_runs import JOB_COLUMNS, Labels, RunsTableMixin
from slamreplay.api.service.store_runs import JOB_STATUSES as JOB_STATUSES
from slamreplay.api.service.store_runs import JobRow as JobRow
from slamreplay.api.service.store_runs import JobStatus as JobStatus
from slamreplay.api.service.store_runs import job_row as _job

MAX_ATTEMPTS = 2  # the first run, and one re-queue after a server stop

SCHEMA = """
CREATE TABLE IF NOT EXISTS recordings (
    id TEXT PRIMARY KEY,            -- sha256 of the file
    filename TEXT NOT NULL,         -- as uploaded, for display and downloads only
    size INTEGER NOT NULL,
    topics TEXT NOT NULL,           -- JSON list of {topic, read_as, schema, encoding, messages}
    message_count INTEGER NOT NULL,
    start_ns INTEGER NOT NULL,
    end_ns INTEGER NOT NULL,
    created REAL NOT NULL
);
CREATE TABLE IF NOT EXISTS jobs (
    seq INTEGER PRIMARY KEY AUTOINCREMENT,
    id TEXT NOT NULL UNIQUE,
    recording_id TEXT NOT NULL,
    pipeline TEXT NOT NULL,
    config TEXT NOT NULL,           -- JSON object, as submitted (validated)
    seed INTEGER NOT NULL,
    status TEXT NOT NULL,
    progress REAL NOT NULL DEFAULT 0,
    error TEXT,
    note TEXT,
    attempts INTEGER NOT NULL DEFAULT 0,
    created REAL NOT NULL,
    started REAL,
    finished REAL,
    name TEXT,                      -- given on the page; NULL: none
    metrics TEXT,                   -- JSON {metric: value} of a succeeded job; NULL: not read yet
    topic_map TEXT,                 -- JSON {file topic: slamreplay topic}; NULL: none
    rev TEXT,                       -- commit sha whose code runs it; NULL: the service's own
    made_by TEXT,                   -- who submitted or pushed it (api/service/auth.py); NULL: a server before people
    source TEXT,                    -- JSON of where a pushed run was made (api/service/push.py); NULL: made here
    git_commit TEXT                 -- the code's commit as its manifest records it; NULL: not known (yet)
);
CREATE INDEX IF NOT EXISTS jobs_status ON jobs (status, seq);
CREATE INDEX IF NOT EXISTS jobs_recording ON jobs (recording_id);
"""
# Columns added since the first schema: (name, declaration), added by ALTER TABLE to an older file.
ADDED_COLUMNS = (("name", "TEXT"), ("metrics", "TEXT"), ("topic_map", "TEXT"), ("rev", "TEXT"), ("made_by", "TEXT"),
                 ("source", "TEXT"), ("git_commit", "TEXT"))
# Run after the columns exist (an index on a column an old file lacks would fail in SCHEMA).
SCHEMA_AFTER = """
CREATE TABLE IF NOT EXISTS job_tags (
    job_id TEXT NOT NULL,
    tag TEXT NOT NULL,
    PRIMARY KEY (job_id, tag)
);
CREATE INDEX IF NOT EXISTS job_tags_tag ON job_tags (tag, job_id);
CREATE INDEX IF NOT EXISTS jobs_pipeline ON jobs (pipeline, seq);
CREATE INDEX IF NOT EXISTS jobs_name ON jobs (name);
-- succeeded jobs whose metrics were never copied (jobs of an older server): found without a scan
CREATE INDEX IF NOT EXISTS jobs_unscored ON jobs (seq) WHERE status = 'succeeded' AND metrics IS NULL;
"""


@dataclass(frozen=True, slots=True)
class RecordingRow:
    id: str
    filename: str
    size: int
    topics: list[dict[str, Any]]
    message_count: int
    start_ns: int
    end_ns: int
    created: float


def _connect(path: Path) -> sqlite3.Connection:
    conn = sqlite3.connect(path, timeout=30.0, isolation_level=None, check_same_thread=False)
    conn.row_factory = sqlite3.Row
    conn.execute("PRAGMA busy_timeout = 30000")
    conn.execute("PRAGMA synchronous = NORMAL")
    # Checkpoint after every commit, so that the next write restarts the WAL from its start: it
    # never grows past a few pages, and writes on a full disk (deleting a recording to make
    # room) reuse its space instead of needing more.
    conn.execute("PRAGMA wal_autocheckpoint = 1")
    return conn


@contextmanager
def _connection(path: Path) -> Iterator[sqlite3.Connection]:
    conn = _connect(path)
    try:
        yield conn
    finally:
        conn.close()


def _recording(row: sqlite3.Row) -> RecordingRow:
    return RecordingRow(row["id"], row["filename"], row["size"], json.loads(row["topics"]), row["message_count"],
                        row["start_ns"], row["end_ns"], row["created"])


def _migrate(conn: sqlite3.Connection) -> None:
    """Upgrade a database made by an older version in place: add the columns it lacks, then the new tables
    and indexes. Idempotent, and safe against another process doing the same (one write transaction)."""
    conn.execute("BEGIN IMMEDIATE")
    try:
        have = {r["name"] for r in conn.execute("PRAGMA table_info(jobs)")}
        for column, decl in ADDED_COLUMNS:
            if column not in have:
                conn.execute(f"ALTER TABLE jobs ADD COLUMN {column} {decl}")
        conn.execute("COMMIT")
    except BaseException:
        conn.execute("ROLLBACK")
        raise
    conn.executescript(SCHEMA_AFTER)


def set_progress(db_path: str | Path, job_id: str, fraction: float) -> None:
    """Record a running job's progress (0..1); called from worker processes. Progress is advisory: a
    database that is busy or on a full disk skips this report rather than failing the job."""
    try:
        with _connection(Path(db_path)) as conn:
            conn.execute("UPDATE jobs SET progress = ? WHERE id = ? AND status = 'running'",
                         (min(max(fraction, 0.0), 1.0), job_id))
    except sqlite3.OperationalError:
        pass


class Store(RunsTableMixin, PeopleMixin):
    """Recordings and jobs in one SQLite file (created, in WAL mode, when missing).

    Each thread keeps one connection for the life of the store: opening one per call cost
    more than most queries, and while a connection stays open SQLite keeps the WAL and
    shared-memory files in place, so reads go on when the disk is full (a first connection
    must create them, which a full disk refuses as "disk I/O error").
    """

    def __init__(self, path: Path) -> None:
        self.path = path  # runs-table queries: RunsTableMixin (api/service/store_runs.py); people: PeopleMixin
        self._local = threading.local()
        self.token_cache = TokenCache()
        with self._read() as conn:
            conn.execute("PRAGMA journal_mode = WAL")
            conn.executescript(SCHEMA)
            _migrate(conn)
            conn.executescript(PEOPLE_SCHEMA)

    def _conn(self) -> sqlite3.Connection:
        conn: sqlite3.Connection | None = getattr(self._local, "conn", None)
        if conn is None:
            conn = self._local.conn = _connect(self.path)
        return conn

    @contextmanager
    def _read(self) -> Iterator[sqlite3.Connection]:
        """This thread's connection, for statements that each run in their own implicit transaction."""
        yield self._conn()

    @contextmanager
    def _tx(self) -> Iterator[sqlite3.Connection]:
        """A write transaction that takes the lock up front (no upgrade deadlocks)."""
        conn = self._conn()
        conn.execute("BEGIN IMMEDIATE")
        try:
            yield conn
            conn.execute("COMMIT")
        except BaseException:
            if conn.in_transaction:  # also when COMMIT itself failed (a full disk)
                try:
                    conn.execute("ROLLBACK")
                except sqlite3.Error:
                    self._local.conn = None  # a connection that cannot roll back is not reused
                    conn.close()
            raise

    # -- recordings ----------------------------------------------------------------------

    def add_recording(self, rec: RecordingRow) -> tuple[RecordingRow, bool]:
        """Insert ``rec`` unless its id is known; (the stored row, whether it was new)."""
        with self._tx() as conn:
            cur = conn.execute(
                "INSERT OR IGNORE INTO recordings (id, filename, size, topics, message_count, start_ns, end_ns, "
                "created) VALUES (?, ?, ?, ?, ?, ?, ?, ?)",
                (rec.id, rec.filename, rec.size, json.dumps(rec.topics), rec.message_count, rec.start_ns,
                 rec.end_ns, rec.created))
            row = conn.execute("SELECT * FROM recordings WHERE id = ?", (rec.id,)).fetchone()
        return _recording(row), cur.rowcount == 1

    def get_recording(self, recording_id: str) -> RecordingRow | None:
        with self._read() as conn:
            row = conn.execute("SELECT * FROM recordings WHERE id = ?", (recording_id,)).fetchone()
        return None if row is None else _recording(row)

    def list_recordings(self) -> list[RecordingRow]:
        with self._read() as conn:
            rows = conn.execute("SELECT * FROM recordings ORDER BY created DESC, id").fetchall()
        return [_recording(r) for r in rows]

    def delete_recording(self, recording_id: str) -> Literal["deleted", "missing", "busy"]:
        """Delete the row unless a queued or running job uses it (checked in the same transaction)."""
        with self._tx() as conn:
            if conn.execute("SELECT 1 FROM recordings WHERE id = ?", (recording_id,)).fetchone() is None:
                return "missing"
            busy = conn.execute("SELECT 1 FROM jobs WHERE recording_id = ? AND status IN ('queued', 'running')",
                                (recording_id,)).fetchone()
            if busy is not None:
                return "busy"
            conn.execute("DELETE FROM recordings WHERE id = ?", (recording_id,))
        return "deleted"

    # -- jobs ------------------------------------------------------------------------------

    def add_job(self, job_id: str, recording_id: str, pipeline: str, config: dict[str, Any],
                seed: int, topic_map: dict[str, str] | None = None, rev: str | None = None,
                made_by: str | None = None, labels: Labels | None = None) -> JobRow | None:
        """Queue a job (``rev``: the commit sha whose code runs it, None for the service's own; ``made_by``: who
        submitted it; ``labels``: its name, tags and note as submitted); None when the recording is unknown
        (checked in the same transaction)."""
        labels = labels or Labels()
        with self._tx() as conn:
            cur = conn.execute(
                "INSERT INTO jobs (id, recording_id, pipeline, config, seed, status, created, topic_map, rev, made_by, "
                "name, note) SELECT ?, ?, ?, ?, ?, 'queued', ?, ?, ?, ?, ?, ? "
                "WHERE EXISTS (SELECT 1 FROM recordings WHERE id = ?)",
                (job_id, recording_id, pipeline, json.dumps(config), seed, time.time(),
                 json.dumps(topic_map) if topic_map else None, rev, made_by, labels.name, labels.note, recording_id))
            if cur.rowcount != 1:
                return None
            conn.executemany("INSERT OR IGNORE INTO job_tags (job_id, tag) VALUES (?, ?)",
                             [(job_id, t) for t in labels.tags])
        return self.get_job(job_id)

    def add_pushed_job(self, job_id: str, recording_id: str, pipeline: str, config: dict[str, Any], seed: int,
                       status: JobStatus, error: str | None, started: float | None, finished: float | None,
                       metrics: dict[str, float], made_by: str, source: dict[str, Any], git_commit: str | None,
                       labels: Labels) -> JobRow:
        """A run made elsewhere (api/service/push.py), kept as a job that ended as it did there."""
        now = time.time()
        with self._tx() as conn:
            conn.execute(
                "INSERT INTO jobs (id, recording_id, pipeline, config, seed, status, progress, error, attempts, "
                "created, started, finished, name, note, metrics, made_by, source, git_commit) "
                "VALUES (?, ?, ?, ?, ?, ?, 1.0, ?, 1, ?, ?, ?, ?, ?, ?, ?, ?, ?)",
                (job_id, recording_id, pipeline, json.dumps(config), seed, status, error, now, started, finished,
                 labels.name, labels.note, json.dumps(metrics), made_by, json.dumps(source), git_commit))
            conn.executemany("INSERT OR IGNORE INTO job_tags (job_id, tag) VALUES (?, ?)",
                             [(job_id, t) for t in labels.tags])
        job = self.get_job(job_id)
        assert job is not None
        return job

    def pushed_job(self, run_id: str) -> JobRow | None:
        """The job a run made elsewhere became (by the run's own id), if it was pushed before."""
        with self._read() as conn:
            row = conn.execute("SELECT id FROM jobs WHERE source IS NOT NULL AND json_extract(source, '$.run_id') = ?",
                               (run_id,)).fetchone()
        return None if row is None else self.get_job(row["id"])

    def get_job(self, job_id: str) -> JobRow | None:
        with self._read() as conn:
            row = conn.execute(f"SELECT {JOB_COLUMNS} FROM jobs j WHERE id = ?", (job_id,)).fetchone()
        return None if row is None else _job(row)

    def list_jobs(self, *, recording_id: str | None = None, pipeline: str | None = None,
                  status: str | None = None, limit: int = 100) -> list[JobRow]:
        """Newest first, filtered by whichever arguments are given."""
        where, args = [], []
        for column, value in (("recording_id", recording_id), ("pipeline", pipeline), ("status", status)):
            if value is not None:
                where.append(f"{column} = ?")
                args.append(value)
        sql = (f"SELECT {JOB_COLUMNS} FROM jobs j" + (" WHERE " + " AND ".join(where) if where else "")
               + " ORDER BY seq DESC LIMIT ?")
        with self._read() as conn:
            rows = conn.execute(sql, (*args, limit)).fetchall()
        return [_job(r) for r in rows]

    def claim_next(self) -> JobRow | None:
        """Mark the oldest queued job running and return it; None when nothing is queued."""
        with self._tx() as conn:
            row = conn.execute("SELECT seq FROM jobs WHERE status = 'queued' ORDER BY seq LIMIT 1").fetchone()
            if row is None:
                return None
            job = conn.execute("UPDATE jobs SET status = 'running', progress = 0, attempts = attempts + 1, "
                               "started = ?, finished = NULL, error = NULL WHERE seq = ? RETURNING *",
                               (time.time(), row["seq"])).fetchone()
        return _job(job)

    def finish_job(self, job_id: str, status: JobStatus, error: str | None,
                   metrics: dict[str, float] | None = None, git_commit: str | None = None) -> bool:
        """Record how a running job ended, and the metric values of a succeeded one (None: read them later,
        see `unscored`); False when it is no longer running (e.g. cancelled meanwhile)."""
        progress = "1.0" if status == "succeeded" else "progress"
        values = None if metrics is None else json.dumps(metrics)
        with self._tx() as conn:
            cur = conn.execute(f"UPDATE jobs SET status = ?, error = ?, finished = ?, progress = {progress}, "
                               "metrics = ?, git_commit = ? WHERE id = ? AND status = 'running'",
                               (status, error, time.time(), values, git_commit, job_id))
        return cur.rowcount == 1

    def cancel_job(self, job_id: str) -> tuple[JobRow | None, JobStatus | None]:
        """Cancel a queued or running job: (the job after, its status before); (None, None) if unknown."""
        with self._tx() as conn:
            row = conn.execute("SELECT status FROM jobs WHERE id = ?", (job_id,)).fetchone()
            if row is None:
                return None, None
            before: JobStatus = row["status"]
            if before in ACTIVE:
                conn.execute("UPDATE jobs SET status = 'cancelled', error = 'cancelled by request', finished = ? "
                             "WHERE id = ?", (time.time(), job_id))
            job = conn.execute("SELECT * FROM jobs WHERE id = ?", (job_id,)).fetchone()
        return _job(job), before

    def recover_after_restart(self) -> tuple[list[str], list[str]]:
        """Jobs left ``running`` by a previous server: re-queue those run once, mark the others interrupted.

        Returns (re-queued ids, interrupted ids).
        """
        now = time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())
        with self._tx() as conn:
            rows = conn.execute("SELECT id, attempts FROM jobs WHERE status = 'running' ORDER BY seq").fetchall()
            requeued = [r["id"] for r in rows if r["attempts"] < MAX_ATTEMPTS]
            interrupted = [r["id"] for r in rows if r["attempts"] >= MAX_ATTEMPTS]
            for job_id in requeued:
                conn.execute("UPDATE jobs SET status = 'queued', progress = 0, started = NULL, "
                             "note = ? WHERE id = ?", (f"interrupted by a server stop; re-queued at {now}", job_id))
            for job_id in interrupted:
                conn.execute("UPDATE jobs SET status = 'interrupted', finished = ?, error = ? WHERE id = ?",
                             (time.time(), f"interrupted by a server stop after {MAX_ATTEMPTS} attempts; "
                                           "not re-queued again (submit it anew)", job_id))
        return requeued, interrupted

    def count_by_status(self) -> dict[str, int]:
        with self._read() as conn:
            rows = conn.execute("SELECT status, COUNT(*) AS n FROM jobs GROUP BY status").fetchall()
        counts: dict[str, int] = dict.fromkeys(JOB_STATUSES, 0)
        counts.update({r["status"]: r["n"] for r in rows})
        return counts

    def durations(self) -> list[tuple[str, float]]:
        """(status, seconds from start to end) of every finished job that started."""
        with self._read() as conn:
            rows = conn.execute("SELECT status, finished - started AS d FROM jobs "
                                "WHERE started IS NOT NULL AND finished IS NOT NULL").fetchall()
        return [(r["status"], max(float(r["d"]), 0.0)) for r in rows]

    def count_recordings(self) -> int:
        with self._read() as conn:
            return int(conn.execute("SELECT COUNT(*) FROM recordings").fetchone()[0])

    def active_jobs_of(self, recording_id: str) -> int:
        with self._read() as conn:
            row = conn.execute("SELECT COUNT(*) FROM jobs WHERE recording_id = ? AND status IN ('queued', 'running')",
                               (recording_id,)).fetchone()
        return int(row[0])
