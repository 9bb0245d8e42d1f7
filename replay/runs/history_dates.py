"""A suite's history over the days it ran, rather than over the commits it ran on.

A team that runs the same code every night on that night's recordings has one commit and many
nights: what it wants to see is the nights. :func:`history_by_date` makes each day (UTC) that a run
of the suite started a point of a :class:`~slamreplay.replay.runs.history.History`, so the same
change detection (``changepoints``) and the same plots read it; a change is a day whose level
differs beyond seed noise and tolerance from the days before it.

- **Which runs.** All of them, whatever code they ran (``version`` keeps one code version's): a team
  whose code also moves sees where a night's level changed, and each day names the code versions
  it ran, so a change that came with new code is told from one that came with new data. A cell
  run twice in a day (a suite sent again, a backfill of an older commit) counts once there, by its
  latest run. A run is dated by its manifest's ``timings.started_at``: a run reused from an
  earlier day stays on that day.
- **Which series.** Per recording, pipeline and variant, as over commits, for each recording that
  ran on two days or more (the same recordings every night: a drift of the code's environment, or
  of a recording replaced under the same name). And when a pipeline and variant ran more than one
  recording, one more series, recording ``all recordings``: each day, per seed, the mean over that
  day's recordings (new recordings every night, each one met once: the pipeline's level over the
  data it gets, its night-to-night spread being the noise the detector measures).
"""

from __future__ import annotations

import json
from collections.abc import Iterable
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import numpy as np

from slamreplay.replay.errors import ReplayError
from slamreplay.replay.runs.gitorder import stamp
from slamreplay.replay.runs.history import Commit, History
from slamreplay.replay.runs.suite_run import ROW_METRIC_KEYS, normalized_row

ALL_RECORDINGS = "all recordings"


def ran_at(row: dict[str, Any]) -> str | None:
    """When a results row's run started (ISO 8601): its ``ran_at``, else its manifest's ``timings.started_at``."""
    if row.get("ran_at"):
        return str(row["ran_at"])
    if not row.get("run_dir"):
        return None
    try:
        manifest = json.loads((Path(str(row["run_dir"])) / "manifest.json").read_text())
        return str(manifest["timings"]["started_at"])
    except (OSError, ValueError, KeyError, TypeError):
        return None


def day_of(stamp: str) -> str | None:
    """The UTC day (``YYYY-MM-DD``) of an ISO 8601 time (one without a zone is taken as UTC); None if not one."""
    try:
        t = datetime.fromisoformat(stamp)
    except ValueError:
        return None
    return (t if t.tzinfo else t.replace(tzinfo=timezone.utc)).astimezone(timezone.utc).date().isoformat()


def matches(version: str, wanted: str) -> bool:
    """Whether code version ``version`` is ``wanted`` (a full or abbreviated sha, or a whole version string)."""
    return version == wanted or (len(wanted) >= 7 and version.startswith(wanted))


