"""A job's actions on the page: rename, tag and annotate it, cancel it, delete it. Plain form POSTs behind a
confirmation page, so they work without JavaScript; each goes back to the page it came from (``next``, a path on
this server only) and is written to the audit trail."""

from __future__ import annotations

import shutil
from typing import Annotated, Any

from fastapi import APIRouter, Depends, Request
from fastapi import Path as PathParam
from fastapi.responses import HTMLResponse, RedirectResponse, Response
from starlette.concurrency import run_in_threadpool

from slamreplay.api.service.audit import label_job, submitted_text
from slamreplay.api.service.auth import client_address, record
from slamreplay.api.service.deps import JobsDep
from slamreplay.api.service.errors import ConflictError
from slamreplay.api.service.jobs import JobService
from slamreplay.api.service.models import JOB_ID
from slamreplay.api.service.store import ACTIVE
from slamreplay.api.service.store_runs import Labels
from slamreplay.api.web.pages import PAGE_ERRORS, web_session
from slamreplay.api.web.pages import error_response as _error
from slamreplay.api.web.pages import page_response as _page
from slamreplay.replay.errors import ReplayError

JobPath = Annotated[str, PathParam(pattern=JOB_ID)]
router = APIRouter(dependencies=[Depends(web_session)], include_in_schema=False)


def _next(raw: Any) -> str:
    """Where to go back to: a path on this server only."""
    nxt = str(raw or "/runs")
    return nxt if nxt.startswith("/") and not nxt.startswith("//") and "\\" not in nxt else "/runs"


@router.get("/ui/jobs/{job_id}/edit")
def edit_form(request: Request, job_id: JobPath, jobs: JobsDep, next: str = "/runs") -> HTMLResponse:
    """The form that names, tags and annotates a job."""
    try:
        job = jobs.get(job_id)
    except PAGE_ERRORS as err:
        return _error(request, err)
    return _page(request, "job_action.html", action="edit", job=job, next=_next(next))


@router.post("/ui/jobs/{job_id}/edit")
async def edit_job(request: Request, job_id: JobPath, jobs: JobsDep) -> Response:
    """Rename, tag and annotate a job (empty fields clear them)."""
    form = await request.form()
    try:
        labels = Labels.parse(str(form.get("name", "")), str(form.get("tags", "")), str(form.get("note", "")))
    except ValueError as err:
        return _error(request, ReplayError(f"cannot save job {job_id[:8]}: {err}"))
    if await run_in_threadpool(label_job, request, jobs.store, job_id, labels) is None:
        return _error(request, jobs.missing(job_id))
    return RedirectResponse(_next(form.get("next")), 303)


def _confirm(request: Request, job_id: str, action: str, jobs: JobService, nxt: str) -> HTMLResponse:
    """Are you sure? (cancel a queued or running job, delete an ended one and its files)."""
    try:
        job = jobs.get(job_id)
    except PAGE_ERRORS as err:
        return _error(request, err)
    return _page(request, "job_action.html", action=action, job=job, next=_next(nxt),
                 allowed=(job.status in ACTIVE) == (action == "cancel"), suite_cells=jobs.store.suite_uses(job_id))


@router.get("/ui/jobs/{job_id}/cancel")
def confirm_cancel(request: Request, job_id: JobPath, jobs: JobsDep, next: str = "/runs") -> HTMLResponse:
    """Ask before cancelling a job."""
    return _confirm(request, job_id, "cancel", jobs, next)


@router.get("/ui/jobs/{job_id}/delete")
def confirm_delete(request: Request, job_id: JobPath, jobs: JobsDep, next: str = "/runs") -> HTMLResponse:
    """Ask before deleting a job."""
    return _confirm(request, job_id, "delete", jobs, next)


@router.post("/ui/jobs/{job_id}/cancel")
async def cancel_job(request: Request, job_id: JobPath, jobs: JobsDep) -> Response:
    """Cancel a queued or running job (409 when it has ended), then go back."""
    form = await request.form()
    try:
        job = await run_in_threadpool(jobs.cancel, job_id)
    except PAGE_ERRORS as err:
        return _error(request, err)
    await run_in_threadpool(record, request, "cancel", job_id, submitted_text(job))
    return RedirectResponse(_next(form.get("next")), 303)


@router.post("/ui/jobs/{job_id}/delete")
async def delete_job(request: Request, job_id: JobPath, jobs: JobsDep) -> Response:
    """Forget an ended job and delete its run directory (and comparison files made from it)."""
    form = await request.form()
    me, address = request.state.principal, client_address(request)
    job = await run_in_threadpool(jobs.store.get_job, job_id)
    outcome = await run_in_threadpool(jobs.store.delete_job, job_id, me.name, address)
    if outcome == "missing" or job is None:
        return _error(request, jobs.missing(job_id))
    if outcome == "active":
        return _error(request, ConflictError(f"job {job_id} is queued or running: cancel it before deleting it"))
    shutil.rmtree(jobs.run_dir(job_id), ignore_errors=True)
    for pair in (jobs.settings.runs_dir / "diffs").glob(f"*{job_id}*.rrd"):
        pair.unlink(missing_ok=True)
    shutil.rmtree(jobs.settings.runs_dir / "diffs" / ".labels" / job_id, ignore_errors=True)  # its named link
    await run_in_threadpool(record, request, "delete", job_id, submitted_text(job) + (f"; {job.name}" if job.name
                                                                                      else ""))
    return RedirectResponse(_next(form.get("next")), 303)
