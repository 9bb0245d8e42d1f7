"""The HTTP service: ``create_service(settings)`` builds a FastAPI app over the job store and an executor.

Routes only validate and delegate (to ``RecordingService``, ``JobService`` and ``replay``);
replays run in worker processes, never in the event loop. Ids in paths and queries must be
hex (sha256 for recordings, 32 digits for jobs), so user input never names a file. When a
token is set, every route but ``/healthz`` needs ``Authorization: Bearer <token>`` (the
interactive ``/docs`` and ``/redoc`` pages, served from installed files, are then off, as a browser
cannot send the token from them). With or without a token, only the host names the server
answers to are served and other sites cannot make changes (``slamreplay.api.service.siteguard``); the
app starts only while it holds its data directory's lock (``slamreplay.api.service.datalock``).
"""

from __future__ import annotations

import shutil
import sqlite3
import uuid
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from typing import Annotated

from fastapi import APIRouter, Depends, FastAPI, Path, Query, Request, Response
from fastapi.middleware import Middleware
from fastapi.responses import FileResponse, JSONResponse, PlainTextResponse
from starlette.concurrency import run_in_threadpool

from slamreplay.api.service.audit import label_job, submitted_text
from slamreplay.api.service.audit import router as audit_router
from slamreplay.api.service.auth import client_address, record, who
from slamreplay.api.service.datalock import DataDirLock
from slamreplay.api.service.deps import ERRORS, JobsDep, RecordingsDep, require_token
from slamreplay.api.service.docs_pages import install_docs
from slamreplay.api.service.errors import ApiError, disk_full_error, is_disk_full
from slamreplay.api.service.executor import Executor, LocalExecutor
from slamreplay.api.service.history_routes import router as history_router
from slamreplay.api.service.idprefix import IdPrefixes, PageError
from slamreplay.api.service.jobs import JobService
from slamreplay.api.service.live_routes import install_live_routes
from slamreplay.api.service.models import (
    JOB_ID,
    SHA256,
    DiffOut,
    HealthOut,
    JobOut,
    JobSpec,
    JobStatusName,
    LabelsPatch,
    RecordingOut,
)
from slamreplay.api.service.monitoring import CONTENT_TYPE, prometheus_text
from slamreplay.api.service.multipart import FILE_FIELD, form_file, is_form
from slamreplay.api.service.record_routes import install_record_routes
from slamreplay.api.service.recordings import RecordingService
from slamreplay.api.service.settings import Settings
from slamreplay.api.service.siteguard import SiteGuard
from slamreplay.api.service.store import JobRow, Store
from slamreplay.api.service.store_runs import MAX_NAME, MAX_NOTE, MAX_TAGS, Labels
from slamreplay.api.service.suites import SuiteService
from slamreplay.api.service.suites_routes import router as suites_router
from slamreplay.api.service.timeouts import BodyTimeout
from slamreplay.recorder.errors import RecorderError
from slamreplay.recorder.version import version
from slamreplay.replay.errors import ReplayError
from slamreplay.replay.runs.diff import diff_runs, parse_tolerances

RecordingId = Annotated[str, Path(pattern=SHA256, description="sha256 of the recording")]
JobId = Annotated[str, Path(pattern=JOB_ID, description="job id (32 hex digits)")]
JobQuery = Annotated[str, Query(pattern=JOB_ID, description="job id (32 hex digits)")]


async def handle_error(request: Request, exc: Exception) -> JSONResponse:
    """The one error handler: service errors carry their status; a full disk is 507 (the service keeps serving);
    ReplayError/RecorderError are bad input (422); any other OSError or SQLite error stays an internal error."""
    if not isinstance(exc, ApiError) and is_disk_full(exc):
        exc = disk_full_error(f"answering {request.method} {request.url.path}")
    elif isinstance(exc, (OSError, sqlite3.Error)):
        raise exc
    if isinstance(exc, ApiError):
        status, body = exc.status, {"detail": exc.detail, **exc.extra}
    else:
        status, body = 422, {"detail": str(exc)}
    return JSONResponse(body, status, headers={"WWW-Authenticate": "Bearer"} if status == 401 else None)


