"""Who is asking and whether they may: the server's mode, the role each route needs, page sessions, CSRF
tokens, and the audit trail's entries.

A server is in one of three modes, read from its data directory at each request (``slamreplay users add``
may run while it serves):

- ``open``: no people and no ``SLAMREPLAY_TOKEN``: anyone who reaches it may do anything (the loopback
  default); the trail names them ``anonymous``.
- ``token``: no people, one shared token: the API wants it as ``Authorization: Bearer``, the page asks for
  it once and keeps a cookie derived from it; the trail names its holder ``token holder``.
- ``people``: once anyone was added (``api/service/people.py``): every request needs a person's token (API) or
  session (page), and each person's role decides what they may do; the shared token is not used.

Roles: a ``viewer`` reads; a ``runner`` also uploads, submits, cancels and labels (anyone's runs); an
``admin`` also deletes and manages people. `RULES` names the role of every route that changes something
(a state-changing route not named there needs ``admin``: a route added later is closed until it is named).
A route a role may not use is a 403: one line of JSON for the API, a readable page for the page. Forms
posted with a session cookie carry a CSRF token derived from that cookie (`csrf_token`); bearer calls
need none.
"""

from __future__ import annotations

import hashlib
import hmac
from dataclasses import dataclass
from typing import Any, Literal

from starlette.requests import Request

from slamreplay.api.service.errors import ForbiddenError, UnauthorizedError
from slamreplay.api.service.people import RANK, Role
from slamreplay.api.service.store import Store

Mode = Literal["open", "token", "people"]
COOKIE = "slamreplay_session"
CSRF_FIELD = "csrf"
STATE_CHANGING = frozenset({"POST", "PUT", "PATCH", "DELETE"})
# (method, route path) -> (role, what it does, in the words of a 403). GET routes not named need a viewer.
RULES: dict[tuple[str, str], tuple[Role, str]] = {
    ("POST", "/recordings"): ("runner", "upload recordings"),
    ("POST", "/recordings/{recording_id}/recover"): ("runner", "recover damaged uploads"),
    ("DELETE", "/recordings/{recording_id}"): ("admin", "delete recordings"),
    ("POST", "/recordings/live"): ("runner", "record live streams"),  # api/service/live_routes.py
    ("POST", "/recordings/live/{task_id}/stop"): ("runner", "stop live recordings"),
    ("POST", "/jobs"): ("runner", "submit jobs"),
    ("DELETE", "/jobs/{job_id}"): ("runner", "cancel jobs"),
    ("PATCH", "/jobs/{job_id}"): ("runner", "name, tag and annotate runs"),
    ("POST", "/runs"): ("runner", "push runs made elsewhere"),
    ("POST", "/suites"): ("runner", "run suites"),
    ("POST", "/runs/suites"): ("runner", "push runs made elsewhere"),
    ("POST", "/history/suites/{name:path}/runs"): ("runner", "run suites on a commit"),
    ("POST", "/ui/recordings"): ("runner", "upload recordings"),
    ("POST", "/ui/jobs"): ("runner", "submit jobs"),
    ("POST", "/ui/suites"): ("runner", "run suites"),
    ("GET", "/ui/jobs/{job_id}/edit"): ("runner", "name, tag and annotate runs"),
    ("POST", "/ui/jobs/{job_id}/edit"): ("runner", "name, tag and annotate runs"),
    ("GET", "/ui/jobs/{job_id}/cancel"): ("runner", "cancel jobs"),
    ("POST", "/ui/jobs/{job_id}/cancel"): ("runner", "cancel jobs"),
    ("GET", "/ui/jobs/{job_id}/delete"): ("admin", "delete runs"),
    ("POST", "/ui/jobs/{job_id}/delete"): ("admin", "delete runs"),
    ("POST", "/ui/history/{name:path}/runs"): ("runner", "run suites on a commit"),
    ("GET", "/audit"): ("admin", "read the audit trail"),
    ("GET", "/ui/people"): ("admin", "manage people"),
    ("POST", "/ui/people"): ("admin", "manage people"),
    ("POST", "/ui/people/{name}"): ("admin", "manage people"),
    ("GET", "/ui/audit"): ("admin", "read the audit trail"),
}
# Failed sign-ins on the page: at most this many from one address in the window, then a 429 until the oldest
# leaves it (each wrong token also costs the server a slow hash: guessing stays hopeless and cheap to refuse)
SIGN_IN_ATTEMPTS, SIGN_IN_WINDOW_S = 10, 900.0
RECORD_PREFIX = "/recordings/record/"  # one route per importer (api/service/record_routes.py): recordings made here
# Page routes whose form is multipart and streamed: the route checks the CSRF field itself (api/web/web.py)
STREAMED_FORMS = frozenset({"/ui/recordings"})


