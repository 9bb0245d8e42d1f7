"""The web page at ``/``: recordings, jobs, suites, metrics, comparisons, and runs in the Rerun web viewer.

Server-rendered Jinja2 templates (``api/templates/``) over the same services as the API; the
only JavaScript (``api/static/web.js``, a dozen lines) refreshes the parts of a page that hold
a queued or running job. "Open in Rerun" opens a job's ``.rrd`` in the Rerun web viewer, which
this service serves itself from the files of the installed rerun-sdk (``slamreplay.api.viewer_assets``).

With ``SLAMREPLAY_TOKEN`` set the page asks for the token once (``/login``) and keeps a session
cookie derived from it (HttpOnly, SameSite=Strict, so another site cannot post forms with it);
the API routes keep requiring the bearer token and do not accept the cookie.
"""

from __future__ import annotations

import contextlib
import hashlib
import hmac
import json
import math
from pathlib import Path
from typing import Annotated, Any, Literal
from urllib.parse import urlencode

from fastapi import APIRouter, Depends, FastAPI, Query, Request
from fastapi import Path as PathParam
from fastapi.responses import FileResponse, HTMLResponse, JSONResponse, RedirectResponse, Response
from fastapi.templating import Jinja2Templates
from starlette.concurrency import run_in_threadpool

from slamreplay.api.deps import JobsDep, RecordingsDep, SettingsDep, get_jobs, rrd_key, viewer_href
from slamreplay.api.errors import ApiError, UnauthorizedError
from slamreplay.api.models import JOB_ID
from slamreplay.api.multipart import form_file, is_form
from slamreplay.api.settings import Settings
from slamreplay.api.suites import ENDED, SuiteService
from slamreplay.api.suites_routes import SuitesDep, comparison
from slamreplay.api.suites_routes import router as suites_router
from slamreplay.recorder.errors import RecorderError
from slamreplay.replay.errors import ReplayError
from slamreplay.replay.pipeline import all_pipelines

HERE = Path(__file__).parent
COOKIE = "slamreplay_session"
templates = Jinja2Templates(directory=HERE / "templates")
JobPath = Annotated[str, PathParam(pattern=JOB_ID)]
PAGE_ERRORS = (ApiError, ReplayError, RecorderError)


class LoginRequiredError(Exception):
    """A page request without a valid session while the server has a token."""


def session_value(token: str) -> str:
    """The session cookie's value: a MAC of a fixed text under the token (the token itself never leaves)."""
    return hmac.new(token.encode(), b"slamreplay web session v1", hashlib.sha256).hexdigest()


def web_session(request: Request, settings: SettingsDep) -> None:
    """Pages need the session cookie when the server has a token."""
    if settings.token is None:
        return
    got = request.cookies.get(COOKIE, "")
    if not got or not hmac.compare_digest(got, session_value(settings.token)):
        raise LoginRequiredError


async def login_required(request: Request, exc: Exception) -> Response:
    if request.method == "GET" and not request.url.path.endswith(".rrd"):
        return RedirectResponse("/login?" + urlencode({"next": request.url.path + (
            f"?{request.url.query}" if request.url.query else "")}), 303)
    return JSONResponse({"detail": "log in at /login with the server's token first"}, 401)


def _fmt(v: Any) -> str:
    if isinstance(v, float):
        return "-" if not math.isfinite(v) else f"{v:.6g}"
    return str(v)


templates.env.filters["num"] = _fmt
templates.env.filters["short"] = lambda s: str(s)[:8]


def _page(request: Request, name: str, status_code: int = 200, **ctx: Any) -> HTMLResponse:
    settings: Settings = request.app.state.settings
    ctx.setdefault("guarded", settings.token is not None)
    return templates.TemplateResponse(request, name, ctx, status_code=status_code)


def _error(request: Request, exc: Exception) -> HTMLResponse:
    status = exc.status if isinstance(exc, ApiError) else 422
    return _page(request, "error.html", status, message=str(exc), status=status)


def _metrics(run_dir: Path) -> list[dict[str, Any]]:
    try:
        doc = json.loads((run_dir / "metrics.json").read_text())
    except (OSError, json.JSONDecodeError):
        return []
    return [{"name": k, **v} for k, v in sorted(doc.get("metrics", {}).items())]


