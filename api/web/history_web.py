"""A suite's history on the web page: ``/ui/history/{name}`` draws the metrics of the suites sent under one name
over the code versions (or days) they ran on, with the changes found (``slamreplay.api.service.history_routes``
computes both), and its "Run this suite on commit" form sends the suite again at another commit.
"""

from __future__ import annotations

from fastapi import APIRouter, Depends, Request
from fastapi.responses import HTMLResponse, RedirectResponse, Response
from markupsafe import Markup
from starlette.concurrency import run_in_threadpool

from slamreplay.api.service.audit import record_suite
from slamreplay.api.service.history_routes import (
    By,
    SuiteName,
    Version,
    order_note,
    run_on_revision,
    service_repo,
    suite_history,
    suite_history_by_date,
)
from slamreplay.api.service.suites_routes import SuitesDep
from slamreplay.api.web.pages import PAGE_ERRORS, web_session
from slamreplay.api.web.pages import error_response as _error
from slamreplay.api.web.pages import page_response as _page
from slamreplay.replay.metric_registry import axis_bounds
from slamreplay.replay.runs.changepoints import detect_changes
from slamreplay.replay.runs.history import series

page = APIRouter(dependencies=[Depends(web_session)], include_in_schema=False)


@page.get("/ui/history/{name:path}")
def history_page(request: Request, name: SuiteName, suites: SuitesDep, by: By = "commit", version: Version = None
                 ) -> HTMLResponse:
    from slamreplay.replay.runs.compare import fmt
    from slamreplay.replay.runs.history_report import plot_svg

    version = version or None
    versions_seen: list[str] = []
    try:
        if by == "date":
            history, versions_seen = suite_history_by_date(suites, name, version)
        else:
            history, ids = suite_history(suites, name)
    except PAGE_ERRORS as err:
        return _error(request, err)
    changes = detect_changes(history)
    over = "days" if by == "date" else "versions"
    groups = []
    for group, by_metric in sorted(series(history).items()):
        plots = [(m, Markup(plot_svg(v, [ch for ch in changes if (ch.recording, ch.pipeline, ch.variant) == group
                                         and ch.metric == m], label=f"{m} of {'/'.join(group)} over {over}",
                                     bounds=axis_bounds(m))))
                 # our own SVG, its text escaped
                 for m, v in sorted(by_metric.items())]
        groups.append({"name": "/".join(group), "plots": plots})
    if by == "date":
        ids = {c.sha: list(history.status[c.sha].get("suites") or []) for c in history.commits}
    points = []
    for k, c in enumerate(history.commits):
        prev = ids.get(history.commits[k - 1].sha, []) if k else []
        mine = ids.get(c.sha, [])
        link = f"/ui/compare?a={prev[-1]}&b={mine[-1]}" if prev and mine and prev[-1] != mine[-1] else None
        points.append({"k": k, "version": c.sha, "short": c.sha[:10], "date": c.date, "subject": c.subject,
                       "suites": mine, "compare": link, "note": c.note,
                       "versions": history.status[c.sha].get("versions", []) if by == "date" else []})
    shown = [{**ch.to_json(), "short": ch.commit[:10], "before": fmt(ch.mean_before),
              "after": "missing" if ch.mean_after is None else fmt(ch.mean_after),
              "delta": fmt(ch.delta, signed=True), "rel": f"{ch.relative:+.1%}" if ch.relative is not None else "",
              "k": ch.index} for ch in changes]
    return _page(request, "suite_history.html", suite_name=name, groups=groups, versions=points, changes=shown,
                 can_run_rev=service_repo() is not None, order=order_note(history), by=by, version=version,
                 versions_seen=versions_seen)



@page.post("/ui/history/{name:path}/runs")
async def run_suite_form(request: Request, name: SuiteName, suites: SuitesDep) -> Response:
    form = await request.form()
    try:
        rev = str(form.get("rev", ""))[:256]
        row = await run_in_threadpool(run_on_revision, suites, name, rev)
    except PAGE_ERRORS as err:
        return _error(request, err)
    await run_in_threadpool(record_suite, request, suites, row, rev)
    return RedirectResponse(f"/ui/suites/{row.id}", 303)