public = APIRouter()
router = APIRouter(dependencies=[Depends(require_token)], responses=ERRORS)


@public.get("/healthz", tags=["service"])
def healthz() -> HealthOut:
    return HealthOut(status="ok", version=version())


@router.get("/metrics", tags=["service"], response_class=PlainTextResponse)
def prometheus_metrics(jobs: JobsDep) -> PlainTextResponse:
    return PlainTextResponse(prometheus_text(jobs.store, jobs.executor.slots), media_type=CONTENT_TYPE)


# -- recordings ------------------------------------------------------------------------------

UPLOAD_BODY = {"requestBody": {
    "required": True,
    "description": "the .mcap file: the raw request body (curl --data-binary @run.mcap), or the field `file` of a "
                   "form (curl -F file=@run.mcap)",
    "content": {"application/octet-stream": {"schema": {"type": "string", "format": "binary"}},
                "multipart/form-data": {"schema": {"type": "object", "required": [FILE_FIELD],
                                                   "properties": {FILE_FIELD: {"type": "string",
                                                                               "format": "binary"}}}}}}}


@router.post("/recordings", status_code=201, tags=["recordings"], openapi_extra=UPLOAD_BODY,
             responses={201: {"description": "stored as a new recording"},
                        200: {"model": RecordingOut, "description": "the same file (same sha256) was stored before: "
                                                                   "the same body, with the stored recording's id; "
                                                                   "nothing new is stored"}})
async def upload_recording(request: Request, response: Response, recordings: RecordingsDep,
                           filename: Annotated[str | None, Query(max_length=255, description="a label")] = None,
                           recover: Annotated[bool, Query(description="salvage a damaged file at once")] = False,
                           ) -> RecordingOut:
    """Upload a recording, raw body or form field `file` (streamed to disk); 201 new, 200 when already stored."""
    content_type = request.headers.get("content-type", "")
    if is_form(content_type):  # the form's own bytes make Content-Length larger than the file: not a size
        name, chunks = await form_file(request.stream(), content_type, recordings.settings.max_upload_bytes)
        stored = await recordings.upload(chunks, filename or name, None, recover)
    else:
        length = request.headers.get("content-length")
        declared = int(length) if length is not None and length.isdigit() else None
        stored = await recordings.upload(request.stream(), filename, declared, recover)
    await run_in_threadpool(record, request, "upload", stored.recording.id,
                            f"{stored.recording.filename} ({'new' if stored.created else 'already stored'})")
    response.status_code = 201 if stored.created else 200
    return RecordingOut.of(stored.recording, stored.report, stored.recovered_from)


@router.post("/recordings/{recording_id}/recover", status_code=201, tags=["recordings"])
def recover_recording(request: Request, recording_id: RecordingId, response: Response,
                      recordings: RecordingsDep) -> RecordingOut:
    """Salvage the readable messages of a damaged upload into a new recording."""
    stored = recordings.recover(recording_id)
    record(request, "recover", stored.recording.id, f"from the damaged upload {recording_id[:8]}")
    response.status_code = 201 if stored.created else 200
    return RecordingOut.of(stored.recording, stored.report, stored.recovered_from)


@router.get("/recordings", tags=["recordings"])
def list_recordings(recordings: RecordingsDep) -> list[RecordingOut]:
    return [RecordingOut.of(r) for r in recordings.store.list_recordings()]


@router.get("/recordings/{recording_id}", tags=["recordings"])
def get_recording(recording_id: RecordingId, recordings: RecordingsDep) -> RecordingOut:
    return RecordingOut.of(recordings.get(recording_id))


@router.get("/recordings/{recording_id}/download", tags=["recordings"], response_class=FileResponse)
def download_recording(recording_id: RecordingId, recordings: RecordingsDep) -> FileResponse:
    rec, path = recordings.file(recording_id)
    return FileResponse(path, media_type="application/octet-stream", filename=rec.filename)


@router.delete("/recordings/{recording_id}", status_code=204, tags=["recordings"])
def delete_recording(request: Request, recording_id: RecordingId, recordings: RecordingsDep) -> Response:
    """Delete a recording (admins); 409 while a queued or running job uses it."""
    name = recordings.get(recording_id).filename
    recordings.delete(recording_id)
    record(request, "delete-recording", recording_id, name)
    return Response(status_code=204)


