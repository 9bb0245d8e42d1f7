"""The web page at ``/``: recordings, jobs, suites, metrics, comparisons, and runs in the Rerun web viewer.

Server-rendered Jinja2 templates (``api/web/templates/``) over the same services as the API; the
only JavaScript (``api/web/static/web.js``, a dozen lines) refreshes the parts of a page that hold
a queued or running job. "Open in Rerun" opens a job's ``.rrd`` in the Rerun web viewer, which
this service serves itself from the files of the installed rerun-sdk (``slamreplay.api.web.viewer_assets``).
The runs table (``/``, ``/runs``) is in ``api/web/runs_web.py``, a job's page in ``api/web/job_web.py``, comparisons
(``/ui/compare``) in ``api/web/compare_web.py``, and what every page shares (templates, session, error page)
in ``api/web/pages.py``. Ids in every route may be the 8-digit prefixes the page shows (``api/service/idprefix.py``).

With people (``slamreplay users``) the page signs each in with their token (``/login``) into a session kept
on the server (``slamreplay.api.service.auth``); with only ``SLAMREPLAY_TOKEN`` set it asks for that token once and
keeps a session cookie derived from it (HttpOnly, SameSite=Strict). Forms posted with either cookie carry a
CSRF token; the API routes keep requiring the bearer token and do not accept the cookie.
"""

from __future__ import annotations

import hmac
import json
import math
from typing import Annotated, Any, Literal
from urllib.parse import urlencode

from fastapi import APIRouter, Depends, FastAPI, Request
from fastapi import Path as PathParam
from fastapi.responses import FileResponse, HTMLResponse, JSONResponse, RedirectResponse, Response, StreamingResponse
from starlette.concurrency import run_in_threadpool

from slamreplay.api.service.audit import record_suite, submitted_text
from slamreplay.api.service.auth import (
    CSRF_FIELD,
    LoginRequiredError,
    PageForbiddenError,
    check_csrf,
    client_address,
    link_secret,
    page_principal,
    record,
    server_mode,
    session_value,
    sign_in_wait_s,
    who,
)
from slamreplay.api.service.deps import JobsDep, RecordingsDep, SettingsDep, rrd_key
from slamreplay.api.service.errors import ApiError, UnauthorizedError
from slamreplay.api.service.models import JOB_ID
from slamreplay.api.service.multipart import form_file, is_form
from slamreplay.api.service.people import SESSION_TTL_S
from slamreplay.api.service.store_runs import Labels
from slamreplay.api.service.submit_checks import parse_topic_map
from slamreplay.api.service.suites import SuiteService
from slamreplay.api.service.suites_routes import SuitesDep
from slamreplay.api.web.audit_web import page as audit_page
from slamreplay.api.web.compare_web import router as compare_router
from slamreplay.api.web.history_web import page as history_page
from slamreplay.api.web.job_actions import router as job_actions
from slamreplay.api.web.job_web import install_job_files
from slamreplay.api.web.job_web import job_ctx as _job_ctx  # the job page's parts (api/web/job_web.py)
from slamreplay.api.web.pages import COOKIE, HERE, PAGE_ERRORS, web_session
from slamreplay.api.web.pages import error_response as _error
from slamreplay.api.web.pages import page_lists as _lists
from slamreplay.api.web.pages import page_response as _page
from slamreplay.api.web.people_web import page as people_page
from slamreplay.api.web.runs_web import router as runs_router  # the runs table at / and /runs
from slamreplay.replay.errors import ReplayError

JobPath = Annotated[str, PathParam(pattern=JOB_ID)]


async def login_required(request: Request, exc: Exception) -> Response:
    if request.method == "GET" and not request.url.path.endswith(".rrd"):
        return RedirectResponse("/login?" + urlencode({"next": request.url.path + (
            f"?{request.url.query}" if request.url.query else "")}), 303)
    return JSONResponse({"detail": "sign in at /login first"}, 401)


async def page_forbidden(request: Request, exc: Exception) -> Response:
    """The 403 page: who is signed in, what they may not do and who can change it."""
    message = str(exc)
    if request.url.path.endswith(".rrd") or request.url.path.startswith("/ui/part/"):
        return JSONResponse({"detail": message}, 403)
    return await run_in_threadpool(_page, request, "error.html", 403, message=message, status=403,
                                   me=getattr(exc, "principal", None))


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


page = APIRouter(dependencies=[Depends(web_session)], include_in_schema=False)
public = APIRouter(include_in_schema=False)


def _safe_next(raw: Any) -> str:
    nxt = str(raw or "/")
    return nxt if nxt.startswith("/") and not nxt.startswith("//") and "\\" not in nxt else "/"


