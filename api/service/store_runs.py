"""Jobs as the store returns them (`JobRow`), and the runs table's part of the job store: labels (name, tags,
note), metric values, and pages of jobs.

`RunsTableMixin` is a base of `slamreplay.api.service.store.Store` (which provides the connections), kept
apart so that each module stays short. The SQL of a page's filters and order is built from a
validated view by `slamreplay.api.service.runs_query`; values only ever travel as ``?`` arguments.
"""

from __future__ import annotations

import json
import re
import sqlite3
import time
from contextlib import AbstractContextManager
from dataclasses import dataclass
from typing import Any, Literal, NamedTuple

JobStatus = Literal["queued", "running", "succeeded", "failed", "cancelled", "interrupted"]
JOB_STATUSES: tuple[JobStatus, ...] = ("queued", "running", "succeeded", "failed", "cancelled", "interrupted")
ACTIVE: tuple[JobStatus, ...] = ("queued", "running")
# Every job column, and its tags as a JSON list (sorted), for queries that build JobRow.
JOB_COLUMNS = ("j.*, (SELECT json_group_array(tag) FROM (SELECT tag FROM job_tags t WHERE t.job_id = j.id "
               "ORDER BY tag)) AS tags")


@dataclass(frozen=True, slots=True)
class JobRow:
    """A job as stored: what ran, how it went, and what people said of it."""

    id: str
    recording_id: str
    pipeline: str
    config: dict[str, Any]
    seed: int
    status: JobStatus
    progress: float
    error: str | None
    note: str | None
    attempts: int
    created: float
    started: float | None
    finished: float | None
    name: str | None = None
    tags: tuple[str, ...] = ()
    metrics: dict[str, float] | None = None  # succeeded jobs, once read from metrics.json
    topic_map: dict[str, str] | None = None  # file topic -> slamreplay topic, as submitted
    rev: str | None = None  # the commit sha whose code runs it (replay/runs/revisions.py); None: the service's own
    made_by: str | None = None  # who submitted or pushed it; None: a server before people (api/service/auth.py)
    source: dict[str, Any] | None = None  # where a pushed run was made (api/service/push.py); None: made by this server
    git_commit: str | None = None  # the code's commit as the run's manifest records it; None: not known (yet)


def job_row(row: sqlite3.Row) -> JobRow:
    """A job of a query's row (``tags`` and ``metrics`` when the query selected them)."""
    keys = row.keys()
    tags = tuple(json.loads(row["tags"])) if "tags" in keys and row["tags"] else ()
    metrics = json.loads(row["metrics"]) if "metrics" in keys and row["metrics"] else None
    topic_map = json.loads(row["topic_map"]) if "topic_map" in keys and row["topic_map"] else None
    source = json.loads(row["source"]) if "source" in keys and row["source"] else None
    return JobRow(row["id"], row["recording_id"], row["pipeline"], json.loads(row["config"]), row["seed"],
                  row["status"], row["progress"], row["error"], row["note"], row["attempts"], row["created"],
                  row["started"], row["finished"], row["name"] if "name" in keys else None, tags, metrics, topic_map,
                  row["rev"] if "rev" in keys else None, row["made_by"] if "made_by" in keys else None, source,
                  row["git_commit"] if "git_commit" in keys else None)


TAG_RE = re.compile(r"[\w.:/+-]{1,40}")
MAX_TAGS = 20
MAX_NAME = 120
MAX_NOTE = 2000


def parse_tags(text: str | list[str]) -> list[str]:
    """Tags from ``a, b c`` (or a list): letters, digits and ``_ . : / + -``, at most 40 characters each and 20 in
    all; ValueError names the first bad one."""
    parts = text if isinstance(text, list) else re.split(r"[,\s]+", text.strip())
    tags = list(dict.fromkeys(t.strip() for t in parts if t.strip()))
    bad = [t for t in tags if not TAG_RE.fullmatch(t)]
    if bad:
        raise ValueError(f"tag {bad[0][:50]!r}: use letters, digits and _ . : / + - (at most 40 characters)")
    if len(tags) > MAX_TAGS:
        raise ValueError(f"{len(tags)} tags: at most {MAX_TAGS}")
    return tags


