"""The runs table (``/`` and ``/runs``): every job, paged, sorted and filtered in SQL, its state in the URL.

A page reads one page of rows from the store (metric values included: `JobService` copies
them from ``metrics.json`` when a job ends, and older jobs are read once, here, the first
time a table is drawn), so its cost does not grow with the number of runs on disk. The same
view exports as CSV (every page). Renaming, tagging, cancelling and deleting a job: ``job_actions``.
"""

from __future__ import annotations

import csv
import io
import re
import time
from collections.abc import Iterator
from dataclasses import replace
from typing import Annotated, Any
from urllib.parse import urlencode

from fastapi import APIRouter, Depends, Query, Request
from fastapi import Path as PathParam
from fastapi.responses import HTMLResponse, RedirectResponse, Response, StreamingResponse

from slamreplay.api.service.deps import JobsDep, get_jobs
from slamreplay.api.service.jobs import JobService
from slamreplay.api.service.models import JOB_ID
from slamreplay.api.service.runs_groups import Group, best_means, runs_of, select_groups, stat_cell
from slamreplay.api.service.runs_query import (
    COLUMNS,
    GROUP_KEYS,
    PAGE_SIZES,
    RunsView,
    best_first,
    metric_heading,
    order_sql,
    parse_view,
    where_sql,
)
from slamreplay.api.service.store import ACTIVE, JOB_STATUSES
from slamreplay.api.service.store_runs import RunRow
from slamreplay.api.web.pages import PAGE_ERRORS, duration_text, suite_key, web_session
from slamreplay.api.web.pages import error_response as _error
from slamreplay.api.web.pages import page_lists as _lists
from slamreplay.api.web.pages import page_response as _page
from slamreplay.api.web.runs_charts import view_chart
from slamreplay.replay.errors import ReplayError

JobPath = Annotated[str, PathParam(pattern=JOB_ID)]
router = APIRouter(dependencies=[Depends(web_session)], include_in_schema=False)
PREVIEW_RUNS = 5  # the newest runs listed in a group's row (all of them: its link)


def _when(t: float | None) -> str:
    return "" if t is None else time.strftime("%Y-%m-%d %H:%M:%S", time.gmtime(t))


def _clock(t: float | None, day_of: float) -> str:
    """A time of the same UTC day as ``day_of`` as its clock time only (the table stays narrow), else in full."""
    if t is None:
        return ""
    same_day = time.gmtime(t)[:3] == time.gmtime(day_of)[:3]
    return time.strftime("%H:%M:%S", time.gmtime(t)) if same_day else _when(t)


def first_line(text: str | None, most: int = 160) -> str:
    """The first line of ``text``, cut to ``most`` characters (an ellipsis says so)."""
    line = (text or "").strip().splitlines()[0] if (text or "").strip() else ""
    return line if len(line) <= most else line[:most - 1] + "…"


def backfill_metrics(jobs: JobService) -> int:
    """Copy the metric values of succeeded jobs that have none in the store (an older server's) from their
    metrics.json, once; how many were read."""
    ids = jobs.store.unscored()
    if ids:
        jobs.store.set_metrics({i: jobs.metric_values(i) for i in ids})
    return len(ids)


def differing_config(rows: list[RunRow]) -> list[str]:
    """Config keys whose submitted value is not the same in every row (a key left out counts as its default)."""
    keys = sorted({k for r in rows for k in r.job.config})
    return [k for k in keys if len({repr(r.job.config.get(k, "\0default")) for r in rows}) > 1]


def _duration(r: RunRow) -> float | None:
    j = r.job
    if j.started is None:
        return None
    return (j.finished if j.finished is not None else time.time()) - j.started


def made_by_text(j: Any) -> str:
    """Who made a run: the person who submitted it, and for a pushed run where it was made."""
    if j.source:
        src = j.source
        host = src.get("origin") or src.get("host") or src.get("address") or "elsewhere"  # api/service/push.py's source
        who = j.made_by or src.get("pushed_by")
        return f"{who + ', ' if who else ''}pushed from {host}"
    return j.made_by or ""


def and_where(view: RunsView, condition: str) -> str:
    """The view's condition and ``condition`` (both must hold)."""
    return f"({view.where}) and {condition}" if view.where else condition


