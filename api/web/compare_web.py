"""The comparison page, ``/ui/compare``: any runs (``?runs=ID1,ID2[,...]``), or two suites or jobs paired over
seeds (``?a=&b=``), each at a stable URL.

Two suites (or jobs) are compared cell by cell as ``slamreplay compare`` does. When nothing pairs
(other pipelines, recordings or seeds), the page says why in one sentence and shows the unpaired
comparison instead of an empty table: the two-run diff for two jobs, the runs side by side for
suites. The comparisons themselves are built in `slamreplay.api.service.compare_runs`.
"""

from __future__ import annotations

import html
from pathlib import Path
from typing import Annotated, Any

from fastapi import APIRouter, Depends, Query, Request
from fastapi.responses import HTMLResponse

from slamreplay.api.service.auth import link_secret
from slamreplay.api.service.compare_runs import (
    job_ids_of,
    many_runs,
    parse_runs,
    require_succeeded,
    runs_of,
    two_runs,
    unpaired_reason,
)
from slamreplay.api.service.deps import get_jobs
from slamreplay.api.service.models import JOB_ID
from slamreplay.api.service.siteguard import REPORT_CSP
from slamreplay.api.service.suites_routes import SuitesDep, service_links
from slamreplay.api.web.compare_plots import plots
from slamreplay.api.web.pages import HERE, PAGE_ERRORS, people_ctx, templates, web_session
from slamreplay.api.web.pages import error_response as _error
from slamreplay.api.web.pages import page_response as _page
from slamreplay.replay.errors import ReplayError
from slamreplay.replay.runs.compare import compare
from slamreplay.replay.runs.diff import parse_tolerances

router = APIRouter(dependencies=[Depends(web_session)], include_in_schema=False)
Ref = Annotated[str | None, Query(pattern=JOB_ID)]


def runs_ctx(request: Request, ids: list[str], tolerances: dict[str, str] | None = None) -> dict[str, Any]:
    """What ``compare_runs.html`` draws for the runs ``ids``: the diff of two, or several side by side."""
    jobs = get_jobs(request)
    if len(ids) == 2:
        require_succeeded(runs_of(jobs, ids))
        ctx = two_runs(jobs, ids, tolerances)
        return {"view": "two", **ctx, **plots(jobs, [ctx["a"], ctx["b"]], ("A", "B")),
                "swap": f"/ui/compare?runs={ids[1]},{ids[0]}"}
    ctx = many_runs(jobs, ids)
    return {"view": "many", **ctx, **plots(jobs, ctx["runs"])}


def deleted_cells(side: Any, name: str) -> list[str]:
    """``A: corridor/odometry/default seed 1, run 1a2b3c4d deleted by alice at ...`` for each deleted run of a side."""
    return [f"{name}: {r.get('recording')}/{r.get('pipeline')}/{r.get('variant')} seed {r.get('seed')}, run "
            f"{str(r.get('job_id'))[:8]} {r.get('error')}" for r in side.rows if r.get("status") == "deleted"]


def light_only(css: str) -> str:
    """``css`` without its dark-scheme block: the comparison report is a self-contained file drawn for a light page
    (its verdict rows, legend and plots have their own light colours), so its page stays light in either scheme."""
    start = css.find("@media (prefers-color-scheme:dark){")
    if start < 0:
        return css
    depth, end = 0, len(css) - 1
    for end in range(css.index("{", start), len(css)):
        depth += {"{": 1, "}": -1}.get(css[end], 0)
        if depth == 0:
            break
    return css[:start] + css[end + 1:]


def _report(request: Request, c: Any, deleted: list[str] | None = None) -> HTMLResponse:
    """The comparison report of ``GET /compare?format=html``, under the page's header."""
    from slamreplay.replay.runs.report import render_html

    report = render_html(c, Path("/"), service_links(str(request.base_url), link_secret(request)))
    nav = templates.get_template("_nav.html").render(**people_ctx(request))
    head, _, body = report.partition("<body>")
    style = "<style>" + light_only((HERE / "static" / "web.css").read_text()) + ":root{color-scheme:light}</style>"
    viewport = ('<meta name="viewport" content="width=device-width, initial-scale=1">'
                '<link rel="icon" href="/static/favicon.svg" type="image/svg+xml">')  # as base.html's head
    head = head.replace("<html>", '<html lang="en">', 1)  # the report has none: screen readers guess the language
    body = body.replace("</body>", "</main></body>")
    if deleted:  # runs deleted since: said where the report begins, by whom and when (never silently absent)
        items = "".join(f"<li>{html.escape(d)}</li>" for d in deleted)
        body = (f'<section id="deleted-runs"><h2>Deleted runs</h2><p>These cells ran, but their runs were deleted: '
                f"the comparison counts them as not succeeded.</p><ul>{items}</ul></section>") + body
    return HTMLResponse(head.replace("</head>", viewport + style + "</head>") + "<body>" + nav + "<main>" + body,
                        headers={"Content-Security-Policy": REPORT_CSP})


def _paired(request: Request, suites: Any, a: str, b: str, tolerance: list[str]) -> HTMLResponse:
    """Suites or jobs A and B cell by cell; when nothing pairs, why, and the unpaired comparison."""
    tolerances = parse_tolerances(tolerance)
    side_a, side_b = suites.side(a), suites.side(b)
    try:
        c = compare(suites.side(a), suites.side(b), tolerances)
    except ReplayError as err:
        if "no cell in common" not in str(err):  # compare's own wording for sides that share no cell
            raise
        c = None
    if c is not None and (c.results or c.failures):
        return _report(request, c, deleted_cells(side_a, "A") + deleted_cells(side_b, "B"))
    ctx: dict[str, Any] = {"reason": unpaired_reason(side_a, side_b), "view": "none", "a_ref": a, "b_ref": b,
                           "deleted": deleted_cells(side_a, "A") + deleted_cells(side_b, "B")}
    ids = list(dict.fromkeys(job_ids_of(side_a) + job_ids_of(side_b)))
    if side_a.kind == "run" and side_b.kind == "run" and len(ids) == 2:
        ctx |= runs_ctx(request, ids, tolerances)
    elif len(ids) >= 2:
        many = many_runs(get_jobs(request), ids[:20])
        ctx |= {"view": "many", **many, **plots(get_jobs(request), many["runs"])}
    return _page(request, "compare_runs.html", **ctx)


@router.get("/ui/compare")
def compare_page(request: Request, suites: SuitesDep, a: Ref = None, b: Ref = None,
                 runs: Annotated[str | None, Query(max_length=2000)] = None,
                 tolerance: Annotated[list[str] | None, Query()] = None) -> HTMLResponse:
    """Any runs (``runs=ID1,ID2,...``; ids or their first 8 digits), or suites/jobs ``a`` and ``b`` paired."""
    tol = [t for t in tolerance or [] if t.strip()]  # the form sends an empty field
    try:
        if runs is not None:
            ids = parse_runs(runs)
            return _page(request, "compare_runs.html", **runs_ctx(request, ids, parse_tolerances(tol)))
        if a is None or b is None:
            raise ReplayError("choose what to compare: ?a=SUITE_OR_JOB&b=SUITE_OR_JOB, or ?runs=ID1,ID2[,...]")
        if a == b:
            raise ReplayError("A and B are the same: choose two different suites or jobs")
        return _paired(request, suites, a, b, tol)
    except PAGE_ERRORS as err:
        return _error(request, err)