def history_by_date(rows: Iterable[dict[str, Any]], version: str | None = None, suite: str = "") -> History:
    """The history of results ``rows`` over the days they ran (see the module docstring).

    Parameters
    ----------
    rows : ``results.jsonl`` rows, each with its ``code_version`` and a run directory or ``ran_at`` (rows with
        neither, whose run left no manifest, are left out); a ``suite_id`` is listed with its day
    version : only the rows of this code version (a sha, at least 7 hex digits of one, or a whole version)
    suite : the suite's name, for the report

    Returns
    -------
    History
        One "commit" per day, oldest first: ``sha`` and ``date`` the day, ``subject`` the code versions that ran
        that day; its status row lists them (``versions``) and the suites (``suites``).
    """
    latest: dict[str, dict[tuple[Any, ...], tuple[float, dict[str, Any]]]] = {}
    found = False
    for r in rows:
        code = str(r.get("code_version") or "unknown")
        if version is not None and not matches(code, version):
            continue
        found = True
        when = ran_at(r)
        day = day_of(when) if when else None
        if when is None or day is None:
            continue
        cell = (r.get("recording"), r.get("recording_seed"), r.get("pipeline"), r.get("variant"), r.get("seed"))
        kept = latest.setdefault(day, {}).get(cell)
        if kept is None or kept[0] <= stamp(when):
            latest[day][cell] = (stamp(when), {**normalized_row(r), "code_version": code, "ran_at": when})
    if version is not None and not found:
        raise ReplayError(f"no run of code version {version!r} in this history: give one of its versions")
    days = sorted(latest)
    by_day = {d: [r for _, r in sorted(latest[d].values(), key=lambda t: t[0])] for d in days}
    recordings: dict[tuple[str, str], set[str]] = {}
    seen_on: dict[tuple[str, str, str], set[str]] = {}
    for d, rs in by_day.items():
        for r in rs:
            pv = (str(r["pipeline"]), str(r["variant"]))
            recordings.setdefault(pv, set()).add(str(r["recording"]))
            seen_on.setdefault((str(r["recording"]), *pv), set()).add(d)
    commits, status, out_rows = [], {}, {}
    for d in days:
        rs = by_day[d]
        # a recording met on one day only, beside others: its runs are listed, drawn only in the pool
        alone = [len(recordings[(str(r["pipeline"]), str(r["variant"]))]) > 1
                 and len(seen_on[(str(r["recording"]), str(r["pipeline"]), str(r["variant"]))]) == 1 for r in rs]
        pooled = [_pooled(d, pv, [r for r in rs if (str(r["pipeline"]), str(r["variant"])) == pv])
                  for pv in sorted(recordings) if len(recordings[pv]) > 1]
        versions = list(dict.fromkeys(str(r["code_version"]) for r in rs))
        suites = list(dict.fromkeys(str(r["suite_id"]) for r in rs if r.get("suite_id")))
        subject = "code " + ", ".join(v[:10] + v[40:] if len(v) > 40 else v[:10] for v in versions)
        commits.append(Commit(d, d, subject))
        status[d] = {"type": "commit", "commit": d, "date": d, "subject": subject, "versions": versions,
                     "suites": suites, "cells": len(rs), "suite": suite,
                     "status": "succeeded" if all(r.get("status") == "succeeded" for r in rs) else "partial"}
        out_rows[d] = [{**r, "alone": True} if one else r for r, one in zip(rs, alone, strict=True)]
        out_rows[d] += [r for rows_ in pooled for r in rows_]
    return History(commits, status, out_rows)


def _pooled(day: str, pv: tuple[str, str], rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """The day's ``all recordings`` rows of one pipeline and variant: per run seed, each metric's mean over the
    recordings (and recording seeds) whose cell succeeded and reported it."""
    out = []
    for seed in sorted({int(r.get("seed") or 0) for r in rows}):
        mine = [r for r in rows if int(r.get("seed") or 0) == seed]
        ok = [r for r in mine if r.get("status") == "succeeded"]
        row: dict[str, Any] = {"recording": ALL_RECORDINGS, "recording_seed": None, "pipeline": pv[0],
                               "variant": pv[1], "seed": seed, "key": f"{day}/{ALL_RECORDINGS}/{pv[0]}/{pv[1]}/{seed}",
                               "status": "succeeded" if ok else "failed", "run_dir": None, "pooled": len(mine),
                               "error": None if ok else "no cell of this day succeeded"}
        for key in ROW_METRIC_KEYS:
            row[key] = {}
            for r in ok:
                row[key].update({k: v for k, v in r.get(key, {}).items() if k not in row[key]})
        values: dict[str, list[float]] = {}
        for r in ok:
            for name, v in r.get("metrics", {}).items():
                if isinstance(v, (int, float)):
                    values.setdefault(name, []).append(float(v))
        row["metrics"] = {name: float(np.mean(vs)) for name, vs in values.items()}
        out.append(row)
    return out


def store_rows(history: History) -> list[dict[str, Any]]:
    """Every cell row of a history store (``run_history``'s), for :func:`history_by_date`."""
    return [r for c in history.commits for r in history.cells(c.sha)]