def _cells(r: RunRow, view: RunsView, config_keys: list[str]) -> dict[str, Any]:
    j = r.job
    commit = j.git_commit or ""
    return {"job": j, "recording": r.recording_name or j.recording_id[:8], "variant": r.variant or "",
            "created": _when(j.created)[:16], "started": _clock(j.started, j.created),
            "finished": _clock(j.finished, j.created), "when": _when(j.created),
            "duration": duration_text(_duration(r)), "error": first_line(j.error), "active": j.status in ACTIVE,
            "metrics": [(j.metrics or {}).get(c) for c in view.cols],
            "config": [j.config.get(k) for k in config_keys],
            "commit": commit[:8] + ("-dirty" if commit.endswith("-dirty") else ""),
            "commit_url": view.url(where=and_where(view, f"commit = {commit}"), page=1) if commit else "",
            "made_by": made_by_text(j)}


def _menu(chosen: tuple[str, ...], available: list[str]) -> list[tuple[str, bool]]:
    """A column menu's entries: the chosen, in their order, then the others by name; (name, chosen)."""
    return [(c, True) for c in chosen] + [(c, False) for c in sorted(set(available) - set(chosen))]


def sort_choices(view: RunsView) -> list[tuple[str, str]]:
    """The sort menu's choices (a phone shows no column headings): (sort key, label)."""
    out = [("-created", "newest first"), ("created", "oldest first")]
    for m in view.cols:
        best = best_first(m)
        worst = best[1:] if best.startswith("-") else f"-{best}"
        out += [(best, f"{m}: best first"), (worst, f"{m}: worst first")]
    out += [("n", "fewest runs first"), ("-n", "most runs first"), ("group", "by group")] if view.group else [
        ("name", "by name")]
    if view.sort not in dict(out):
        out.append((view.sort, f"by {view.sort.lstrip('-')}{' (descending)' if view.sort.startswith('-') else ''}"))
    return out