def _job_ctx(request: Request, jobs: Any, job_id: str) -> dict[str, Any]:
    job = jobs.get(job_id)
    run_dir = jobs.run_dir(job_id)
    ctx: dict[str, Any] = {"job": job, "active": job.status not in ENDED, "metrics": [], "manifest": None}
    if job.status == "succeeded":
        ctx["metrics"] = _metrics(run_dir)
        ctx["rerun"] = viewer_href(str(request.base_url), request.app.state.settings.token,
                                   f"/jobs/{job_id}/run.rrd")
    with contextlib.suppress(OSError, json.JSONDecodeError):
        ctx["manifest"] = json.loads((run_dir / "manifest.json").read_text())
    return ctx


def _suite_ctx(suites: SuiteService, suite_id: str) -> dict[str, Any]:
    row, text, cells = suites.get(suite_id)
    rows = [suites.result_row(c) for c in cells]
    tables = []  # one table per pipeline: each has its own metrics
    for pipeline in dict.fromkeys(r["pipeline"] for r in rows):
        mine = [r for r in rows if r["pipeline"] == pipeline]
        tables.append((pipeline, sorted({m for r in mine for m in r["metrics"]}), mine))
    progress = suites.progress(cells)
    return {"suite": row, "text": text, "tables": tables, "progress": progress,
            "active": progress["ended"] < progress["cells"]}


JOBS_SHOWN = 12  # the newest; a suite's page lists its own, GET /jobs all of them


def _lists(request: Request) -> dict[str, Any]:
    jobs = get_jobs(request)
    suites: SuiteService = request.app.state.suites
    recs = jobs.store.list_recordings()
    job_rows = jobs.store.list_jobs(limit=JOBS_SHOWN)
    suite_rows = [(s, suites.progress(suites.get(s.id)[2])) for s in suites.recent(50)]
    return {"recordings": recs, "jobs": job_rows, "suites": suite_rows, "rec_names": {r.id: r.filename for r in recs},
            "jobs_total": sum(jobs.store.count_by_status().values()),
            "jobs_active": any(j.status not in ENDED for j in job_rows),
            "suites_active": any(p["ended"] < p["cells"] for _, p in suite_rows)}


page = APIRouter(dependencies=[Depends(web_session)], include_in_schema=False)
public = APIRouter(include_in_schema=False)


@public.get("/login")
def login_form(request: Request, next: str = "/") -> HTMLResponse:
    return _page(request, "login.html", next=next, wrong=False)


@public.post("/login")
async def login(request: Request, settings: SettingsDep) -> Response:
    form = await request.form()
    token, nxt = str(form.get("token", "")), str(form.get("next", "/"))
    if not nxt.startswith("/") or nxt.startswith("//"):
        nxt = "/"
    if settings.token is not None and not hmac.compare_digest(token.encode(), settings.token.encode()):
        return _page(request, "login.html", 401, next=nxt, wrong=True)
    resp = RedirectResponse(nxt, 303)
    if settings.token is not None:
        resp.set_cookie(COOKIE, session_value(settings.token), httponly=True, samesite="strict", path="/")
    return resp


@public.get("/logout")
def logout() -> Response:
    resp = RedirectResponse("/login", 303)
    resp.delete_cookie(COOKIE, path="/")
    return resp


@page.get("/")
def index(request: Request, uploaded: Annotated[str | None, Query(max_length=64)] = None) -> HTMLResponse:
    example = None
    lists = _lists(request)
    if lists["recordings"]:
        example = (f'seeds = [1, 2, 3]\n\n[recordings.{_name(lists["recordings"][0].filename)}]\n'
                   f'id = "{lists["recordings"][0].id}"\n\n[pipelines.odometry]\n\n[pipelines.dslam]\n')
    return _page(request, "index.html", **lists, uploaded=uploaded, pipelines=sorted(all_pipelines()),
                 example=example)


