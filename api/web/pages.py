"""What every page of the web page shares: the templates, the session check, rendering and error pages.

Its own module so that the page's route modules (api/web/web.py, api/web/runs_web.py, api/web/job_web.py) import it
and not each other.
"""

from __future__ import annotations

import math
import time
from pathlib import Path
from typing import Any

from fastapi import Request
from fastapi.responses import HTMLResponse
from fastapi.templating import Jinja2Templates

from slamreplay.api.service.auth import (
    COOKIE as COOKIE,  # the page's names for these (api/service/auth.py)
)
from slamreplay.api.service.auth import LoginRequiredError as LoginRequiredError
from slamreplay.api.service.auth import PageForbiddenError as PageForbiddenError
from slamreplay.api.service.auth import Principal, page_check, principal_of, server_mode
from slamreplay.api.service.auth import session_value as session_value
from slamreplay.api.service.deps import get_jobs
from slamreplay.api.service.errors import ApiError
from slamreplay.api.service.suites import ENDED, SuiteService
from slamreplay.recorder.errors import RecorderError
from slamreplay.replay.errors import ReplayError

HERE = Path(__file__).parent
templates = Jinja2Templates(directory=HERE / "templates")
PAGE_ERRORS = (ApiError, ReplayError, RecorderError)


async def web_session(request: Request) -> Principal:
    """Pages need a session (a person's, or the shared token's cookie) unless the server is open; the route's
    role; and, for a form posted with a session cookie, its CSRF token (``slamreplay.api.service.auth``)."""
    return await page_check(request)


def _num(v: Any) -> str:
    if isinstance(v, float):
        return "-" if not math.isfinite(v) else f"{v:.6g}"
    return str(v)


templates.env.filters["num"] = _num
templates.env.filters["short"] = lambda s: str(s)[:8]
templates.env.filters["utc"] = lambda t: time.strftime("%Y-%m-%d %H:%M", time.gmtime(t)) if t is not None else ""


def people_ctx(request: Request) -> dict[str, Any]:
    """What every page's header and forms need: the mode, who is signed in (``me``), what they may do and the
    CSRF token their forms carry."""
    mode = server_mode(request)
    me = principal_of(request)
    return {"mode": mode, "me": me, "guarded": mode != "open", "csrf": me.csrf if me is not None else None,
            "can_run": me is not None and me.can("runner"), "can_admin": me is not None and me.can("admin")}


def page_response(request: Request, name: str, status_code: int = 200, **ctx: Any) -> HTMLResponse:
    """Template ``name`` rendered with ``ctx`` and `people_ctx` (the nav bar, which buttons to show, CSRF)."""
    for key, value in people_ctx(request).items():
        ctx.setdefault(key, value)
    return templates.TemplateResponse(request, name, ctx, status_code=status_code)


def error_response(request: Request, exc: Exception) -> HTMLResponse:
    """The error page: one line saying what is wrong, with the error's status (422 for bad input)."""
    status = exc.status if isinstance(exc, ApiError) else 422
    return page_response(request, "error.html", status, message=str(exc), status=status)


JOBS_SHOWN = 12  # the newest; a suite's page lists its own, GET /jobs all of them


def page_lists(request: Request) -> dict[str, Any]:
    """The recordings, newest jobs and suites the main page lists below the runs table."""
    jobs = get_jobs(request)
    suites: SuiteService = request.app.state.suites
    recs = jobs.store.list_recordings()
    job_rows = jobs.store.list_jobs(limit=JOBS_SHOWN)
    suite_rows = [(s, suites.progress(suites.get(s.id)[2])) for s in suites.recent(50)]
    return {"recordings": recs, "jobs": job_rows, "suites": suite_rows, "rec_names": {r.id: r.filename for r in recs},
            "jobs_total": sum(jobs.store.count_by_status().values()),
            "jobs_active": any(j.status not in ENDED for j in job_rows),
            "suites_active": any(p["ended"] < p["cells"] for _, p in suite_rows)}


def suite_key(filename: str) -> str:
    """A TOML key made of a recording's file name (for the example suite)."""
    stem = "".join(ch if ch.isalnum() or ch in "_-" else "_" for ch in Path(filename).stem)[:40]
    return stem if stem and stem[0].isalnum() else f"r{stem}"


def duration_text(seconds: float | None) -> str:
    """``12.3 s``, ``4 min 05 s``, ``2 h 03 min``; empty for None."""
    if seconds is None:
        return ""
    s = max(seconds, 0.0)
    if s < 60:
        return f"{s:.1f} s"
    if s < 3600:
        return f"{int(s // 60)} min {int(s % 60):02d} s"
    return f"{int(s // 3600)} h {int(s % 3600 // 60):02d} min"