@public.get("/login")
def login_form(request: Request, next: str = "/") -> HTMLResponse:
    return _page(request, "login.html", next=_safe_next(next), wrong=False)


@public.post("/login")
async def login(request: Request, settings: SettingsDep) -> Response:
    """Sign in: a person's token opens a session (its id in an HttpOnly cookie, only its hash stored); the shared
    token sets the cookie derived from it; an open server needs nothing."""
    form = await request.form()
    token, nxt = str(form.get("token", "")).strip(), _safe_next(form.get("next"))
    mode = await run_in_threadpool(server_mode, request)
    resp = RedirectResponse(nxt, 303)
    secure = request.url.scheme == "https"
    store = request.app.state.jobs.store
    if mode != "open" and (wait := await run_in_threadpool(sign_in_wait_s, request)) > 0:
        return _page(request, "login.html", 429, next=nxt, wait_min=math.ceil(wait / 60))
    if mode == "people":
        user = await run_in_threadpool(store.user_of_token, token)
        if user is None:
            await run_in_threadpool(store.add_audit, "(unknown)", client_address(request), "sign-in-failed", None,
                                    "a token that is unknown, replaced or disabled")
            return _page(request, "login.html", 401, next=nxt, wrong=True)
        if (old := request.cookies.get(COOKIE)) is not None:  # signing in over a session ends that one
            await run_in_threadpool(store.close_session, old)
        session = await run_in_threadpool(store.open_session, user.name, client_address(request))
        resp.set_cookie(COOKIE, session, max_age=int(SESSION_TTL_S), httponly=True, samesite="lax", secure=secure,
                        path="/")
        await run_in_threadpool(store.add_audit, user.name, client_address(request), "sign-in", user.name, user.role)
    elif mode == "token":
        if not hmac.compare_digest(token.encode(), settings.token.encode()):  # type: ignore[union-attr]
            await run_in_threadpool(store.add_audit, "(unknown)", client_address(request), "sign-in-failed", None,
                                    "not the shared token")
            return _page(request, "login.html", 401, next=nxt, wrong=True)
        resp.set_cookie(COOKIE, session_value(settings.token), httponly=True,  # type: ignore[arg-type]
                        samesite="strict", secure=secure, path="/")
    return resp


@public.get("/favicon.ico")
def favicon() -> FileResponse:
    """The page's icon (an SVG; browsers that ask for /favicon.ico take it too)."""
    return FileResponse(HERE / "static" / "favicon.svg", media_type="image/svg+xml",
                        headers={"Cache-Control": "max-age=86400"})


@public.get("/logout")
def logout_page(request: Request) -> Response:
    """With a person's session: a page with the sign-out button (a form with its CSRF token, so no other site can
    sign anyone out); else the cookie is dropped at once, as before there were people."""
    me = page_principal(request)
    if me is not None and me.via == "session":
        return _page(request, "login.html", signout=True, me=me, next="/")
    resp = RedirectResponse("/login", 303)
    resp.delete_cookie(COOKIE, path="/")
    return resp


@public.post("/logout")
async def logout(request: Request) -> Response:
    """Sign out: the session ends on the server (its row is deleted) and the cookie is dropped."""
    me = await run_in_threadpool(page_principal, request)
    if me is not None and me.via == "session" and me.cookie is not None:
        form = await request.form()
        check_csrf(me, form.get(CSRF_FIELD))
        store = request.app.state.jobs.store
        await run_in_threadpool(store.close_session, me.cookie)
        await run_in_threadpool(store.add_audit, me.name, client_address(request), "sign-out", me.name, None)
    resp = RedirectResponse("/login", 303)
    resp.delete_cookie(COOKIE, path="/")
    return resp


@page.get("/ui/part/lists")
def part_lists(request: Request, part: Literal["recordings", "jobs", "suites"]) -> HTMLResponse:
    return _page(request, "_lists.html", **_lists(request), part=part)


@page.post("/ui/recordings")
async def upload_form(request: Request, recordings: RecordingsDep) -> Response:
    content_type = request.headers.get("content-type", "")
    if not is_form(content_type):
        return _error(request, ApiError("send the upload form (multipart/form-data with a field `file`)"))
    fields: dict[str, str] = {}
    try:
        name, chunks = await form_file(request.stream(), content_type, recordings.settings.max_upload_bytes, fields)
        check_csrf(request.state.principal, fields.get(CSRF_FIELD))  # sent before the file: checked before storing
        stored = await recordings.upload(chunks, name, None, False)
    except PAGE_ERRORS as err:
        return _error(request, err)
    await run_in_threadpool(record, request, "upload", stored.recording.id,
                            f"{stored.recording.filename} ({'new' if stored.created else 'already stored'})")
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
        topic_map = parse_topic_map(str(form.get("topic_map", "")))
        labels = Labels.parse(str(form.get("name", "")), str(form.get("tags", "")), str(form.get("note", "")))
        job = await run_in_threadpool(jobs.submit, str(form.get("recording_id", "")), str(form.get("pipeline", "")),
                                      config, seed, topic_map, None, who(request), labels)
    except ValueError as err:
        return _error(request, ReplayError(f"bad job form: {err}"))
    except PAGE_ERRORS as err:
        return _error(request, err)
    await run_in_threadpool(record, request, "submit", job.id, submitted_text(job))
    return RedirectResponse(f"/ui/jobs/{job.id}", 303)


