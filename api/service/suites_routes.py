"""Routes for suites and comparisons: ``POST /suites``, ``GET /suites``, ``GET /suites/{id}``, ``GET /compare``.

A suite is sent as TOML (any content type but JSON) or JSON (``application/json``), in the
form ``slamreplay suite run`` reads, with recordings named by id::

    seeds = [1, 2, 3]
    [recordings.robot1]
    id = "<sha256 from POST /recordings>"
    [pipelines.odometry]
    [pipelines.dslam.variants]
    default = {}
    tight = { range_sigma_m = 0.05 }

Its cells become jobs of the job store (reusing jobs with the same inputs). ``GET /compare``
compares two suites, two jobs, or one of each, as ``slamreplay compare`` does: JSON, or the
HTML report with ``Accept: text/html`` or ``format=html``.
"""

from __future__ import annotations

import math
from datetime import datetime, timezone
from typing import Annotated, Any, Literal
from urllib.parse import urlencode

from fastapi import APIRouter, Depends, Path, Query, Request
from fastapi.responses import HTMLResponse, JSONResponse, RedirectResponse
from pydantic import BaseModel, ConfigDict, Field
from starlette.concurrency import run_in_threadpool

from slamreplay.api.service.audit import record_suite
from slamreplay.api.service.auth import link_secret, record, who
from slamreplay.api.service.deps import ERRORS, require_token, viewer_href
from slamreplay.api.service.errors import ApiError
from slamreplay.api.service.models import JOB_ID
from slamreplay.api.service.siteguard import REPORT_CSP
from slamreplay.api.service.store_runs import MAX_NOTE, MAX_TAGS, Labels
from slamreplay.api.service.suites import SuiteCell, SuiteRow, SuiteService
from slamreplay.replay.errors import ReplayError
from slamreplay.replay.runs.compare import Comparison, compare
from slamreplay.replay.runs.diff import parse_tolerances
from slamreplay.replay.runs.report import Links, render_html

MAX_SUITE_BYTES = 1 << 20
SuiteId = Annotated[str, Path(pattern=JOB_ID, description="suite id (32 hex digits)")]
OptRef = Annotated[str | None, Query(pattern=JOB_ID, description="a suite id or a job id (32 hex digits, or the first "
                                                                  "8 of them)")]
SUITE_BODY = {"requestBody": {
    "required": True,
    "description": "a suite file: TOML (any content type but JSON), or the same structure as JSON; recordings by id",
    "content": {"application/toml": {"schema": {"type": "string"}},
                "application/json": {"schema": {"type": "object"}}}}}


class SuiteTooLargeError(ApiError):
    status = 413


def get_suites(request: Request) -> SuiteService:
    suites: SuiteService = request.app.state.suites
    return suites


SuitesDep = Annotated[SuiteService, Depends(get_suites)]


class SuiteCellOut(BaseModel):
    recording: str
    recording_seed: int | None
    pipeline: str
    variant: str
    seed: int
    config: dict[str, Any]
    job_id: str
    reused: bool = Field(description="an existing job with the same inputs serves this cell")
    status: str
    progress: float
    error: str | None
    metrics: dict[str, float]


class SuiteProgressOut(BaseModel):
    status: Literal["running", "succeeded", "finished with failures"]
    cells: int
    ended: int
    counts: dict[str, int] = Field(description="cells by job status")
    fraction: float = Field(ge=0.0, le=1.0)


class SuiteOut(BaseModel):
    id: str
    name: str
    format: Literal["toml", "json"]
    created_at: datetime
    progress: SuiteProgressOut
    cells: list[SuiteCellOut]
    links: dict[str, str]

    @classmethod
    def of(cls, suites: SuiteService, row: SuiteRow, cells: list[SuiteCell]) -> SuiteOut:
        out = []
        for c in cells:
            r = suites.result_row(c)
            out.append(SuiteCellOut(**{k: r[k] for k in ("recording", "recording_seed", "pipeline", "variant", "seed",
                                                          "config", "job_id", "reused", "status", "progress",
                                                          "error", "metrics")}))
        return cls(id=row.id, name=row.name, format=row.format,  # type: ignore[arg-type]
                   created_at=datetime.fromtimestamp(row.created, timezone.utc),
                   progress=SuiteProgressOut(**suites.progress(cells)), cells=out,
                   links={"self": f"/suites/{row.id}", "page": f"/ui/suites/{row.id}",
                          "compare": f"/compare?a={row.id}&b=OTHER_SUITE_OR_JOB"})


router = APIRouter(dependencies=[Depends(require_token)], responses=ERRORS, tags=["suites"])


@router.post("/suites", status_code=202, openapi_extra=SUITE_BODY)
async def submit_suite(request: Request, suites: SuitesDep,
                       tags: Annotated[list[str] | None, Query(max_length=MAX_TAGS, description=(
                           "tags of every job the suite queues (a reused job keeps its own)"))] = None,
                       note: Annotated[str | None, Query(max_length=MAX_NOTE, description=(
                           "a note on every job the suite queues"))] = None) -> SuiteOut:
    """Queue every cell of a suite as a job (or reuse a job with the same inputs); 422 naming a bad key."""
    try:
        labels = Labels.parse(None, [t for raw in tags or [] for t in raw.split(",")], note)
    except ValueError as err:
        raise ReplayError(str(err)) from None
    body = b""
    async for chunk in request.stream():
        body += chunk
        if len(body) > MAX_SUITE_BYTES:
            raise SuiteTooLargeError(f"a suite file is at most {MAX_SUITE_BYTES} bytes")
    try:
        text = body.decode("utf-8")
    except UnicodeDecodeError:
        raise ApiError("the suite is not UTF-8 text: send the TOML file (or JSON) as it is") from None
    fmt = "json" if "json" in request.headers.get("content-type", "") else "toml"
    row = await run_in_threadpool(suites.submit, text, fmt, None, who(request), labels)
    await run_in_threadpool(record_suite, request, suites, row)
    _, _, cells = suites.get(row.id)
    return SuiteOut.of(suites, row, cells)