def _name(filename: str) -> str:
    stem = "".join(ch if ch.isalnum() or ch in "_-" else "_" for ch in Path(filename).stem)[:40]
    return stem if stem and stem[0].isalnum() else f"r{stem}"


@page.get("/ui/part/lists")
def part_lists(request: Request, part: Literal["recordings", "jobs", "suites"]) -> HTMLResponse:
    return _page(request, "_lists.html", **_lists(request), part=part)


@page.post("/ui/recordings")
async def upload_form(request: Request, recordings: RecordingsDep) -> Response:
    content_type = request.headers.get("content-type", "")
    if not is_form(content_type):
        return _error(request, ApiError("send the upload form (multipart/form-data with a field `file`)"))
    try:
        name, chunks = await form_file(request.stream(), content_type, recordings.settings.max_upload_bytes)
        stored = await recordings.upload(chunks, name, None, False)
    except PAGE_ERRORS as err:
        return _error(request, err)
    return RedirectResponse(f"/?uploaded={stored.recording.id}#recordings", 303)


@page.post("/ui/jobs")
async def job_form(request: Request, jobs: JobsDep) -> Response:
    form = await request.form()
    try:
        seed = int(str(form.get("seed", "0")) or 0)
        raw = str(form.get("config", "")).strip()
        config = json.loads(raw) if raw else {}
        if not isinstance(config, dict):
            raise ReplayError('config must be a JSON object, e.g. {"range_sigma_m": 0.05}')
        job = await run_in_threadpool(jobs.submit, str(form.get("recording_id", "")), str(form.get("pipeline", "")),
                                      config, seed)
    except ValueError as err:
        return _error(request, ReplayError(f"bad job form: {err}"))
    except PAGE_ERRORS as err:
        return _error(request, err)
    return RedirectResponse(f"/ui/jobs/{job.id}", 303)


@page.post("/ui/suites")
async def suite_form(request: Request, suites: SuitesDep) -> Response:
    form = await request.form()
    try:
        row = await run_in_threadpool(suites.submit, str(form.get("suite", "")), "toml")
    except PAGE_ERRORS as err:
        return _error(request, err)
    return RedirectResponse(f"/ui/suites/{row.id}", 303)


@page.get("/ui/jobs/{job_id}")
def job_page(request: Request, job_id: JobPath, jobs: JobsDep) -> HTMLResponse:
    try:
        return _page(request, "job.html", **_job_ctx(request, jobs, job_id))
    except PAGE_ERRORS as err:
        return _error(request, err)


@page.get("/ui/part/jobs/{job_id}")
def job_part(request: Request, job_id: JobPath, jobs: JobsDep) -> HTMLResponse:
    return _page(request, "_job.html", **_job_ctx(request, jobs, job_id))


@page.get("/ui/suites/{suite_id}")
def suite_page(request: Request, suite_id: JobPath, suites: SuitesDep) -> HTMLResponse:
    try:
        others = [s for s in suites.recent(50) if s.id != suite_id]
        return _page(request, "suite.html", **_suite_ctx(suites, suite_id), others=others)
    except PAGE_ERRORS as err:
        return _error(request, err)


@page.get("/ui/part/suites/{suite_id}")
def suite_part(request: Request, suite_id: JobPath, suites: SuitesDep) -> HTMLResponse:
    return _page(request, "_suite.html", **_suite_ctx(suites, suite_id))


@page.get("/ui/compare")
def compare_page(request: Request, suites: SuitesDep, a: Annotated[str, Query(pattern=JOB_ID)],
                 b: Annotated[str, Query(pattern=JOB_ID)],
                 tolerance: Annotated[list[str] | None, Query()] = None) -> HTMLResponse:
    """The comparison report of ``GET /compare?format=html``, under the page's header."""
    from slamreplay.api.suites_routes import service_links
    from slamreplay.replay.report import render_html

    try:
        c = comparison(suites, a, b, [t for t in tolerance or [] if t.strip()])  # the form sends an empty field
    except PAGE_ERRORS as err:
        return _error(request, err)
    report = render_html(c, Path("/"), service_links(str(request.base_url), request.app.state.settings.token))
    nav = templates.get_template("_nav.html").render(guarded=request.app.state.settings.token is not None)
    head, _, body = report.partition("<body>")
    style = "<style>" + (HERE / "static" / "web.css").read_text() + "</style>"
    body = body.replace("</body>", "</main></body>")
    return HTMLResponse(head.replace("</head>", style + "</head>") + "<body>" + nav + "<main>" + body)