@dataclass(frozen=True, slots=True)
class Labels:
    """What people say of a run: its name, tags and note (the page's edit form, submit and ``PATCH /jobs/ID``)."""

    name: str | None = None
    tags: tuple[str, ...] = ()
    note: str | None = None

    @classmethod
    def parse(cls, name: str | None, tags: str | list[str] | None, note: str | None) -> Labels:
        """Labels from what a person typed (empty: none); ValueError says what is wrong in one line."""
        name, note = (name or "").strip() or None, (note or "").strip() or None
        if name is not None and len(name) > MAX_NAME:
            raise ValueError(f"a name has at most {MAX_NAME} characters ({len(name)} given)")
        if note is not None and len(note) > MAX_NOTE:
            raise ValueError(f"a note has at most {MAX_NOTE} characters ({len(note)} given)")
        return cls(name, tuple(parse_tags(tags or [])), note)


@dataclass(frozen=True, slots=True)
class RunRow:
    """A job as the runs table lists it: with its recording's file name and its suite variant, if any."""

    job: JobRow
    recording_name: str | None
    variant: str | None


class GroupRow(NamedTuple):
    """One of the newest runs of a group of the runs table: what its row in the group lists."""

    seq: int
    id: str
    name: str | None
    status: str
    seed: int
    keys: tuple[Any, ...]  # its values of the group keys
    metrics: dict[str, float]  # of the chosen metrics, those it reports


class GroupSums(NamedTuple):
    """A group of the runs table as SQL sums it up: its key values, and per metric (count, mean, min, max, sum of
    squared deviations from the mean) over the runs that report it."""

    keys: tuple[Any, ...]
    recording_name: str | None  # the file name of its recording, when it is grouped by recording
    n: int
    newest: int  # the largest sequence number of its runs
    sums: dict[str, tuple[int, float, float, float, float]]


# SQLite computes a common table expression once when told (3.35+), not once per reference of its columns
MATERIALIZED = "MATERIALIZED" if sqlite3.sqlite_version_info >= (3, 35) else ""
# The group keys that are job columns (and config.KEY), as SQL over j, r and v
GROUP_COLUMNS = {"recording": "j.recording_id", "pipeline": "j.pipeline", "variant": "v.variant",
                 "commit": "j.git_commit"}


# A job's suite variant: the first cell naming it (the suites tables are made by api/service/suites.py, which a bare
# store may not have run: then no job has a variant).
VARIANTS = ("LEFT JOIN (SELECT job_id, MIN(json_extract(cell, '$.variant')) AS variant FROM suite_cells "
            "GROUP BY job_id) v ON v.job_id = j.id")
NO_VARIANTS = "LEFT JOIN (SELECT NULL AS job_id, NULL AS variant) v ON 0"