class PushedCell(BaseModel):
    """A cell of a suite that ran elsewhere and the job its pushed run became."""

    model_config = ConfigDict(extra="forbid")

    recording: str = Field(min_length=1, max_length=200)
    recording_seed: int | None = None
    pipeline: str = Field(min_length=1, max_length=100)
    variant: str | None = Field(default=None, max_length=200)
    seed: int = Field(ge=0, le=2**63 - 1)
    config: dict[str, Any] = Field(default_factory=dict)
    job_id: str = Field(pattern=JOB_ID)


class PushedSuite(BaseModel):
    """``POST /runs/suites``: a suite that ran elsewhere, its runs already pushed (``POST /runs``)."""

    model_config = ConfigDict(extra="forbid")

    name: str = Field(min_length=1, max_length=200)
    text: str = Field(default="", max_length=MAX_SUITE_BYTES, description="the suite file, as it ran")
    cells: list[PushedCell] = Field(min_length=1, max_length=10_000)


@router.post("/runs/suites", status_code=201)
def push_suite(request: Request, body: PushedSuite, suites: SuitesDep) -> SuiteOut:
    """Record a suite that ran elsewhere (`slamreplay push` of a `suite run` folder), so that its page, compare and
    the history of its name count it beside the server's own (runners); 404 names a job not pushed yet."""
    cells = [({k: v for k, v in c.model_dump().items() if k != "job_id"}, c.job_id) for c in body.cells]
    row = suites.add_pushed(body.name, body.text, cells)
    record(request, "suite", row.id, f"{row.name}: {len(cells)} cells run elsewhere and pushed")
    _, _, got = suites.get(row.id)
    return SuiteOut.of(suites, row, got)


@router.get("/suites")
def list_suites(suites: SuitesDep) -> list[SuiteOut]:
    """The 100 newest suites, newest first, with their progress."""
    return [SuiteOut.of(suites, row, suites.get(row.id)[2]) for row in suites.recent(100)]


@router.get("/suites/{suite_id}")
def get_suite(suite_id: SuiteId, suites: SuitesDep) -> SuiteOut:
    """Progress (cells by status, fraction done) and results: each cell's job, status and metrics."""
    row, _, cells = suites.get(suite_id)
    return SuiteOut.of(suites, row, cells)


def service_links(base_url: str, token: str | None) -> Links:
    """Report links into the web page: each run's job page, each A/B pair in the Rerun web viewer."""

    def run(row: Any) -> str | None:
        job = row.get("job_id")
        return f"/ui/jobs/{job}" if job else None

    def pair(ra: Any, rb: Any) -> str | None:
        ja, jb = ra.get("job_id"), rb.get("job_id")
        if not ja or not jb or ra.get("status") != "succeeded" or rb.get("status") != "succeeded":
            return None
        return viewer_href(base_url, token, f"/diff/{ja}-{jb}.rrd")

    return Links(run=run, pair=pair)


def comparison(suites: SuiteService, a: str, b: str, tolerance: list[str] | None) -> Comparison:
    """B against A (each a suite or a job id); 404 unknown, 409 unfinished, 422 nothing in common."""
    return compare(suites.side(a), suites.side(b), parse_tolerances(tolerance or []))


@router.get("/compare", tags=["diff"], responses={200: {"content": {"text/html": {}}}})
def compare_route(request: Request, suites: SuitesDep, a: OptRef = None, b: OptRef = None,
                  runs: Annotated[str | None, Query(max_length=2000, description=(
                      "any runs: ID1,ID2[,...] (job ids or their first 8 digits); two: what changed and the metric "
                      "deltas, as `slamreplay diff`; more: their metrics side by side"))] = None,
                  tolerance: Annotated[list[str] | None, Query(description="NAME=VALUE or NAME=N%; * for all")] = None,
                  format: Annotated[Literal["json", "html"] | None, Query(
                      description="html: the report (also chosen by Accept: text/html)")] = None,
                  ) -> Any:
    """Compare B against A cell by cell (paired t-test over seeds), or any ``runs``: JSON, or the HTML page."""
    wants_html = format == "html" or (format is None and "text/html" in request.headers.get("accept", ""))
    if runs is not None:
        from slamreplay.api.service.compare_runs import parse_runs, runs_json

        ids = parse_runs(runs)
        if wants_html:  # the page draws it (the same URL state), under the page's header and session
            return RedirectResponse("/ui/compare?" + urlencode({"runs": ",".join(ids)}), 303)
        return JSONResponse(_finite(runs_json(suites.jobs, ids)))
    if a is None or b is None:
        raise ApiError("give a and b (suite or job ids), or runs=ID1,ID2[,...]")
    c = comparison(suites, a, b, tolerance)
    if wants_html:
        from pathlib import Path as FsPath
        return HTMLResponse(render_html(c, FsPath("/"), service_links(str(request.base_url), link_secret(request))),
                            headers={"Content-Security-Policy": REPORT_CSP})
    return JSONResponse(_finite(c.to_json() | {"a_id": a, "b_id": b}))


def _finite(x: Any) -> Any:
    """JSON has no NaN or infinity: null instead."""
    if isinstance(x, float):
        return x if math.isfinite(x) else None
    if isinstance(x, dict):
        return {k: _finite(v) for k, v in x.items()}
    if isinstance(x, list | tuple):
        return [_finite(v) for v in x]
    return x