@dataclass(frozen=True, slots=True)
class Principal:
    """Who a request is from: a person (``bearer``, ``session``), the shared token's holder, or anyone."""

    name: str
    role: Role
    via: Literal["open", "token", "bearer", "session"]
    cookie: str | None = None  # the session cookie that identified them: their forms' CSRF tokens derive from it

    def can(self, role: str) -> bool:
        return RANK[self.role] >= RANK[role]

    @property
    def csrf(self) -> str | None:
        return None if self.cookie is None else csrf_token(self.cookie)


ANYONE = Principal("anonymous", "admin", "open")
TOKEN_HOLDER = "token holder"


def csrf_token(cookie: str) -> str:
    """The CSRF token of the forms of a session: a MAC of a fixed text under the session's cookie value."""
    return hmac.new(cookie.encode(), b"slamreplay csrf v1", hashlib.sha256).hexdigest()


def session_value(token: str) -> str:
    """The ``token`` mode's cookie: a MAC of a fixed text under the shared token (the token itself never leaves)."""
    return hmac.new(token.encode(), b"slamreplay web session v1", hashlib.sha256).hexdigest()


def store_of(request: Request) -> Store:
    store: Store = request.app.state.jobs.store
    return store


def server_mode(request: Request) -> Mode:
    if store_of(request).has_people():
        return "people"
    return "token" if request.app.state.settings.token is not None else "open"


def client_address(request: Request) -> str:
    """The client's address as the server sees it (behind a proxy: what uvicorn's proxy headers make of it)."""
    return request.client.host if request.client is not None else "unknown"


def required(method: str, route_path: str) -> tuple[Role, str]:
    """The role a route needs and what it does: `RULES`, else a viewer for reading, an admin for a change."""
    rule = RULES.get((method, route_path))
    if rule is not None:
        return rule
    if method in STATE_CHANGING:
        if route_path.startswith(RECORD_PREFIX):
            return "runner", "record on the server"
        return "admin", f"{method} {route_path}"
    return "viewer", "read"


def route_rule(request: Request) -> tuple[Role, str]:
    route = request.scope.get("route")
    return required(request.method, getattr(route, "path", request.url.path))


def bearer_principal(request: Request) -> Principal | None:
    """Who an API request is from, or None (no token, or a wrong one). People's tokens cost a slow hash
    (cached for minutes per process): call it from a worker thread."""
    mode = server_mode(request)
    if mode == "open":
        return ANYONE
    scheme, _, value = request.headers.get("authorization", "").partition(" ")
    value = value.strip()
    if scheme.lower() != "bearer" or not value:
        return None
    if mode == "token":
        token = request.app.state.settings.token
        return Principal(TOKEN_HOLDER, "admin", "token") if hmac.compare_digest(value.encode(), token.encode()) \
            else None
    user = store_of(request).user_of_token(value)
    return None if user is None else Principal(user.name, user.role, "bearer")


def page_principal(request: Request) -> Principal | None:
    """Who a page request is from (its session cookie), or None."""
    mode = server_mode(request)
    if mode == "open":
        return ANYONE
    cookie = request.cookies.get(COOKIE, "")
    if not cookie:
        return None
    if mode == "token":
        ok = hmac.compare_digest(cookie, session_value(request.app.state.settings.token))
        return Principal(TOKEN_HOLDER, "admin", "token", cookie) if ok else None
    user = store_of(request).user_of_session(cookie)
    return None if user is None else Principal(user.name, user.role, "session", cookie)


def unauthorized(request: Request) -> UnauthorizedError:
    """The 401 of an API request without a good token, saying how to send one in this mode."""
    sent = request.headers.get("authorization", "").partition(" ")
    if sent[0].lower() == "bearer" and sent[2].strip():
        return UnauthorizedError("wrong bearer token")
    if server_mode(request) == "people":
        return UnauthorizedError("this server knows its people: send your token as the header `Authorization: Bearer "
                                 "<TOKEN>` (an admin makes one: `slamreplay users add NAME --role runner`)")
    return UnauthorizedError("this server needs a token: send the header `Authorization: Bearer <SLAMREPLAY_TOKEN>`")


