"""A suite's history in the service: its metrics over the code versions it was run on, and where they changed.

Every cell a service suite runs records the code it ran on (the job's manifest, ``git_commit``); the
suites sent under one name, oldest first, are grouped by that version, each version a point of the
history (the rows of its latest suites, one per cell), and the changes are found as
``slamreplay history`` finds them (``slamreplay.replay.runs.changepoints``). ``GET
/history/suites/{name}`` returns it as JSON for dashboards; the web page draws it (``slamreplay.api.web.history_web``).

When the service runs from a git checkout, ``POST /history/suites/{name}/runs`` (``{"rev": "..."}``) and the
page's "Run this suite on commit" form send the latest suite of that name again, its cells run by that
commit's own code (``slamreplay.replay.runs.revisions``): a new point of the history.
"""

from __future__ import annotations

from collections import Counter
from datetime import datetime, timezone
from pathlib import Path as FsPath
from typing import Annotated, Any, Literal

import numpy as np
from fastapi import APIRouter, Depends, Path, Query, Request
from pydantic import BaseModel, Field

from slamreplay.api.service.audit import record_suite
from slamreplay.api.service.deps import ERRORS, require_token
from slamreplay.api.service.errors import ConflictError, NotFoundError
from slamreplay.api.service.suites import SuiteRow, SuiteService
from slamreplay.api.service.suites_routes import SuiteOut, SuitesDep
from slamreplay.replay.runs.changepoints import Change, detect_changes
from slamreplay.replay.runs.history import Commit, History, git_order, history_of_versions, series
from slamreplay.replay.runs.history_dates import history_by_date, ran_at

SUITES_READ = 10_000
# a suite's name is any string its file gives (spaces, slashes...): the route takes the rest of the path
SuiteName = Annotated[str, Path(min_length=1, max_length=256, description="a suite's name, URL-encoded")]
router = APIRouter(dependencies=[Depends(require_token)], responses=ERRORS, tags=["suites"])


def _subjects(repo: FsPath | None, versions: list[str]) -> dict[str, str]:
    """Commit subjects of the versions ``repo`` has (a ``<sha>-dirty...`` version: its commit's, so marked)."""
    from slamreplay.replay.errors import ReplayError
    from slamreplay.replay.runs.gitorder import SHA, known_commits
    from slamreplay.replay.runs.history import commit_info

    base = {v: m.group(1) for v in versions if (m := SHA.fullmatch(v))}
    if repo is None or not base:
        return {}
    try:
        info = commit_info(repo, sorted(known_commits(repo, sorted(set(base.values())))))
    except (ReplayError, OSError):
        return {}
    return {v: info[b].subject + ("" if v == b else " (with uncommitted changes)") for v, b in base.items()
            if b in info}


def service_repo() -> FsPath | None:
    """The git checkout the service runs from (``find_repo``), or None."""
    from slamreplay.replay.errors import ReplayError
    from slamreplay.replay.runs.revisions import find_repo

    try:
        return find_repo()
    except ReplayError:
        return None


def run_on_revision(suites: SuiteService, name: str, rev: str) -> SuiteRow:
    """Send the latest suite named ``name`` again, its cells run by the code of commit ``rev``.

    NotFoundError for an unknown name; ConflictError when the service does not run from a git checkout;
    ReplayError (422) for a revision git does not know."""
    from slamreplay.replay.errors import ReplayError
    from slamreplay.replay.runs.revisions import resolve

    latest = max((s for s in suites.recent(SUITES_READ) if s.name == name), key=lambda s: s.created, default=None)
    if latest is None:
        raise NotFoundError(f"no suite named {name!r}: GET /suites lists the suites and their names")
    repo = service_repo()
    if repo is None:
        raise ConflictError("this service does not run from a git checkout, so it runs suites on its own code "
                            "only: start it from a clone of the slamreplay repository to run other commits")
    try:
        sha = resolve(repo, rev.strip())
    except ReplayError:  # its message names the server's folder
        raise ReplayError(f"unknown revision {rev.strip()!r}: give a commit, branch or tag that `git rev-parse` "
                          "knows in the checkout the service runs from") from None
    row, text, _ = suites.get(latest.id)
    return suites.submit(text, row.format, rev=sha)


def ended_suites(suites: SuiteService, name: str) -> list[tuple[SuiteRow, list[dict[str, Any]]]]:
    """The ended suites named ``name``, oldest first, each with its cells' results rows; NotFoundError if none."""
    named = sorted((s for s in suites.recent(SUITES_READ) if s.name == name), key=lambda s: s.created)
    if not named:
        raise NotFoundError(f"no suite named {name!r}: GET /suites lists the suites and their names")
    out = []
    for s in named:
        _, _, cells = suites.get(s.id)
        progress = suites.progress(cells)
        if progress["ended"] == progress["cells"]:
            out.append((s, [suites.result_row(c) for c in cells]))
    return out


def suite_history_by_date(suites: SuiteService, name: str, version: str | None = None) -> tuple[History, list[str]]:
    """The history of the ended suites named ``name`` over the days their runs started (``history_dates``: every
    code version's runs, or ``version``'s), and every code version they ran, in the order they first ran."""
    rows = []
    for s, got in ended_suites(suites, name):
        sent = datetime.fromtimestamp(s.created, timezone.utc).isoformat(timespec="seconds")
        # a run is dated by its manifest; one without (deleted) by its suite
        rows += [{**r, "suite_id": s.id, "ran_at": r.get("ran_at") or ran_at(r) or sent} for r in got]
    versions = list(dict.fromkeys(str(r.get("code_version") or "unknown") for r in rows))
    return history_by_date(rows, version, name), versions


