"""A subscribing client of the Foxglove WebSocket protocol (v1), as ``foxglove_bridge`` and the Foxglove SDK serve it.

The protocol (github.com/foxglove/ws-protocol, docs/spec.md; the SDK's rust/foxglove/src/protocol/v1): the client
offers subprotocols in the handshake and the server picks one: ``foxglove.sdk.v1`` (the Foxglove SDK, and
``foxglove_bridge`` built on it) or ``foxglove.websocket.v1`` (older bridges and ws-protocol servers); both speak
the same v1 messages. The server sends JSON text messages (``serverInfo`` first, then ``advertise`` /
``unadvertise`` of channels, ``status``) and binary ones (``0x01`` message data: subscription id u32, the
server's log time u64 in ns, the payload; ``0x02`` time); the client sends ``subscribe`` with ids of its choosing.
A channel's schema arrives base64-encoded when its schema encoding is binary (protobuf, flatbuffer), as text
otherwise (ros2msg, jsonschema); without a ``schemaEncoding`` it follows from the message encoding.

Only connecting, reading and subscribing are here; what the messages become is :mod:`.foxglove_live`'s.
"""

from __future__ import annotations

import base64
import binascii
import json
import struct
import time
from collections.abc import Iterator
from contextlib import ExitStack, contextmanager
from dataclasses import dataclass
from typing import Any
from urllib.parse import urlsplit

from slamreplay.recorder.errors import RecorderError

SUBPROTOCOLS = ("foxglove.sdk.v1", "foxglove.websocket.v1")
BINARY_SCHEMA_ENCODINGS = ("protobuf", "flatbuffer")
SCHEMA_ENCODING_OF = {"protobuf": "protobuf", "flatbuffer": "flatbuffer", "cdr": "ros2msg", "ros1": "ros1msg",
                      "json": "jsonschema"}
OP_MESSAGE_DATA, OP_TIME = 0x01, 0x02
_DATA_HEADER = struct.Struct("<BIQ")
# One WebSocket message: an uncompressed 4K rgb8 image is 25 MB; a payload past this is refused by the library
# (the connection closes with 1009 and is retried) rather than held in memory.
MAX_MESSAGE_BYTES = 64 << 20
# Frames the library reads ahead of the recorder: a burst of images or a slow write waits here, not at the server
# (whose own backlog drops the oldest messages when full).
READ_AHEAD_FRAMES = 4096


class ConnectError(RecorderError):
    """The server could not be reached, or does not speak the Foxglove WebSocket protocol."""


class ConnectionLostError(RecorderError):
    """An open connection ended."""


@dataclass(frozen=True, slots=True)
class ServerInfo:
    name: str
    session_id: str
    subprotocol: str
    capabilities: tuple[str, ...]


@dataclass(frozen=True, slots=True)
class ChannelInfo:
    """One advertised channel; ``schema`` decoded to bytes (``problem``: why it could not be, else None)."""

    id: int
    topic: str
    encoding: str
    schema_name: str
    schema_encoding: str
    schema: bytes
    problem: str | None = None

    @property
    def kind(self) -> tuple[str, str, str, bytes]:
        """What a channel is, apart from its id: a re-advertised channel with the same kind is the same stream."""
        return self.topic, self.encoding, self.schema_name, self.schema


@dataclass(frozen=True, slots=True)
class Advertise:
    channels: tuple[ChannelInfo, ...]


@dataclass(frozen=True, slots=True)
class Unadvertise:
    channel_ids: tuple[int, ...]


@dataclass(frozen=True, slots=True)
class Status:
    level: int  # 0 info, 1 warning, 2 error
    message: str


@dataclass(frozen=True, slots=True)
class MessageData:
    """A message on a subscription: the server's log time (ns) and the payload; ``receive_ns``: our wall clock."""

    subscription_id: int
    log_time_ns: int
    payload: bytes
    receive_ns: int


Event = Advertise | Unadvertise | Status | MessageData


def check_url(url: str) -> str:
    """``url`` when it is a ws:// or wss:// URL with a host; RecorderError saying what to give otherwise."""
    try:
        parts = urlsplit(url)
        port = parts.port
    except ValueError as err:
        raise RecorderError(f"{url!r} is not a WebSocket URL ({err}): give ws://HOST:PORT (foxglove_bridge and the "
                            f"Foxglove SDK listen on port 8765)") from None
    if parts.scheme not in ("ws", "wss") or not parts.hostname:
        raise RecorderError(f"{url!r} is not a WebSocket URL: give ws://HOST:PORT (foxglove_bridge and the Foxglove "
                            f"SDK listen on port 8765)")
    del port
    return url


def channel_info(obj: Any) -> ChannelInfo:
    """An ``advertise`` entry as a ChannelInfo; ValueError (KeyError, TypeError) when it lacks a field."""
    encoding = str(obj["encoding"])
    schema_encoding = str(obj.get("schemaEncoding") or SCHEMA_ENCODING_OF.get(encoding, ""))
    text = str(obj.get("schema", ""))
    problem = None
    if schema_encoding in BINARY_SCHEMA_ENCODINGS:
        try:
            schema = base64.b64decode(text, validate=True)
        except (binascii.Error, ValueError) as err:
            schema, problem = b"", f"its {schema_encoding} schema is not valid base64 ({err})"
    else:
        schema = text.encode()
    return ChannelInfo(int(obj["id"]), str(obj["topic"]), encoding, str(obj.get("schemaName", "")), schema_encoding,
                       schema, problem)


