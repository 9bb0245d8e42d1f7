"""Time and size bounds on what a client may hold: slow headers, stalled or trickling bodies, huge headers.

uvicorn bounds the pause between two requests of a kept-alive connection (``timeout_keep_alive``)
and the size of a header still incomplete after a read (h11's ``max_incomplete_event_size``), but
nothing else: measured with ``benchmarks/hostile_clients.py``, 200 connections trickling a header
byte every 2 s, 500 connections that send nothing, and uploads that stall half-way or send a byte
a second were all held for as long as their clients liked, each upload with its
``.upload-*.partial`` file. Two mechanisms of ours close that gap:

- ``GuardedH11Protocol`` (uvicorn's h11 protocol, one timer more): a connection must deliver a
  request's whole header within ``header_timeout_s`` of its first byte (or of the connection, for
  a first request); else it gets a 408 (or, when it sent nothing, is closed) and is gone. A
  response sent before its request's body was read (a 413 on a declared size) gives the client
  the same time to finish sending before the connection is closed. A header over
  ``MAX_HEADER_BYTES`` is a 431 naming the limit (uvicorn said 400, and only when the header
  came in more than one read of the socket: a 1 MB header sent at once was served).
- ``BodyTimeout`` (ASGI middleware): a request body must keep coming. A wait of more than
  ``body_timeout_s`` for the next chunk, or a body slower than ``min_body_rate`` bytes/s on
  average once ``body_timeout_s`` has passed, ends the request with a 408 and ``Connection:
  close``; the route sees the client go away (``http.disconnect``), exactly as when a client
  drops the connection, so an upload removes its temporary file. A client that went away is
  one log line, not a traceback.
"""

from __future__ import annotations

import asyncio
import logging
from typing import Any

import h11
from starlette.requests import ClientDisconnect
from starlette.types import ASGIApp, Message, Receive, Scope, Send
from uvicorn.protocols.http.h11_impl import H11Protocol

# Why these values:
HEADER_TIMEOUT_S = 10.0  # a real client sends its header in one packet, in milliseconds; 10 s leaves a slow
#                          link its round trips, and bounds what a slowloris connection holds to 10 s
BODY_TIMEOUT_S = 30.0  # no byte of a body for 30 s is a stall: longer than TCP's retransmission backs off
#                        through a brief outage (a Wi-Fi roam), far shorter than "until the client hangs up"
MIN_BODY_RATE = 1024  # bytes/s on average once BODY_TIMEOUT_S has passed: a trickle of a byte a second (which
#                       no pause timeout catches) ends at 30 s, while the slowest link that uploads MCAP files
#                       at all (a 64 kbit/s modem, 8 KiB/s) is eight times faster
KEEP_ALIVE_S = 5  # uvicorn's default pause allowed between two requests of a connection, stated here
MAX_HEADER_BYTES = 16 * 1024  # h11's default and Node's: the service's own headers (a token, a session
#                               cookie) are under 1 KiB; nginx's default is 8 KiB per line
HEADER_TOO_LARGE = (f"request header over {MAX_HEADER_BYTES // 1024} KiB (the server's limit): send fewer or "
                    "shorter headers")

logger = logging.getLogger("uvicorn.error")


def _raw_response(status: int, reason: str, text: str) -> bytes:
    """A whole ``Connection: close`` response, for a connection whose request h11 never parsed."""
    body = (text + "\n").encode()
    return (f"HTTP/1.1 {status} {reason}\r\ncontent-type: text/plain; charset=utf-8\r\nconnection: close\r\n"
            f"content-length: {len(body)}\r\n\r\n").encode() + body


class GuardedH11Protocol(H11Protocol):
    """uvicorn's h11 protocol with a header deadline and a 431 for oversized headers.

    ``header_timeout_s`` is a class attribute: ``protocol_class`` makes a subclass per server.
    """

    header_timeout_s = HEADER_TIMEOUT_S

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self._deadline: asyncio.TimerHandle | None = None
        self._draining = False  # the deadline is the one for an unread body after the response, not a header's
        self._header_bytes = 0

    def connection_made(self, transport: asyncio.Transport) -> None:  # type: ignore[override]
        super().connection_made(transport)
        self._arm(self._header_timed_out)  # a connection that never sends its header is a slowloris too

    def data_received(self, data: bytes) -> None:
        if self.conn.their_state is h11.IDLE:
            if self._header_too_large(data):
                return
            self._header_bytes += len(data)
            if self._deadline is None or self._draining:  # the next request of a kept-alive connection starts
                self._arm(self._header_timed_out)
        super().data_received(data)
        if self.conn.their_state is not h11.IDLE and not self._draining:
            self._disarm()  # the header is in: the body's pace is BodyTimeout's to judge
            self._header_bytes = 0

    def on_response_complete(self) -> None:
        unread = self.conn.their_state is h11.SEND_BODY  # this request's, before a pipelined one is parsed
        super().on_response_complete()
        if unread and self.conn.their_state is h11.SEND_BODY and not self.transport.is_closing():
            # answered before the body was read (a 413 on its declared size): uvicorn would read the rest for
            # as long as it comes, and each byte stops its keep-alive timer
            self._arm(self._drain_timed_out, draining=True)

    def connection_lost(self, exc: Exception | None) -> None:
        self._disarm()
        super().connection_lost(exc)

    def _header_too_large(self, data: bytes) -> bool:
        """Refuse the request with a 431 when its header, as far as it has come, is over the limit.

        Checked here, before h11 parses: h11's own limit holds only for a header still incomplete after a read,
        so a 1 MB header that arrived in one read of the socket was served."""
        buffered = self.conn.trailing_data[0] + data
        ends = [i for i in (buffered.find(b"\n\r\n"), buffered.find(b"\n\n")) if i >= 0]
        if (min(ends) if ends else len(buffered)) <= MAX_HEADER_BYTES:
            return False
        logger.info("431: %s (%d bytes of it received)", HEADER_TOO_LARGE, len(buffered))
        self.transport.write(_raw_response(431, "Request Header Fields Too Large", HEADER_TOO_LARGE))
        self.transport.close()
        return True

    def _arm(self, callback: Any, draining: bool = False) -> None:
        self._disarm()
        self._draining = draining
        self._deadline = self.loop.call_later(self.header_timeout_s, callback)

    def _disarm(self) -> None:
        if self._deadline is not None:
            self._deadline.cancel()
        self._deadline, self._draining = None, False

    def _header_timed_out(self) -> None:
        self._deadline = None
        if self.transport.is_closing() or self.conn.their_state is not h11.IDLE:
            return
        if self._header_bytes:  # a client that sent nothing made no request to answer
            logger.info("closed a connection whose request header was not complete after %g s (%d bytes)",
                        self.header_timeout_s, self._header_bytes)
            self.transport.write(_raw_response(408, "Request Timeout", f"request header not complete after "
                                                                       f"{self.header_timeout_s:g} s"))
        self.transport.close()

    def _drain_timed_out(self) -> None:
        self._deadline, self._draining = None, False
        if not self.transport.is_closing() and self.conn.their_state is h11.SEND_BODY:
            self.transport.close()