def forbidden_text(p: Principal, need: Role, what: str) -> str:
    return (f"{p.name} is a {p.role} and may not {what}: that needs the role {need} (an admin can give it: "
            f"`slamreplay users role {p.name} {need}`)")


def api_principal(request: Request) -> Principal:
    """The API's check: 401 without a good token, 403 when the person's role may not use the route.

    A read (GET, HEAD) without an Authorization header may come from the page's session instead (the page links to
    a job's manifest, log and files); a change through the API always needs the token (a cookie alone would let
    another site's form make it: the page's own forms carry CSRF tokens)."""
    p = bearer_principal(request)
    if p is None and request.method in ("GET", "HEAD") and "authorization" not in request.headers:
        p = page_principal(request)
    if p is None:
        raise unauthorized(request)
    need, what = route_rule(request)
    if not p.can(need):
        raise ForbiddenError(forbidden_text(p, need, what))
    request.state.principal = p
    return p


class LoginRequiredError(Exception):
    """A page request without a valid session while the server needs one."""


class PageForbiddenError(Exception):
    """A page request the person's role may not make, or a form without its CSRF token: the 403 page."""

    def __init__(self, message: str, principal: Principal | None = None) -> None:
        super().__init__(message)
        self.principal = principal


def check_csrf(p: Principal, sent: Any) -> None:
    """PageForbiddenError unless ``sent`` is the CSRF token of ``p``'s session (nothing to check without one)."""
    want = p.csrf
    if want is not None and not (isinstance(sent, str) and hmac.compare_digest(sent.encode(), want.encode())):
        raise PageForbiddenError("This form did not come from this server's page for your session (its CSRF token "
                                 "is missing or out of date): go back, reload the page and send it again.", p)


async def page_check(request: Request) -> Principal:
    """The page's check: sign-in (LoginRequiredError), the route's role (PageForbiddenError) and, for a form
    posted with a session cookie, its CSRF token."""
    from starlette.concurrency import run_in_threadpool

    p = await run_in_threadpool(page_principal, request)
    if p is None:
        raise LoginRequiredError
    need, what = route_rule(request)
    if not p.can(need):
        raise PageForbiddenError(forbidden_text(p, need, what), p)
    request.state.principal = p
    if request.method in STATE_CHANGING and p.cookie is not None:
        route = getattr(request.scope.get("route"), "path", "")
        if route not in STREAMED_FORMS:  # those check the field as the body streams in
            form = await request.form()
            check_csrf(p, form.get(CSRF_FIELD))
    return p


def principal_of(request: Request) -> Principal | None:
    """Who the request is from, as its route's check found it (or the page's session, for a public page)."""
    p: Principal | None = getattr(request.state, "principal", None)
    return p if p is not None else page_principal(request)


def sign_in_wait_s(request: Request) -> float:
    """Seconds until this address may try to sign in again (0: now): `SIGN_IN_ATTEMPTS` failures in the window."""
    import time

    now = time.time()
    failed, oldest = store_of(request).failed_sign_ins(client_address(request), now - SIGN_IN_WINDOW_S)
    return 0.0 if failed < SIGN_IN_ATTEMPTS or oldest is None else max(oldest + SIGN_IN_WINDOW_S - now, 1.0)


def who(request: Request) -> str:
    """The name of whom the request is from (``anonymous`` on an open server, ``token holder`` with one token)."""
    return (principal_of(request) or ANYONE).name


def record(request: Request, action: str, target: str | None = None, detail: str | None = None) -> None:
    """Add a change to the audit trail: who (the request's principal), when, from which address."""
    p = principal_of(request) or ANYONE
    store_of(request).add_audit(p.name, client_address(request), action, target, detail)


def link_secret(request: Request) -> str | None:
    """The key of the viewer's .rrd links (``deps.rrd_key``): the shared token, a secret of the data directory
    once it has people, None when the server is open."""
    if server_mode(request) == "people":
        return store_of(request).server_secret("viewer-links").hex()
    token: str | None = request.app.state.settings.token
    return token