Key = Annotated[str, PathParam(pattern=r"^[0-9a-f]{32}$")]


def _check_key(settings: Settings, key: str, rrd_path: str) -> None:
    if settings.token is not None and not hmac.compare_digest(key, rrd_key(settings.token, rrd_path)):
        raise UnauthorizedError("wrong key in the .rrd URL: open the run from the web page")


@page.get("/ui/jobs/{job_id}/run.rrd")
def job_rrd(job_id: JobPath, jobs: JobsDep) -> FileResponse:
    return FileResponse(jobs.artifact(job_id, "run.rrd"), media_type="application/octet-stream")


@public.get("/ui/shared/{key}/jobs/{job_id}/run.rrd")
def shared_job_rrd(key: Key, job_id: JobPath, jobs: JobsDep, settings: SettingsDep) -> FileResponse:
    _check_key(settings, key, f"/jobs/{job_id}/run.rrd")
    return FileResponse(jobs.artifact(job_id, "run.rrd"), media_type="application/octet-stream")


@public.get("/ui/shared/{key}/diff/{a}-{b}.rrd")
def shared_diff_rrd(key: Key, a: JobPath, b: JobPath, jobs: JobsDep, settings: SettingsDep) -> FileResponse:
    """One .rrd with job A under runs/A and job B under runs/B (made on the first request)."""
    _check_key(settings, key, f"/diff/{a}-{b}.rrd")
    return FileResponse(jobs.comparison_rrd(a, b), media_type="application/octet-stream")


# The viewer may load and fetch from this server only: its version check and usage statistics
# (requests to other hosts) are blocked by the browser before they leave.
VIEWER_CSP = ("default-src 'self'; script-src 'self' 'unsafe-inline' 'wasm-unsafe-eval'; "
              "style-src 'self' 'unsafe-inline'; img-src 'self' data: blob:; connect-src 'self'; "
              "worker-src 'self' blob:; font-src 'self' data:")
VIEWER_TYPES = {".html": "text/html; charset=utf-8", ".js": "text/javascript", ".wasm": "application/wasm",
                ".ico": "image/x-icon", ".png": "image/png"}


@page.get("/viewer")
def viewer_root(request: Request) -> Response:
    return RedirectResponse("/viewer/" + (f"?{request.url.query}" if request.url.query else ""), 307)


@page.get("/viewer/{name:path}")
async def viewer_file(name: str, settings: SettingsDep) -> Response:
    """The Rerun web viewer's files (``/viewer/?url=...rrd`` opens a recording)."""
    from slamreplay.api.viewer_assets import FILES, ViewerAssetsError, viewer_dir

    name = name or "index.html"
    if name not in FILES:
        return JSONResponse({"detail": f"the web viewer has no file {name}"}, 404)
    try:
        folder = await run_in_threadpool(viewer_dir, settings.runs_dir / "web-viewer")
    except (ViewerAssetsError, OSError) as err:
        return JSONResponse({"detail": f"the Rerun web viewer is not available: {err}"}, 503)
    path = folder / name
    if not path.is_file():
        return JSONResponse({"detail": f"the web viewer has no file {name}"}, 404)
    return FileResponse(path, media_type=VIEWER_TYPES.get(path.suffix, "application/octet-stream"),
                        headers={"Cache-Control": "no-cache", "Content-Security-Policy": VIEWER_CSP})


def install_web(app: FastAPI) -> None:
    """The suites and compare API routes, the web page, its static files and the viewer, on ``app``."""
    from fastapi.staticfiles import StaticFiles

    app.state.suites = SuiteService(app.state.jobs)
    app.add_exception_handler(LoginRequiredError, login_required)
    app.include_router(suites_router)
    app.include_router(public)
    app.include_router(page)
    app.mount("/static", StaticFiles(directory=HERE / "static"), name="static")