class RunsTableMixin:
    """Store methods of the runs table; ``Store`` provides the connections (`_read`, `_tx`) and `get_job`."""

    def _read(self) -> AbstractContextManager[sqlite3.Connection]:
        raise NotImplementedError

    def _tx(self) -> AbstractContextManager[sqlite3.Connection]:
        raise NotImplementedError

    def get_job(self, job_id: str) -> JobRow | None:
        raise NotImplementedError

    def set_labels(self, job_id: str, labels: Labels) -> JobRow | None:
        """Replace a job's name, tags and note; None when the job is unknown."""
        with self._tx() as conn:
            cur = conn.execute("UPDATE jobs SET name = ?, note = ? WHERE id = ?", (labels.name, labels.note, job_id))
            if cur.rowcount != 1:
                return None
            conn.execute("DELETE FROM job_tags WHERE job_id = ?", (job_id,))
            conn.executemany("INSERT OR IGNORE INTO job_tags (job_id, tag) VALUES (?, ?)",
                             [(job_id, t) for t in labels.tags])
        return self.get_job(job_id)

    def delete_job(self, job_id: str, who: str = "anonymous",
                   address: str = "unknown") -> Literal["deleted", "missing", "active"]:
        """Forget an ended job and its tags (its run directory is the caller's), leaving a tombstone saying who
        deleted it, when and from where (``tombstones``: api/service/people.py); a queued or running one is refused."""
        with self._tx() as conn:
            row = conn.execute("SELECT status, pipeline, recording_id, seed, name FROM jobs WHERE id = ?",
                               (job_id,)).fetchone()
            if row is None:
                return "missing"
            if row["status"] in ACTIVE:
                return "active"
            conn.execute("INSERT OR REPLACE INTO tombstones (job_id, who, at, address, pipeline, recording_id, seed, "
                         "name) VALUES (?, ?, ?, ?, ?, ?, ?, ?)", (job_id, who, time.time(), address, row["pipeline"],
                                                                   row["recording_id"], row["seed"], row["name"]))
            conn.execute("DELETE FROM job_tags WHERE job_id = ?", (job_id,))
            conn.execute("DELETE FROM jobs WHERE id = ?", (job_id,))
        return "deleted"

    def unscored(self, limit: int = 10_000) -> list[str]:
        """Ids of succeeded jobs whose metric values were never copied into the store (an older server's)."""
        with self._read() as conn:
            rows = conn.execute("SELECT id FROM jobs WHERE status = 'succeeded' AND metrics IS NULL ORDER BY seq "
                                "LIMIT ?", (limit,)).fetchall()
        return [r["id"] for r in rows]

    def set_metrics(self, values: dict[str, dict[str, float]]) -> None:
        """Store the metric values of succeeded jobs (job id -> {metric: value}; {} when there are none)."""
        with self._tx() as conn:
            conn.executemany("UPDATE jobs SET metrics = ? WHERE id = ? AND status = 'succeeded'",
                             [(json.dumps(v), k) for k, v in values.items()])

    def tag_counts(self) -> list[tuple[str, int]]:
        """Every tag in use and how many jobs carry it, by tag."""
        with self._read() as conn:
            rows = conn.execute("SELECT tag, COUNT(*) AS n FROM job_tags GROUP BY tag ORDER BY tag").fetchall()
        return [(r["tag"], int(r["n"])) for r in rows]

    def pipelines_used(self) -> list[str]:
        """The pipelines that jobs in the store ran, by name."""
        with self._read() as conn:
            return [r[0] for r in conn.execute("SELECT DISTINCT pipeline FROM jobs ORDER BY pipeline")]

    def _variants(self, conn: sqlite3.Connection) -> str:
        found = conn.execute("SELECT 1 FROM sqlite_master WHERE type = 'table' AND name = 'suite_cells'").fetchone()
        return VARIANTS if found else NO_VARIANTS

    def select_runs(self, where: str, args: list[Any], order: str, limit: int | None = None,
                    offset: int = 0) -> tuple[list[RunRow], int]:
        """One page of jobs and how many match in all.

        ``where`` and ``order`` are SQL over ``j`` (jobs), ``r`` (recordings) and ``v.variant``, built by
        `slamreplay.api.service.runs_query` from a validated view (values only as ``?`` arguments in ``args``).
        ``limit`` None: every matching job (the CSV export).
        """
        with self._read() as conn:
            joins = f"FROM jobs j LEFT JOIN recordings r ON r.id = j.recording_id {self._variants(conn)}"
            total = int(conn.execute(f"SELECT COUNT(*) {joins} WHERE {where}", args).fetchone()[0])
            rows = conn.execute(f"SELECT {JOB_COLUMNS}, r.filename AS recording_name, v.variant AS variant {joins} "
                                f"WHERE {where} ORDER BY {order} LIMIT ? OFFSET ?",
                                (*args, -1 if limit is None else limit, offset)).fetchall()
        return [RunRow(job_row(r), r["recording_name"], r["variant"]) for r in rows], total

    def json_keys(self, where: str, args: list[Any]) -> tuple[list[str], list[str]]:
        """The metric names and the config keys of the jobs matching ``where`` (as `select_runs`), each by name:
        one pass over the matching jobs."""
        with self._read() as conn:
            joins = f"FROM jobs j LEFT JOIN recordings r ON r.id = j.recording_id {self._variants(conn)}"
            rows = conn.execute(f"WITH m AS (SELECT j.metrics AS metrics, j.config AS config {joins} WHERE {where}) "
                                "SELECT DISTINCT 'm', e.key FROM m, json_each(m.metrics) e WHERE m.metrics IS NOT NULL "
                                "UNION SELECT DISTINCT 'c', e.key FROM m, json_each(m.config) e ORDER BY 1, 2",
                                args).fetchall()
        return [r[1] for r in rows if r[0] == "m"], [r[1] for r in rows if r[0] == "c"]

    def select_groups(self, where: str, args: list[Any], keys: tuple[str, ...], metrics: tuple[str, ...],
                      preview: int = 10) -> tuple[list[GroupSums], list[GroupRow]]:
        """The jobs matching ``where`` (as `select_runs`) grouped by ``keys`` (``recording``, ``pipeline``,
        ``variant``, ``commit`` or ``config.KEY``), summed up in SQL: per group its key values, the file name of its
        recording, how many runs, its newest run's sequence number, and per metric of ``metrics`` how many runs
        report it, their mean, minimum, maximum and sum of squared deviations; and the ``preview`` newest runs of
        each group (names as ``NAME_RE`` of `slamreplay.api.service.runs_grammar`). A config key's value is its JSON
        value (True and 1 differ; None: not submitted)."""
        name_re = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")
        bad = [n for n in (*metrics, *(k.removeprefix("config.") for k in keys)) if not name_re.fullmatch(n)]
        bad += [k for k in keys if k not in GROUP_COLUMNS and not k.startswith("config.")]
        if bad or not keys:
            raise ValueError(f"cannot group by {keys} with metrics {metrics}")
        cols = []
        for i, k in enumerate(keys):
            if k in GROUP_COLUMNS:
                cols += [f"NULL AS t{i}", f"{GROUP_COLUMNS[k]} AS k{i}"]
            else:
                path = f"'$.\"{k.removeprefix('config.')}\"'"
                cols += [f"json_type(j.config, {path}) AS t{i}", f"json_extract(j.config, {path}) AS k{i}"]
        cols += [f"json_extract(j.metrics, '$.\"{m}\"') AS m{i}" for i, m in enumerate(metrics)]
        key_cols = [f"{c}{i}" for i in range(len(keys)) for c in ("t", "k")]
        keys_sql = ", ".join(key_cols)
        sums = [f"COUNT(m{i}) AS c{i}, AVG(m{i}) AS a{i}, MIN(m{i}) AS lo{i}, MAX(m{i}) AS hi{i}, "
                f"SUM(d{i} * d{i}) AS ss{i}" for i in range(len(metrics))]
        # deviations from the group's mean by a window over the group: one pass, no cancellation of sum(x^2)
        devs = "".join(f", m{i} - AVG(m{i}) OVER w AS d{i}" for i in range(len(metrics)))
        with self._read() as conn:
            base = (f"WITH base AS {MATERIALIZED} (SELECT j.seq AS seq, j.id AS id, j.name AS name, "
                    f"j.status AS status, j.seed AS seed, r.filename AS filename, {', '.join(cols)} "
                    f"FROM jobs j LEFT JOIN recordings r ON r.id = j.recording_id {self._variants(conn)} "
                    f"WHERE {where})")
            groups = conn.execute(
                f"{base}, d AS (SELECT *{devs} FROM base WINDOW w AS (PARTITION BY {keys_sql})) "
                f"SELECT {keys_sql}, COUNT(*) AS n, MAX(seq) AS newest, MIN(filename) AS filename"
                f"{''.join(', ' + x for x in sums)} FROM d GROUP BY {keys_sql}", args).fetchall()
            runs = conn.execute(
                f"{base} SELECT * FROM (SELECT b.*, ROW_NUMBER() OVER (PARTITION BY {keys_sql} "
                f"ORDER BY seq DESC) AS rn FROM base b) WHERE rn <= ? ORDER BY seq DESC", (*args, preview)).fetchall()
        nk = len(keys)

        def values(row: sqlite3.Row, offset: int) -> tuple[Any, ...]:
            out = []
            for i in range(nk):
                kind, value = row[offset + 2 * i], row[offset + 2 * i + 1]
                out.append(kind == "true" if kind in ("true", "false") else
                           json.loads(value) if kind in ("object", "array") else value)
            return tuple(out)

        sums_out = [GroupSums(values(g, 0), g["filename"], g["n"], g["newest"],
                              {m: (g[f"c{i}"], g[f"a{i}"], g[f"lo{i}"], g[f"hi{i}"], g[f"ss{i}"] or 0.0)
                               for i, m in enumerate(metrics) if g[f"c{i}"]}) for g in groups]
        rows = [GroupRow(r["seq"], r["id"], r["name"], r["status"], r["seed"], values(r, 6),
                         {m: r[6 + 2 * nk + i] for i, m in enumerate(metrics) if r[6 + 2 * nk + i] is not None})
                for r in runs]
        return sums_out, rows

    def chart_points(self, where: str, args: list[Any], metric: str, x: str,
                     limit: int = 1000) -> list[tuple[str, str | None, int, Any, float]]:
        """The newest ``limit`` jobs matching ``where`` (as `select_runs`) that report ``metric``: (id, name, seed,
        value of ``x``, value of the metric), ``x`` one of seed, created, commit or config.KEY (its JSON value; None:
        not submitted)."""
        name_re = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")
        key = x.removeprefix("config.")
        if not name_re.fullmatch(metric) or not (x in ("seed", "created", "commit") or
                                                 (x.startswith("config.") and name_re.fullmatch(key))):
            raise ValueError(f"cannot chart {metric!r} against {x!r}")
        path = f"'$.\"{key}\"'"
        x_sql = {"seed": "NULL, j.seed", "created": "NULL, j.created", "commit": "NULL, j.git_commit"}.get(
            x, f"json_type(j.config, {path}), json_extract(j.config, {path})")
        y_sql = f"json_extract(j.metrics, '$.\"{metric}\"')"
        with self._read() as conn:
            joins = f"FROM jobs j LEFT JOIN recordings r ON r.id = j.recording_id {self._variants(conn)}"
            rows = conn.execute(f"SELECT j.id, j.name, j.seed, {x_sql}, {y_sql} {joins} WHERE ({where}) AND "
                                f"{y_sql} IS NOT NULL ORDER BY j.seq DESC LIMIT ?", (*args, limit)).fetchall()
        return [(r[0], r[1], r[2], r[4] if r[3] not in ("true", "false") else r[3] == "true", r[5]) for r in rows]

    def jobs_page(self, where: str, args: list[Any], limit: int,
                  before: int | None = None) -> tuple[list[JobRow], int, int | None]:
        """Jobs matching ``where`` (as `select_runs`), newest first, after the cursor ``before`` (a job's sequence
        number; None: from the newest): (at most ``limit`` jobs, how many match in all, the next page's cursor or
        None when this is the last). A cursor stays valid while jobs are added or deleted."""
        with self._read() as conn:
            joins = f"FROM jobs j LEFT JOIN recordings r ON r.id = j.recording_id {self._variants(conn)}"
            total = int(conn.execute(f"SELECT COUNT(*) {joins} WHERE {where}", args).fetchone()[0])
            after = "" if before is None else " AND j.seq < ?"
            rows = conn.execute(f"SELECT {JOB_COLUMNS}, j.seq AS seq {joins} WHERE ({where}){after} "
                                "ORDER BY j.seq DESC LIMIT ?",
                                (*args, *(() if before is None else (before,)), limit + 1)).fetchall()
        more = len(rows) > limit
        rows = rows[:limit]
        return [job_row(r) for r in rows], total, int(rows[-1]["seq"]) if more else None

    def ids_starting(self, table: str, prefix: str, limit: int = 10) -> list[str]:
        """Ids of ``table`` (jobs, recordings or suites) that start with the hex ``prefix``, at most ``limit``, by id.

        A range over the id index rather than LIKE (which SQLite would not answer from the index)."""
        if table not in ("jobs", "recordings", "suites"):
            raise ValueError(f"table {table!r}: not one with ids")
        with self._read() as conn:
            try:  # "g" follows every hex digit: [prefix, prefix + "g") holds exactly the ids starting with it
                rows = conn.execute(f"SELECT id FROM {table} WHERE id >= ? AND id < ? ORDER BY id LIMIT ?",
                                    (prefix, prefix + "g", limit)).fetchall()
            except sqlite3.OperationalError:  # no suites table: a bare store
                return []
        return [r[0] for r in rows]

    def suite_uses(self, job_id: str) -> int:
        """How many suite cells a job serves (0 when no suite was ever stored)."""
        with self._read() as conn:
            if self._variants(conn) == NO_VARIANTS:
                return 0
            return int(conn.execute("SELECT COUNT(*) FROM suite_cells WHERE job_id = ?", (job_id,)).fetchone()[0])