def suite_history(suites: SuiteService, name: str) -> tuple[History, dict[str, list[str]]]:
    """The history of the ended suites named ``name``, and the suite ids of each version; NotFoundError if none.

    Versions in git's order in the checkout the service runs from (``history.git_order``), whenever they ran: a
    commit run after a newer one still comes before it; versions that checkout does not know come last, by the
    date they first ran, each with a note."""
    rows: dict[str, dict[tuple[Any, ...], dict[str, Any]]] = {}
    first: dict[str, float] = {}
    ids: dict[str, list[str]] = {}
    for s, got in ended_suites(suites, name):
        seen = Counter(str(r["code_version"]) for r in got if r.get("code_version"))
        version = seen.most_common(1)[0][0] if seen else "unknown"
        first.setdefault(version, s.created)
        ids.setdefault(version, []).append(s.id)
        for r in got:  # a later suite of the same version wins for the same cell
            rows.setdefault(version, {})[(r["recording"], r.get("recording_seed"), r["pipeline"], r["variant"],
                                          r.get("seed"))] = r
    repo = service_repo()
    subjects = _subjects(repo, list(first))
    commits = git_order(repo, [Commit(v, datetime.fromtimestamp(first[v], timezone.utc).isoformat(timespec="seconds"),
                                      subjects.get(v, "")) for v in sorted(first, key=lambda v: first[v])])
    return history_of_versions([(c, list(rows[c.sha].values())) for c in commits]), ids


def order_note(history: History) -> str:
    """How the versions are ordered, in a sentence."""
    stray = sum(1 for c in history.commits if c.note)
    text = "git's order (git rev-list --topo-order of the server's checkout), whenever each version ran"
    if stray:
        text += (f"; {stray} version(s) the server's checkout cannot place (another clone's commits, or no checkout) "
                 "come last, by the date they first ran")
    return text


def history_json(history: History, changes: list[Change], ids: dict[str, list[str]], name: str) -> dict[str, Any]:
    """The history for dashboards: versions, each series' points (mean, sd, seeds), the changes."""
    return {"suite": name, "by": "commit", "order": order_note(history),
            "versions": [{"code_version": c.sha, "first_run": c.date, "subject": c.subject,
                          "suites": ids.get(c.sha, []), "status": history.status.get(c.sha, {}).get("status"),
                          "placed": c.note or "git"} for c in history.commits],
            "series": _series_json(history, "version"), "changes": [ch.to_json() for ch in changes]}


def history_json_by_date(history: History, changes: list[Change], name: str, version: str | None) -> dict[str, Any]:
    """The history over days for dashboards: the days (their code versions and suites), each series' points, the
    changes (each between two days, ``previous_date`` and ``date``)."""
    days = [{"date": c.sha, **{k: history.status[c.sha].get(k) for k in ("versions", "suites", "status")}}
            for c in history.commits]
    moved = [{**{k: v for k, v in ch.to_json().items() if k not in ("commit", "previous", "report")},
              "date": ch.commit, "previous_date": ch.previous} for ch in changes]
    return {"suite": name, "by": "date", "version": version, "days": days, "series": _series_json(history, "date"),
            "changes": moved}


def _series_json(history: History, point: str) -> list[dict[str, Any]]:
    """Each series' points: the point's key (a version or a day), the seeds' values, their mean and sd."""
    out_series = []
    for (rec, pipe, variant), by_metric in sorted(series(history).items()):
        for metric, values in sorted(by_metric.items()):
            points = []
            for c, v in zip(history.commits, values, strict=True):
                xs = list(v.values())
                points.append({point: c.sha, "n": len(xs), "values": xs,
                               "mean": float(np.mean(xs)) if xs else None,
                               "sd": float(np.std(xs, ddof=1)) if len(xs) > 1 else None})
            out_series.append({"recording": rec, "pipeline": pipe, "variant": variant, "metric": metric,
                               "points": points})
    return out_series


By = Annotated[Literal["commit", "date"], Query(description="commit: over the code versions, in git's order; "
                                                         "date: over the days the runs started")]
Version = Annotated[str | None, Query(max_length=64, description="with by=date: only this code version's runs "
                                                                 "(a sha, 7 or more of its hex digits)")]


@router.get("/history/suites/{name:path}")
def get_suite_history(name: SuiteName, suites: SuitesDep, by: By = "commit", version: Version = None
                      ) -> dict[str, Any]:
    """The metrics of the suites sent under ``name`` over the code versions they ran on (in git's order, whenever
    they ran), or with ``by=date`` over the days their runs started, and the changes found between consecutive
    points (the method of ``slamreplay history``)."""
    if by == "date":
        dated, _versions = suite_history_by_date(suites, name, version or None)
        return history_json_by_date(dated, detect_changes(dated), name, version or None)
    history, ids = suite_history(suites, name)
    return history_json(history, detect_changes(history), ids, name)


class RevIn(BaseModel):
    rev: str = Field(min_length=1, max_length=256, description="a commit, branch or tag that `git rev-parse` knows")


@router.post("/history/suites/{name:path}/runs", status_code=202)
def run_suite_on_revision(request: Request, name: SuiteName, body: RevIn, suites: SuitesDep) -> SuiteOut:
    """Send the latest suite named ``name`` again with its cells run by the code of commit ``rev`` (the service
    must run from a git checkout: else 409; an unknown revision is a 422); the new suite, as ``POST /suites``."""
    row = run_on_revision(suites, name, body.rev)
    record_suite(request, suites, row, rev=body.rev)
    return SuiteOut.of(suites, row, suites.get(row.id)[2])