def parse_text(text: str) -> Event | ServerInfo | None:
    """A JSON message of the server as an event (None: one the recorder does not use)."""
    try:
        obj = json.loads(text)
        op = obj.get("op")
        if op == "advertise":
            return Advertise(tuple(channel_info(c) for c in obj["channels"]))
        if op == "unadvertise":
            return Unadvertise(tuple(int(i) for i in obj["channelIds"]))
        if op == "status":
            return Status(int(obj.get("level", 0)), str(obj.get("message", "")))
        if op == "serverInfo":
            return ServerInfo(str(obj.get("name", "")), str(obj.get("sessionId", "")), "",
                              tuple(str(c) for c in obj.get("capabilities", ())))
    except (ValueError, KeyError, TypeError, AttributeError) as err:
        return Status(2, f"the server sent a message that is not the protocol's: {type(err).__name__}: {err}")
    return None


def parse_binary(data: bytes, receive_ns: int) -> MessageData | None:
    """A binary message of the server: message data, or None (time, and what a subscriber does not use)."""
    if len(data) >= _DATA_HEADER.size and data[0] == OP_MESSAGE_DATA:
        _, sub, log_time = _DATA_HEADER.unpack_from(data)
        return MessageData(sub, log_time, data[_DATA_HEADER.size:], receive_ns)
    return None


class Session:
    """One open connection: read its events, subscribe to channels."""

    def __init__(self, ws: Any, url: str) -> None:
        self._ws, self.url = ws, url
        self.subprotocol: str = ws.subprotocol
        self.server: ServerInfo | None = None
        self._next_subscription = 1

    def recv(self, timeout_s: float) -> Event | None:
        """The next event, or None when nothing came within ``timeout_s`` (or the message is not used)."""
        from websockets.exceptions import ConnectionClosed

        try:
            data = self._ws.recv(timeout=timeout_s)
        except TimeoutError:
            return None
        except ConnectionClosed as err:
            raise ConnectionLostError(_closed(err)) from err
        if isinstance(data, bytes):
            return parse_binary(data, time.time_ns())
        event = parse_text(data)
        if isinstance(event, ServerInfo):
            self.server = ServerInfo(event.name, event.session_id, self.subprotocol, event.capabilities)
            return None
        return event

    def subscribe(self, channel_ids: list[int]) -> dict[int, int]:
        """Subscribe to ``channel_ids``; subscription id -> channel id."""
        from websockets.exceptions import ConnectionClosed

        subs = {}
        for cid in channel_ids:
            subs[self._next_subscription] = cid
            self._next_subscription += 1
        if subs:
            try:
                self._ws.send(json.dumps({"op": "subscribe", "subscriptions": [
                    {"id": sid, "channelId": cid} for sid, cid in subs.items()]}))
            except ConnectionClosed as err:
                raise ConnectionLostError(_closed(err)) from err
        return subs


def _closed(err: Any) -> str:
    """Why a connection closed, in words."""
    rcvd = getattr(err, "rcvd", None)
    if rcvd is None:
        return "the connection dropped (no close frame)"
    return f"the server closed the connection (code {rcvd.code}{': ' + rcvd.reason if rcvd.reason else ''})"


@contextmanager
def connect(url: str, *, open_timeout_s: float = 5.0, ping_interval_s: float = 5.0,
            ping_timeout_s: float = 20.0) -> Iterator[Session]:
    """An open session with the server at ``url``; ConnectError, one line, when there is none.

    Pings every ``ping_interval_s`` find a link that died without a close (a cable, Wi-Fi) within about
    ``ping_timeout_s``. The server's pong waits behind the messages it has queued for us, so the timeout is the
    backlog tolerated when the recorder falls behind a burst: at 5 s, a stream of ROS 2 laser scans faster than
    the pole extractor dropped a connection that was alive.
    """
    from websockets.exceptions import InvalidHandshake, InvalidURI
    from websockets.sync.client import connect as ws_connect

    check_url(url)
    with ExitStack() as stack:
        try:
            ws = stack.enter_context(ws_connect(
                url, subprotocols=list(SUBPROTOCOLS), open_timeout=open_timeout_s,  # type: ignore[arg-type]
                max_size=MAX_MESSAGE_BYTES, max_queue=READ_AHEAD_FRAMES, compression=None,
                ping_interval=ping_interval_s, ping_timeout=ping_timeout_s))
        except InvalidURI as err:
            raise ConnectError(f"{url!r} is not a WebSocket URL: {err}") from None
        except InvalidHandshake as err:
            raise ConnectError(f"{url} answered, but not as a Foxglove WebSocket server ({err}); it must accept one "
                               f"of the subprotocols {', '.join(SUBPROTOCOLS)}") from None
        except TimeoutError:
            raise ConnectError(f"{url}: no answer within {open_timeout_s:g} s (is the robot on this network, and "
                               f"its server running?)") from None
        except OSError as err:
            why = err.strerror or str(err) or type(err).__name__
            raise ConnectError(f"cannot connect to {url}: {why} (is foxglove_bridge or the Foxglove SDK server "
                               f"running there?)") from None
        if ws.subprotocol not in SUBPROTOCOLS:
            raise ConnectError(f"{url} did not accept the Foxglove WebSocket protocol (offered "
                               f"{', '.join(SUBPROTOCOLS)}; it chose {ws.subprotocol or 'none'})")
        yield Session(ws, url)
