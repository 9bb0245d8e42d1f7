"""Ids as the page shows them: any unambiguous prefix (at least 4 hex digits; the page shows 8) of a recording,
job or suite id stands for the whole id, in every route that takes one, API and page alike.

`IdPrefixes` is an ASGI middleware that rewrites a request's path and query before routing: a
prefix naming one id becomes that id, so the routes keep their strict patterns (an id never
names a file the service did not make). A prefix naming several ids is a 409 listing them; an
id that is not hex, or too long, or names nothing, is a 404 with the id, one line, instead of
the routes' raw pattern error. Those answers name ids, so they are given only to a request
that carries the server's token (bearer header or the page's session cookie); any other
request passes through unchanged and gets the routes' usual 401.
"""

from __future__ import annotations

import re
from collections.abc import Awaitable, Callable, MutableMapping
from typing import Any
from urllib.parse import parse_qsl, urlencode

from fastapi.responses import JSONResponse, Response
from starlette.concurrency import run_in_threadpool
from starlette.requests import Request

from slamreplay.api.service.errors import ApiError
from slamreplay.api.service.ids import is_whole, resolve_id
from slamreplay.api.service.store import Store

Scope = MutableMapping[str, Any]
ASGIApp = Callable[[Scope, Any, Any], Awaitable[None]]
PageError = Callable[[Request, ApiError], Response]
# Path segments that hold an id: (pattern with the group "id", kinds it may be). Words that are routes of their
# own (/recordings/importers, /recordings/record/NAME, /recordings/live) are not ids.
PATHS = (
    (re.compile(r"^/recordings/(?P<id>(?!importers$|record$|live$)[^/]+)(?:/(?:recover|download))?$"),
     ("recording",)),
    (re.compile(r"^/jobs/(?P<id>[^/]+)(?:/(?:rrd|metrics|manifest|log))?$"), ("job",)),
    (re.compile(r"^/suites/(?P<id>[^/]+)$"), ("suite",)),
    (re.compile(r"^/ui/(?:part/)?jobs/(?P<id>[^/]+)(?:/.*)?$"), ("job",)),
    (re.compile(r"^/ui/(?:part/)?suites/(?P<id>[^/]+)$"), ("suite",)),
)
EITHER = ("suite", "job")
# Query parameters that hold ids, per path; ``runs`` holds a comma-separated list.
QUERIES: dict[str, dict[str, tuple[str, ...]]] = {
    "/jobs": {"recording": ("recording",)},
    "/diff": {"a": ("job",), "b": ("job",)},
    "/diff.rrd": {"a": ("job",), "b": ("job",)},
    "/compare": {"a": EITHER, "b": EITHER, "runs": ("job",)},
    "/ui/compare": {"a": EITHER, "b": EITHER, "runs": ("job",)},
    "/ui/runs/compare": {"sel": ("job",)},
}


def _authorized(scope: Scope) -> bool:
    """Whether the request carries a good token (bearer, or the page's session cookie), or none is needed; a
    person's bearer token costs a slow hash: call it from a worker thread."""
    from slamreplay.api.service.auth import bearer_principal, page_principal

    request = Request(scope)
    return page_principal(request) is not None or bearer_principal(request) is not None


def rewrite(scope: Scope, store: Store) -> bool:
    """Replace id prefixes in the request's path and query by whole ids; whether anything changed.
    ApiError (404, 409) for a prefix that names no id or several."""
    changed = False
    path: str = scope["path"]
    for pattern, kinds in PATHS:
        m = pattern.match(path)
        if m is not None:
            whole = resolve_id(store, m.group("id"), kinds)
            if whole != m.group("id"):
                path = path[:m.start("id")] + whole + path[m.end("id"):]
                scope["path"], scope["raw_path"] = path, path.encode()
                changed = True
            break
    params = QUERIES.get(path)
    if params is not None and scope.get("query_string"):
        items = parse_qsl(scope["query_string"].decode("latin-1"), keep_blank_values=True)
        out = []
        for key, value in items:
            kinds = params.get(key)
            if kinds is not None and value.strip():
                parts = [p.strip() for p in value.split(",")] if key == "runs" else [value]
                whole = ",".join(resolve_id(store, p, kinds) for p in parts if p)
                changed |= whole != value
                value = whole
            out.append((key, value))
        if changed:
            scope["query_string"] = urlencode(out).encode("latin-1")
    return changed


def _needs_store(scope: Scope) -> bool:
    """Whether the request names an id that is not whole (only then is the store asked)."""
    path: str = scope["path"]
    for pattern, kinds in PATHS:
        m = pattern.match(path)
        if m is not None:
            if not is_whole(m.group("id"), kinds):
                return True
            break
    params = QUERIES.get(path)
    if params is None or not scope.get("query_string"):
        return False
    for key, value in parse_qsl(scope["query_string"].decode("latin-1"), keep_blank_values=True):
        kinds = params.get(key)
        if kinds is not None and value.strip():
            parts = value.split(",") if key == "runs" else [value]
            if any(not is_whole(p.strip(), kinds) for p in parts if p.strip()):
                return True
    return False


class IdPrefixes:
    """ASGI middleware: id prefixes become whole ids before routing (see the module's docstring)."""

    def __init__(self, app: ASGIApp, page_error: PageError | None = None) -> None:
        self.app = app
        self.page_error = page_error  # the web page's error page, for page routes (api/app.py gives it)

    async def __call__(self, scope: Scope, receive: Any, send: Any) -> None:
        if scope["type"] == "http" and _needs_store(scope):
            store: Store = scope["app"].state.jobs.store
            original = (scope["path"], scope.get("raw_path"), scope.get("query_string"))
            try:
                await run_in_threadpool(rewrite, scope, store)  # SQLite off the event loop
            except ApiError as err:
                scope["path"], scope["raw_path"], scope["query_string"] = original
                if await run_in_threadpool(_authorized, scope):
                    await self._error(scope, err)(scope, receive, send)
                    return
        await self.app(scope, receive, send)

    def _error(self, scope: Scope, err: ApiError) -> Response:
        """The page's error page for a page route, else the API's one-line JSON error."""
        if scope["path"].startswith("/ui/") and self.page_error is not None:
            return self.page_error(Request(scope), err)
        return JSONResponse({"detail": err.detail}, err.status)