# -- jobs ---------------------------------------------------------------------------------------


@router.post("/jobs", status_code=202, tags=["jobs"])
def submit_job(request: Request, spec: JobSpec, jobs: JobsDep) -> JobOut:
    """Queue a job (runners), with its name, tags and note if given; 422 naming an unknown pipeline or config key,
    404 for an unknown recording."""
    job = jobs.submit(spec.recording_id, spec.pipeline, spec.config, spec.seed, spec.topic_map,
                      made_by=who(request), labels=spec.labels())
    record(request, "submit", job.id, submitted_text(job))
    return JobOut.of(job)


@router.get("/jobs", tags=["jobs"], responses={200: {"headers": {
    "X-Total-Count": {"description": "how many jobs match the filters in all", "schema": {"type": "integer"}},
    "Link": {"description": 'the next page: <URL>; rel="next" (absent on the last page)',
             "schema": {"type": "string"}}}}})
def list_jobs(request: Request, response: Response, jobs: JobsDep,
              recording: Annotated[str | None, Query(max_length=200, description=(
                  "a recording's id, its first 4+ digits, or its file name"))] = None,
              pipeline: Annotated[str | None, Query(max_length=100)] = None, status: JobStatusName | None = None,
              tag: Annotated[str | None, Query(max_length=40)] = None,
              q: Annotated[str | None, Query(max_length=500, description=(
                  "words found anywhere in a run: id, name, note, tags, pipeline, recording, error, config"))] = None,
              where: Annotated[str | None, Query(max_length=500, description=(
                  "a metric condition, as the runs table's: e.g. `ape_rmse_m < 0.1 and landmark_nees_mean <= 3`"))]
              = None,
              limit: Annotated[int, Query(ge=1, le=1000)] = 100,
              cursor: Annotated[str | None, Query(pattern=r"^[0-9]{1,19}$", description=(
                  "where the next page starts: the cursor of the previous page's Link header"))] = None,
              ) -> list[JobOut]:
    """Jobs, newest first, filtered as the runs table filters (recording, pipeline, status, tag, words, metric
    condition), a page at a time: ``X-Total-Count`` says how many match, ``Link: <...>; rel="next"`` where the next
    page is (a cursor that stays valid while jobs are added or deleted)."""
    from slamreplay.api.service.runs_query import strict_view, where_sql

    view = strict_view({k: [v] for k, v in (("recording", recording), ("pipeline", pipeline), ("status", status),
                                            ("tag", tag), ("q", q), ("where", where)) if v})
    sql, args = where_sql(view)
    rows, total, nxt = jobs.store.jobs_page(sql, args, limit, None if cursor is None else int(cursor))
    response.headers["X-Total-Count"] = str(total)
    if nxt is not None:
        url = request.url.include_query_params(cursor=str(nxt))
        response.headers["Link"] = f'<{url.path}?{url.query}>; rel="next"'
    return [JobOut.of(j) for j in rows]


@router.patch("/jobs/{job_id}", tags=["jobs"])
def label_job_route(request: Request, job_id: JobId, patch: LabelsPatch, jobs: JobsDep) -> JobOut:
    """Name, tag and annotate a job (runners): the fields given replace the job's; null or "" clears one."""
    labels = patch.applied_to(jobs.get(job_id))
    job = label_job(request, jobs.store, job_id, labels)
    if job is None:
        raise jobs.missing(job_id)
    return JobOut.of(job)


@router.post("/runs", status_code=201, tags=["jobs"], openapi_extra={"requestBody": {
    "required": True, "description": "a tar of the run directory, gzipped or not (any content type)",
    "content": {"application/octet-stream": {"schema": {"type": "string", "format": "binary"}}}}},
    responses={201: {"description": "kept as a new job"},
               200: {"model": JobOut, "description": "this run (its manifest's run_id) was pushed before: its job"}})
