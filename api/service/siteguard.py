"""Requests from other sites: the Host check (against DNS rebinding) and the Origin check (against cross-site
form posts), one pure ASGI middleware in front of every route.

A web page the user visits on another site can make the browser send requests to
``http://127.0.0.1:8000``: a form posted there carries the other site's ``Origin`` and creates a job
(the browser does not let that page read the answer, but the job exists). And a name the other site
controls, rebound from its own address to 127.0.0.1 (DNS rebinding), lets its scripts read the answers
too, with ``Host: evil.example``. So, with or without a token:

- only the host names the server answers to are served (``served_hosts``): the loopback names, the
  address it is bound to, and those configured (``--allowed-host``, ``SLAMREPLAY_ALLOWED_HOSTS``; ``*``
  for any, ``*.example.org`` for its subdomains); any other ``Host`` is a 400;
- a POST, PUT, PATCH or DELETE whose ``Origin`` (else ``Referer``) is not this server's own origin is a
  403. Requests with neither header (curl, scripts, the CLI) are not from a browser page and pass;
- no page may be framed by another site (clickjacking: a page framing ``/ui/jobs/ID/delete`` under a decoy
  button gets a real click that posts the form with this server's own Origin, which the check above lets
  through): every response says ``Content-Security-Policy: frame-ancestors 'none'`` and
  ``X-Frame-Options: DENY`` (OWASP's defence, the second for browsers without CSP level 2). No page of
  this server frames another of its own, so nothing is given up;
- no script that is not one of this server's files runs on its pages: every page says
  ``Content-Security-Policy: PAGE_CSP`` (scripts, styles, images and connections from this server only; no
  inline script, event handler or style attribute; forms post only here; no ``<base>``, no plugins), so
  text a user wrote (a run's name, a note, a suite file) cannot become a script even if escaping ever failed.
  Three kinds of page set their own policy, which keeps ``frame-ancestors 'none'``: the Rerun web viewer
  (api/web/web.py ``VIEWER_CSP``: WebAssembly and its inline loader), the API docs (api/service/docs_pages.py: the hash
  of Swagger UI's one inline script, ReDoc's inline styles) and the comparison and history reports, which are
  self-contained HTML files with an inline stylesheet (``REPORT_CSP``: inline styles, still no inline script).

Ports are not compared for ``Host``: a rebinding attack keeps the victim's port and changes the name.
"""

from __future__ import annotations

import ipaddress
from collections.abc import Iterable
from urllib.parse import urlsplit

from starlette.datastructures import Headers
from starlette.responses import JSONResponse
from starlette.types import ASGIApp, Message, Receive, Scope, Send

LOOPBACK_HOSTS = ("127.0.0.1", "localhost", "::1")
WILDCARD_BINDS = ("", "0.0.0.0", "::")  # "every address": never a Host a client sends
STATE_CHANGING = frozenset({"POST", "PUT", "PATCH", "DELETE"})
DEFAULT_PORTS = {"http": 80, "https": 443, "ws": 80, "wss": 443}
# The policy of slamreplay's own pages (see the module docstring)
PAGE_CSP = ("default-src 'self'; script-src 'self'; style-src 'self'; img-src 'self' data:; connect-src 'self'; "
            "font-src 'self'; object-src 'none'; base-uri 'none'; form-action 'self'; frame-ancestors 'none'")
# A self-contained report (replay/runs/report.py's HTML) served as a page: its inline stylesheet, no inline script
REPORT_CSP = PAGE_CSP.replace("style-src 'self'", "style-src 'self' 'unsafe-inline'")
# on every response (see the module docstring): no framing by any site, only this server's scripts, no
# content-type sniffing, no full URL (with its query: a filter, a run's name) sent to other sites
SECURITY_HEADERS = ((b"content-security-policy", PAGE_CSP.encode()), (b"x-frame-options", b"DENY"),
                    (b"x-content-type-options", b"nosniff"), (b"referrer-policy", b"same-origin"))
FRAME_ANCESTORS = b"frame-ancestors 'none'"


def split_host(value: str) -> tuple[str, int | None]:
    """``host[:port]`` (a Host header, or an allowed host) as (lower-case name without brackets, port or None).

    A bare IPv6 address (``::1``) is a name without a port; in a Host header it is bracketed (``[::1]:8000``).
    """
    value = value.strip().lower()
    if value.startswith("["):
        name, _, rest = value[1:].partition("]")
        port = rest[1:] if rest.startswith(":") else ""
        return name, int(port) if port.isdigit() else None
    if value.count(":") == 1:
        name, _, port = value.partition(":")
        return name, int(port) if port.isdigit() else None
    return value, None


