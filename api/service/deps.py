"""What the service's routes share: the settings, job and recording services, the bearer token check (who asks,
and whether their role may: ``slamreplay.api.service.auth``), the documented error responses, and the keyed links the
Rerun web viewer opens a run's ``.rrd`` through.

Its own module so that the routes (api/service/app.py, suites_routes.py, api/web/web.py) import it and not
each other.
"""

from __future__ import annotations

import hashlib
import hmac
from typing import Annotated, Any
from urllib.parse import quote

from fastapi import Depends, Request
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer

from slamreplay.api.service.auth import Principal, api_principal
from slamreplay.api.service.jobs import JobService
from slamreplay.api.service.models import ErrorOut
from slamreplay.api.service.recordings import RecordingService
from slamreplay.api.service.settings import Settings, get_settings

SettingsDep = Annotated[Settings, Depends(get_settings)]
# Errors are JSON on every route, file downloads included (FastAPI would document them with the route's media type).
ERRORS: dict[int | str, dict[str, Any]] = {
    code: {"model": ErrorOut, "content": {"application/json": {"schema": {"$ref": "#/components/schemas/ErrorOut"}}}}
    for code in (400, 401, 403, 404, 409, 413, 415, 422, 507)}
_bearer = HTTPBearer(auto_error=False, description="your own token (`slamreplay users add`) on a server with people, "
                                                   "else SLAMREPLAY_TOKEN when the server has one")


def get_jobs(request: Request) -> JobService:
    jobs: JobService = request.app.state.jobs
    return jobs


def get_recordings(request: Request) -> RecordingService:
    recordings: RecordingService = request.app.state.recordings
    return recordings


JobsDep = Annotated[JobService, Depends(get_jobs)]
RecordingsDep = Annotated[RecordingService, Depends(get_recordings)]


def require_token(request: Request,
                  credentials: Annotated[HTTPAuthorizationCredentials | None, Depends(_bearer)]) -> Principal:
    """401 unless the request carries a good bearer token (a person's, or the shared one; none on an open server),
    403 when that person's role may not use the route (``slamreplay.api.service.auth``)."""
    return api_principal(request)


PrincipalDep = Annotated[Principal, Depends(require_token)]


def rrd_key(token: str | None, rrd_path: str) -> str:
    """The key in a viewer's .rrd URL: a MAC of the path under the token (any key does without a token)."""
    return hmac.new((token or "").encode(), rrd_path.encode(), hashlib.sha256).hexdigest()[:32]


def viewer_href(base_url: str, token: str | None, rrd_path: str) -> str:
    """The Rerun web viewer (served here) opening the .rrd at ``/ui/shared/KEY{rrd_path}`` of this server.

    The viewer fetches the file itself, without the page's cookie, so the URL carries its own
    key: it opens that one file and nothing else (a link to share, like the token's holder can)."""
    url = f"{base_url.rstrip('/')}/ui/shared/{rrd_key(token, rrd_path)}{rrd_path}"
    return "/viewer/?url=" + quote(url, safe="")
