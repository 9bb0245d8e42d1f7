"""What every page of the web page shares: the templates, the session check, rendering and error pages.

Its own module so that the page's route modules (api/web.py, api/runs_web.py, api/job_web.py) import it
and not each other.
"""

from __future__ import annotations

import hashlib
import hmac
import math
from pathlib import Path
from typing import Any

from fastapi import Request
from fastapi.responses import HTMLResponse
from fastapi.templating import Jinja2Templates

from slamreplay.api.deps import SettingsDep, get_jobs
from slamreplay.api.errors import ApiError
from slamreplay.api.settings import Settings
from slamreplay.api.suites import ENDED, SuiteService
from slamreplay.recorder.errors import RecorderError
from slamreplay.replay.errors import ReplayError

HERE = Path(__file__).parent
COOKIE = "slamreplay_session"
templates = Jinja2Templates(directory=HERE / "templates")
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


def _num(v: Any) -> str:
    if isinstance(v, float):
        return "-" if not math.isfinite(v) else f"{v:.6g}"
    return str(v)


templates.env.filters["num"] = _num
templates.env.filters["short"] = lambda s: str(s)[:8]


def page_response(request: Request, name: str, status_code: int = 200, **ctx: Any) -> HTMLResponse:
    """Template ``name`` rendered with ``ctx`` (and whether the server asks for a token, for the nav bar)."""
    settings: Settings = request.app.state.settings
    ctx.setdefault("guarded", settings.token is not None)
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