def served_hosts(configured: Iterable[str], bind_host: str | None = None) -> tuple[str, ...]:
    """The host names a server answers to: loopback, ``bind_host`` (unless it means every address) and
    ``configured``, lower-case, without ports, first occurrence kept."""
    names = [*LOOPBACK_HOSTS]
    if bind_host is not None and bind_host not in WILDCARD_BINDS:
        names.append(bind_host)
    names += configured
    return tuple(dict.fromkeys(split_host(n)[0] for n in names))


def _matches(name: str, pattern: str) -> bool:
    if pattern == "*":
        return True
    if pattern.startswith("*."):
        return name.endswith(pattern[1:]) and len(name) > len(pattern) - 1
    return name == pattern


def _same_host(a: str, b: str) -> bool:
    """Host names equal, IP addresses compared as addresses (``::1`` and ``0:0::1``)."""
    try:
        return ipaddress.ip_address(a) == ipaddress.ip_address(b)
    except ValueError:
        return a == b


def same_origin(source: str, host_header: str, scheme: str) -> bool:
    """Whether the URL ``source`` (an Origin or a Referer) is the origin of a request to ``host_header``.

    The scheme is not compared: behind a TLS proxy the page is ``https`` while this server sees ``http``.
    A port left out on either side is the default port of the source's scheme.
    """
    try:
        url = urlsplit(source.strip())
        src_port = url.port
    except ValueError:
        return False
    if not url.hostname:
        return False  # "null" (a sandboxed frame, a file:// page) or garbage
    default = DEFAULT_PORTS.get(url.scheme or scheme)
    name, port = split_host(host_header)
    return _same_host(url.hostname, name) and (src_port or default) == (port or default)


class SiteGuard:
    """ASGI middleware: 400 for a ``Host`` not in ``hosts``, 403 for a state-changing request from another origin.

    Parameters
    ----------
    app : the wrapped application
    hosts : host names served besides the loopback ones (patterns: ``*``, ``*.example.org``)
    """

    def __init__(self, app: ASGIApp, hosts: Iterable[str] = ()) -> None:
        self.app = app
        self.hosts = served_hosts(hosts)

    def host_allowed(self, host_header: str) -> bool:
        name, _ = split_host(host_header)
        return bool(name) and any(_matches(name, p) or _same_host(name, p) for p in self.hosts)

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] not in ("http", "websocket"):
            await self.app(scope, receive, send)
            return
        headers = Headers(scope=scope)
        host = headers.get("host", "")
        problem: tuple[int, str] | None = None
        if not self.host_allowed(host):
            shown = host[:100] or "(none)"
            problem = (400, f"this server does not serve the host name {shown!r} (a guard against DNS rebinding): "
                            "use the address it was started on, or start it with --allowed-host NAME "
                            "(SLAMREPLAY_ALLOWED_HOSTS)")
        elif scope["type"] == "http" and scope["method"] in STATE_CHANGING:
            source = headers.get("origin") or headers.get("referer")
            if source is not None and not same_origin(source, host, scope.get("scheme", "http")):
                problem = (403, f"cross-site request refused: a {scope['method']} from {source[:100]!r} to {host!r}; "
                                "this server takes changes only from its own pages and from clients that send no "
                                "Origin (curl, scripts)")
        if scope["type"] == "http":
            send = _with_headers(send)
        if problem is None:
            await self.app(scope, receive, send)
        elif scope["type"] == "websocket":
            await send({"type": "websocket.close", "code": 1008, "reason": problem[1][:120]})
        else:
            await JSONResponse({"detail": problem[1]}, problem[0])(scope, receive, send)


def _with_headers(send: Send) -> Send:
    """``send`` adding ``SECURITY_HEADERS`` to the response's start (replacing any of the same name, but for a
    route's own Content-Security-Policy, which keeps its directives and gains frame-ancestors)."""
    names = {name for name, _ in SECURITY_HEADERS}
    csp = FRAME_ANCESTORS

    async def wrapped(message: Message) -> None:
        if message["type"] == "http.response.start":
            headers = message.get("headers", [])
            own = [v for k, v in headers if k.lower() == b"content-security-policy"]
            kept = [(k, v) for k, v in headers if k.lower() not in names]
            added = [(k, own[0] + b"; " + csp if own and b"frame-ancestors" not in own[0] else own[0] if own else v)
                     if k == b"content-security-policy" else (k, v) for k, v in SECURITY_HEADERS]
            message = {**message, "headers": [*kept, *added]}
        await send(message)

    return wrapped