async def push_run(request: Request, response: Response, jobs: JobsDep,
                   origin: Annotated[str | None, Query(max_length=200, description=(
                       "where the run was made, in your words: a host, a CI job's URL"))] = None,
                   name: Annotated[str | None, Query(max_length=MAX_NAME)] = None,
                   tags: Annotated[list[str] | None, Query(max_length=MAX_TAGS)] = None,
                   note: Annotated[str | None, Query(max_length=MAX_NOTE)] = None) -> JobOut:
    """Push a run made elsewhere (CI, a laptop's `suite run`, `evaluate`, an external program): a tar of its run
    directory (`tar -czf - -C RUN_DIR .`), checked (manifest, metrics, the artifacts' sha256, the recording held
    here) and listed beside the server's own runs, marked with where it came from (runners); `slamreplay push`."""
    from slamreplay.api.service import push

    try:
        labels = Labels.parse(name, [t for raw in tags or [] for t in raw.split(",")], note)
    except ValueError as err:
        raise ReplayError(str(err)) from None
    runs_dir, limit = jobs.settings.runs_dir, jobs.settings.max_upload_bytes
    stem = runs_dir / f".push-{uuid.uuid4().hex}"
    archive, folder = stem.with_suffix(".partial"), stem
    try:
        try:
            await push.spool(request.stream(), archive, limit)
        except OSError as err:
            if is_disk_full(err):
                raise disk_full_error("storing a pushed run") from err
            raise

        def accept() -> tuple[JobRow, bool]:
            push.unpack(archive, folder, limit)
            run = push.check_run(folder)
            return push.keep(jobs.store, runs_dir, run, who(request), client_address(request), origin, labels)

        job, new = await run_in_threadpool(accept)
    finally:
        archive.unlink(missing_ok=True)
        shutil.rmtree(folder, ignore_errors=True)
    if new:
        await run_in_threadpool(record, request, "push", job.id,
                                f"{submitted_text(job)}; made {'at ' + origin if origin else 'elsewhere'}")
    response.status_code = 201 if new else 200
    return JobOut.of(job, jobs.run_dir(job.id))


@router.get("/jobs/{job_id}", tags=["jobs"])
def get_job(job_id: JobId, jobs: JobsDep) -> JobOut:
    """Status, progress, and metrics and manifest once written."""
    return JobOut.of(jobs.get(job_id), jobs.run_dir(job_id))


@router.delete("/jobs/{job_id}", tags=["jobs"])
def cancel_job(request: Request, job_id: JobId, jobs: JobsDep) -> JobOut:
    """Cancel a queued or running job (runners); 409 when it has already ended."""
    job = jobs.cancel(job_id)
    record(request, "cancel", job_id, submitted_text(job))
    return JobOut.of(job)


@router.get("/jobs/{job_id}/rrd", tags=["jobs"], response_class=FileResponse)
def job_rrd(job_id: JobId, jobs: JobsDep) -> FileResponse:
    return FileResponse(jobs.artifact(job_id, "run.rrd"), media_type="application/octet-stream",
                        filename=f"{job_id}.rrd")


@router.get("/jobs/{job_id}/metrics", tags=["jobs"], response_class=FileResponse)
def job_metrics(job_id: JobId, jobs: JobsDep) -> FileResponse:
    return FileResponse(jobs.artifact(job_id, "metrics.json"), media_type="application/json")


@router.get("/jobs/{job_id}/manifest", tags=["jobs"], response_class=FileResponse)
def job_manifest(job_id: JobId, jobs: JobsDep) -> FileResponse:
    return FileResponse(jobs.artifact(job_id, "manifest.json"), media_type="application/json")


@router.get("/jobs/{job_id}/log", tags=["jobs"], response_class=FileResponse)
def job_log(job_id: JobId, jobs: JobsDep) -> FileResponse:
    return FileResponse(jobs.artifact(job_id, "log.txt"), media_type="text/plain; charset=utf-8")


# -- diff -----------------------------------------------------------------------------------------


@router.get("/diff", tags=["diff"])
def diff(a: JobQuery, b: JobQuery, jobs: JobsDep,
         tolerance: Annotated[list[str] | None, Query(description="NAME=VALUE or NAME=N%; * for all")] = None,
         ) -> DiffOut:
    """Job B against job A: what changed, metric deltas with verdicts, run.rrd content equality."""
    result = diff_runs(jobs.finished_run(a), jobs.finished_run(b), parse_tolerances(tolerance or []))
    return DiffOut(**(result.to_json() | {"a": a, "b": b}))