def runs_ctx(request: Request, view: RunsView) -> dict[str, Any]:
    """What ``_runs.html`` draws: one page of the view (runs, or groups of runs), its headings, pager, column menu
    and the filter choices."""
    jobs = get_jobs(request)
    backfill_metrics(jobs)
    where, args = where_sql(view)
    ctx: dict[str, Any] = {}
    if view.group:
        groups = select_groups(jobs.store, view, where, args, PREVIEW_RUNS)
        total = len(groups)
        pages = max(1, -(-total // view.per))
        if view.page > pages:
            view = replace(view, page=pages)
        shown = groups[(view.page - 1) * view.per: view.page * view.per]
        best = best_means(shown, view.cols)
        ctx = {"groups": [{"g": g, "link": runs_of(view, g), "preview": g.runs,
                           "cells": [stat_cell(m, g.stats.get(m), g.n, best.get(m)) for m in view.cols]}
                          for g in shown], "runs_total": sum(g.n for g in groups), "rows": []}
        config_keys: list[str] = []
    else:
        order = order_sql(view)
        rows, total = jobs.store.select_runs(where, args, order, view.per, (view.page - 1) * view.per)
        pages = max(1, -(-total // view.per))
        if view.page > pages:  # past the end (runs deleted since the link was made): the last page
            view = replace(view, page=pages)
            rows, total = jobs.store.select_runs(where, args, order, view.per, (view.page - 1) * view.per)
        config_keys = differing_config(rows) if "config" in view.show else []
        ctx = {"rows": [_cells(r, view, config_keys) for r in rows], "groups": None}
    chart = view_chart(jobs.store, view, where, args, ctx["groups"])
    recs = jobs.store.list_recordings()
    listed_metrics, listed_config = jobs.store.json_keys(where, args)
    group_choices = list(GROUP_KEYS) + [f"config.{k}" for k in listed_config]
    return {**ctx, "view": view, "total": total, "pages": pages, "config_keys": config_keys,
            "metric_cols": [metric_heading(c) for c in view.cols], "metric_menu": _menu(view.cols, listed_metrics),
            "column_menu": [(c, COLUMNS[c], on) for c, on in _menu(view.show, list(COLUMNS))],
            "group_menu": _menu(view.group, group_choices), "sort_choices": sort_choices(view),
            "chart_svg": chart,
            "chart_x": ["seed", "created", "commit", *[f"config.{k}" for k in listed_config], "parallel"],
            "chart_metrics": sorted({*listed_metrics, *view.cols, *([view.chart] if view.chart else [])}),
            "page_sizes": PAGE_SIZES, "statuses": JOB_STATUSES,
            "filter_recordings": recs, "filter_pipelines": jobs.store.pipelines_used(),
            "filter_tags": jobs.store.tag_counts(), "csv_url": view.url("/runs.csv", page=1),
            "here": view.url("/runs")}


def _view(request: Request) -> RunsView:
    """The view the request's query asks for."""
    query: dict[str, list[str]] = {}
    for k, v in request.query_params.multi_items():
        query.setdefault(k, []).append(v)
    return parse_view(query)


@router.get("/")
def home_page(request: Request, uploaded: Annotated[str | None, Query(max_length=64)] = None) -> HTMLResponse:
    """The main page: the runs table first, then recordings, a job form, suites and compare (``/#recordings`` ...)."""
    from slamreplay.replay.engine.pipeline import all_pipelines

    view = _view(request)
    lists = _lists(request)
    example = None
    if lists["recordings"]:
        first = lists["recordings"][0]
        example = (f'seeds = [1, 2, 3]\n\n[recordings.{suite_key(first.filename)}]\nid = "{first.id}"\n\n'
                   '[pipelines.odometry]\n\n[pipelines.dslam]\n')
    ctx = runs_ctx(request, view)
    names = lists["rec_names"]
    return _page(request, "index.html", 422 if view.errors else 200, **lists, **ctx,
                 uploaded=names.get(uploaded or "", uploaded), uploaded_id=uploaded,
                 pipelines=sorted(all_pipelines()), example=example, full=True,
                 compare_options=compare_options(lists["suites"], lists["jobs"], names))


def compare_options(suites: list[Any], jobs: list[Any], rec_names: dict[str, str]) -> list[dict[str, Any]]:
    """The compare form's choices (suites, then succeeded jobs, newest first), with B the newest and A the one
    before it, so that the form never starts with A = B."""
    opts = [{"id": s.id, "label": f"suite {s.name} ({s.id[:8]})"} for s, _ in suites]
    opts += [{"id": j.id, "label": f"job {j.name or j.id[:8]}: {j.pipeline} on {rec_names.get(j.recording_id, '?')}, "
                                   f"seed {j.seed}"} for j in jobs if j.status == "succeeded"]
    for i, o in enumerate(opts):
        o["a"], o["b"] = i == (1 if len(opts) > 1 else 0), i == 0
    return opts


@router.get("/runs")
def runs_page(request: Request) -> HTMLResponse:
    """The runs table alone (what its sort, filter and page links open): it reads one page of rows, whatever the
    number of recordings and suites."""
    view = _view(request)
    return _page(request, "index.html", 422 if view.errors else 200, **runs_ctx(request, view), full=False)


@router.get("/ui/part/runs")
def runs_part(request: Request) -> HTMLResponse:
    """The table alone, for the live refresh while a listed job is queued or running."""
    return _page(request, "_runs.html", **runs_ctx(request, _view(request)))


def _csv_text(v: Any) -> str:
    """A text cell that a spreadsheet would run as a formula (= + - @) is quoted with a leading apostrophe."""
    s = "" if v is None else str(v)
    return "'" + s if s[:1] in ("=", "+", "-", "@") else s


@router.get("/runs.csv")
def runs_csv(request: Request) -> Response:
    """The view as CSV: every page, the chosen metric columns with units, the config as JSON."""
    import json

    view = _view(request)
    if view.errors:
        return _error(request, ReplayError("; ".join(view.errors)))
    jobs = get_jobs(request)
    backfill_metrics(jobs)
    where, args = where_sql(view)
    heads = [metric_heading(c) for c in view.cols]
    headers = {"Content-Disposition": f'attachment; filename="{"groups" if view.group else "runs"}.csv"'}
    if view.group:
        return StreamingResponse(_group_lines(view, select_groups(jobs.store, view, where, args, PREVIEW_RUNS), heads),
                                 media_type="text/csv; charset=utf-8", headers=headers)
    rows, _ = jobs.store.select_runs(where, args, order_sql(view))

    def lines() -> Iterator[str]:
        buf = io.StringIO()
        w = csv.writer(buf)
        w.writerow(["id", "name", "tags", "note", "recording", "recording_id", "pipeline", "variant", "seed",
                    "created", "started", "finished", "duration_s", "status", "error", "config", "commit", "made_by",
                    *[h["name"] + (f" [{h['unit']}]" if h["unit"] else "") for h in heads]])
        for r in rows:
            j = r.job
            d = _duration(r)
            w.writerow([j.id, _csv_text(j.name), _csv_text(" ".join(j.tags)), _csv_text(j.note), r.recording_name,
                        j.recording_id, j.pipeline, r.variant or "", j.seed, _when(j.created), _when(j.started),
                        _when(j.finished), "" if d is None else f"{d:.3f}", j.status,
                        _csv_text(first_line(j.error, 10_000)), json.dumps(j.config, sort_keys=True),
                        j.git_commit or "", _csv_text(made_by_text(j)),
                        *["" if (j.metrics or {}).get(c) is None else repr((j.metrics or {})[c]) for c in view.cols]])
            yield buf.getvalue()
            buf.seek(0)
            buf.truncate()

    return StreamingResponse(lines(), media_type="text/csv; charset=utf-8", headers=headers)


def _group_lines(view: RunsView, groups: list[Group], heads: list[dict[str, str]]) -> Iterator[str]:
    """The groups of a grouped view as CSV lines: the group keys, the number of runs, and per metric its mean,
    standard deviation, minimum, maximum and how many runs report it."""
    buf = io.StringIO()
    w = csv.writer(buf)
    w.writerow([*view.group, "runs", *[f"{h['name']} {s}" + (f" [{h['unit']}]" if h["unit"] and s != "n" else "")
                                       for h in heads for s in ("mean", "std", "min", "max", "n")]])
    for g in groups:
        cells: list[str] = [_csv_text(lab) if k == "recording" else _csv_text(v if v is not None else "")
                            for k, v, lab in zip(view.group, g.values, g.labels, strict=True)]
        cells.append(str(g.n))
        for m in view.cols:
            st = g.stats.get(m)
            cells += ["", "", "", "", "0"] if st is None else [
                repr(st.mean), "" if st.std is None else repr(st.std), repr(st.lo), repr(st.hi), str(st.n)]
        w.writerow(cells)
        yield buf.getvalue()
        buf.seek(0)
        buf.truncate()


@router.get("/ui/runs/compare")
def compare_selected(request: Request, jobs: JobsDep,
                     sel: Annotated[list[str] | None, Query(max_length=32)] = None) -> Response:
    """The selected runs, straight to their comparison: two succeeded runs of one recording, pipeline and seed to
    the paired comparison (``/ui/compare?a=...&b=...``), any others to their comparison at its stable URL
    (``/ui/compare?runs=...``: two as a diff, more side by side)."""
    from slamreplay.api.service.compare_runs import MAX_RUNS

    ids = list(dict.fromkeys(s for s in sel or [] if re.fullmatch(JOB_ID, s)))
    if len(ids) < 2:
        return _error(request, ReplayError("select at least two runs (the boxes in the table's first column), "
                                           "then Compare selected"))
    if len(ids) > MAX_RUNS:
        return _error(request, ReplayError(f"{len(ids)} runs selected: compare at most {MAX_RUNS} at once"))
    try:
        chosen = [jobs.get(i) for i in ids]
    except PAGE_ERRORS as err:
        return _error(request, err)
    a, b = chosen[0], chosen[-1]
    if (len(chosen) == 2 and all(j.status == "succeeded" for j in chosen) and a.recording_id == b.recording_id
            and a.pipeline == b.pipeline and a.seed == b.seed):
        return RedirectResponse("/ui/compare?" + urlencode({"a": a.id, "b": b.id}), 303)
    return RedirectResponse("/ui/compare?runs=" + ",".join(ids), 303)