@page.post("/ui/suites")
async def suite_form(request: Request, suites: SuitesDep) -> Response:
    form = await request.form()
    try:
        row = await run_in_threadpool(suites.submit, str(form.get("suite", "")), "toml", None, who(request))
    except PAGE_ERRORS as err:
        return _error(request, err)
    await run_in_threadpool(record_suite, request, suites, row)
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


Key = Annotated[str, PathParam(pattern=r"^[0-9a-f]{32}$")]


def _check_key(request: Request, key: str, rrd_path: str) -> None:
    secret = link_secret(request)
    if secret is not None and not hmac.compare_digest(key, rrd_key(secret, rrd_path)):
        raise UnauthorizedError("wrong key in the .rrd URL: open the run from the web page")


@page.get("/ui/jobs/{job_id}/run.rrd")
def job_rrd(job_id: JobPath, jobs: JobsDep) -> FileResponse:
    return FileResponse(jobs.artifact(job_id, "run.rrd"), media_type="application/octet-stream")


@public.get("/ui/shared/{key}/jobs/{job_id}/run.rrd")
def shared_job_rrd(request: Request, key: Key, job_id: JobPath, jobs: JobsDep) -> FileResponse:
    _check_key(request, key, f"/jobs/{job_id}/run.rrd")
    return FileResponse(jobs.artifact(job_id, "run.rrd"), media_type="application/octet-stream")


@public.get("/ui/shared/{key}/jobs/{job_id}/live.rrd")
def shared_live_rrd(request: Request, key: Key, job_id: JobPath, jobs: JobsDep) -> StreamingResponse:
    """The job's .rrd as the run writes it, until it ends (the viewer follows it live; api.live_view)."""
    from slamreplay.api.service.store import ACTIVE
    from slamreplay.api.web.live_view import follow_rrd
    from slamreplay.replay.engine.views import following_layout_rrd

    _check_key(request, key, f"/jobs/{job_id}/live.rrd")
    job = jobs.get(job_id)
    # a running job's viewer follows the newest step until the run's own layout arrives at its end
    prefix = following_layout_rrd(job.pipeline, job.id) if job.status in ACTIVE else b""
    return StreamingResponse(follow_rrd(jobs.run_dir(job_id), lambda: jobs.get(job_id).status in ACTIVE,
                                        prefix=prefix),
                             media_type="application/octet-stream", headers={"Cache-Control": "no-store"})


@public.get("/ui/shared/{key}/diff/{a}-{b}.rrd")
def shared_diff_rrd(request: Request, key: Key, a: JobPath, b: JobPath, jobs: JobsDep) -> FileResponse:
    """One .rrd with job A under runs/A and job B under runs/B (made on the first request)."""
    _check_key(request, key, f"/diff/{a}-{b}.rrd")
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
    from slamreplay.api.web.viewer_assets import FILES, ViewerAssetsError, viewer_dir

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
    """The web page, its static files and the viewer, on the service ``app`` (``slamreplay.api.app``)."""
    from fastapi.staticfiles import StaticFiles

    app.add_exception_handler(LoginRequiredError, login_required)
    app.add_exception_handler(PageForbiddenError, page_forbidden)
    app.include_router(history_page)  # /ui/history/{name} (api/web/history_web.py)
    app.include_router(public)
    app.include_router(runs_router)  # the runs table at / and /runs (api/web/runs_web.py)
    app.include_router(job_actions)  # rename, tag, cancel, delete a job (api/web/job_actions.py)
    app.include_router(install_job_files([web_session]))  # a run's files, for its page
    app.include_router(compare_router)  # /ui/compare: any runs, or suites paired (api/web/compare_web.py)
    app.include_router(page)
    app.include_router(audit_page)  # /ui/audit: the trail, for admins (api/web/audit_web.py)
    app.include_router(people_page)  # /ui/people: an admin's page of people (api/web/people_web.py)
    app.mount("/static", StaticFiles(directory=HERE / "static"), name="static")