def protocol_class(header_timeout_s: float) -> type[GuardedH11Protocol]:
    """The protocol class of a server whose clients get ``header_timeout_s`` to send a header."""
    return type("GuardedH11Protocol", (GuardedH11Protocol,), {"header_timeout_s": header_timeout_s})


class BodyTimeout:
    """ASGI middleware: 408 for a request body that stalls (``idle_s``) or trickles (under ``min_rate``
    bytes/s once ``idle_s`` has passed; 0: no rate); one log line for a client that went away.

    Parameters
    ----------
    app : the ASGI app to wrap
    idle_s : float, > 0
        longest wait for the next chunk of a body, in seconds
    min_rate : int, >= 0
        lowest average body rate in bytes/s, checked from ``idle_s`` after the request started
    """

    def __init__(self, app: ASGIApp, idle_s: float = BODY_TIMEOUT_S, min_rate: int = MIN_BODY_RATE) -> None:
        if idle_s <= 0 or min_rate < 0:
            raise ValueError(f"idle_s must be > 0 and min_rate >= 0, not {idle_s} and {min_rate}")
        self.app, self.idle_s, self.min_rate = app, idle_s, min_rate

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        loop = asyncio.get_running_loop()
        start = loop.time()
        received, body_done, answered, timed_out = 0, False, False, False
        where = f"{scope['method']} {scope['path']}"

        async def timed_receive() -> Message:
            nonlocal received, body_done, answered, timed_out
            if body_done or timed_out:  # after the body, a receive waits for the disconnect: no bound
                return await receive()
            wait = self.idle_s
            if self.min_rate:
                wait = min(wait, start + self.idle_s + received / self.min_rate - loop.time())
            try:
                message = await asyncio.wait_for(receive(), max(wait, 0.0))
            except asyncio.TimeoutError:  # not the builtin TimeoutError before Python 3.11
                timed_out = True
                why = (f"no body bytes for {self.idle_s:g} s" if wait >= self.idle_s else
                       f"body slower than {self.min_rate} bytes/s after {loop.time() - start:.0f} s")
                logger.info("408 for %s: %s (%d bytes received); connection closed", where, why, received)
                if not answered:
                    answered = True
                    await _send_408(send, f"request body timed out: {why} ({received} bytes received)")
                return {"type": "http.disconnect"}  # to the route, as if the client had gone: it cleans up
            if message["type"] == "http.request":
                received += len(message.get("body", b""))
                body_done = not message.get("more_body", False)
            return message

        async def guarded_send(message: Message) -> None:
            nonlocal answered
            if timed_out:  # the 408 went out; whatever the route says after it has no client
                return
            answered = answered or message["type"] == "http.response.start"
            await send(message)

        try:
            await self.app(scope, timed_receive, guarded_send)
        except ClientDisconnect:
            if not timed_out:
                logger.info("client went away during %s (%d body bytes received)", where, received)


async def _send_408(send: Send, text: str) -> None:
    body = (text + "\n").encode()
    await send({"type": "http.response.start", "status": 408,
                "headers": [(b"content-type", b"text/plain; charset=utf-8"), (b"connection", b"close"),
                            (b"content-length", str(len(body)).encode())]})
    await send({"type": "http.response.body", "body": body})


def server_config(app: ASGIApp, host: str, port: int, log_level: str, header_timeout_s: float) -> Any:
    """The ``uvicorn.Config`` of ``slamreplay serve``: the guarded protocol and the bounds above."""
    import uvicorn

    return uvicorn.Config(app, host=host, port=port, log_level=log_level, http=protocol_class(header_timeout_s),
                          timeout_keep_alive=KEEP_ALIVE_S, h11_max_incomplete_event_size=MAX_HEADER_BYTES)