@router.get("/diff.rrd", tags=["diff"], response_class=FileResponse)
def diff_rrd(a: JobQuery, b: JobQuery, jobs: JobsDep) -> FileResponse:
    """One .rrd with job A under runs/A and job B under runs/B."""
    return FileResponse(jobs.comparison_rrd(a, b), media_type="application/octet-stream",
                        filename=f"diff-{a[:8]}-{b[:8]}.rrd")


# -- the app --------------------------------------------------------------------------------------


def make_executor(settings: Settings) -> Executor:
    """The executor named by the settings (``ray``: ImportError with the install command when Ray is missing)."""
    if settings.executor == "ray":
        from slamreplay.api.service.ray_executor import RayExecutor

        return RayExecutor(settings.workers, settings.job_limits, address=settings.ray_address)
    return LocalExecutor(settings.workers, settings.job_limits)


def create_service(settings: Settings | None = None, executor: Executor | None = None,
                   lock: DataDirLock | None = None, page_error: PageError | None = None) -> FastAPI:
    """The service over ``settings.data_dir``; the executor runs (and the scheduler starts) with the lifespan.
    The web page mounts itself on it (``slamreplay.api.app.create_app``); ``page_error`` draws an error of a
    page route (``/ui/...``) that the id-prefix middleware answers.

    ``lock``: the data directory's lock when the caller took it already (``slamreplay serve``); else the
    lifespan takes it, and fails with ``DataDirInUseError`` while another server holds the directory.
    """
    settings = settings or Settings.from_env()
    settings.make_dirs()
    store = Store(settings.db_path)
    jobs = JobService(settings, store, executor or make_executor(settings), lock)
    recordings = RecordingService(settings, store)

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        await run_in_threadpool(jobs.hold_data_dir)  # before the sweep: another server's uploads are not ours
        try:
            await run_in_threadpool(recordings.sweep)
            await run_in_threadpool(jobs.start)
        except BaseException:
            jobs.lock.release()
            raise
        try:
            yield
        finally:
            await run_in_threadpool(jobs.stop)

    docs = settings.token is None
    # /docs and /redoc are served from installed files, not FastAPI's CDN links (api/service/docs_pages.py)
    app = FastAPI(title="slamreplay", version=version(), lifespan=lifespan, docs_url=None,
                  redoc_url=None, openapi_url="/openapi.json" if docs else None,
                  description="Upload MCAP recordings, replay them through SLAM pipelines as jobs, "
                              "fetch metrics and Rerun recordings, and diff runs.")
    app.state.settings = settings
    app.state.jobs = jobs
    app.state.recordings = recordings
    app.state.suites = SuiteService(jobs)
    app.add_middleware(BodyTimeout, idle_s=settings.body_timeout_s, min_rate=settings.min_body_rate)  # 408 on stalls
    app.add_middleware(SiteGuard, hosts=settings.allowed_hosts)  # outermost: before any route or error handler
    for exc in (ApiError, ReplayError, RecorderError, OSError, sqlite3.Error):
        app.add_exception_handler(exc, handle_error)
    install_live_routes(app)  # /recordings/live, before /recordings/{id} would read "live" as an id
    app.include_router(public)
    app.include_router(router)
    install_record_routes(app)  # POST /recordings/record/NAME per importer the server may run
    app.include_router(suites_router)  # POST /suites, GET /suites/ID, GET /compare (api/service/suites_routes.py)
    app.include_router(history_router)  # GET /history/suites/{name} (api/service/history_routes.py)
    app.include_router(audit_router)  # GET /audit: the trail, for admins (api/service/audit.py)
    # Id prefixes become whole ids before routing; innermost of the middleware, so the site guard stays outermost.
    app.user_middleware.append(Middleware(IdPrefixes, page_error=page_error))
    if docs:
        install_docs(app)
    else:
        @app.get("/openapi.json", include_in_schema=False, dependencies=[Depends(require_token)])
        def openapi() -> JSONResponse:
            return JSONResponse(app.openapi())
    return app
