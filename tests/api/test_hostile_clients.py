"""Hostile clients against a real `slamreplay serve` with short timeouts: a stalled or trickling upload is cut off
with a 408 and leaves no partial file, a slowloris or idle connection is closed within the header timeout while
other clients are served, and an oversized header is a 431 after which the server keeps serving."""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest
from patience import deadline as give_up_at
from pydantic import ValidationError

from slamreplay.api.service.settings import Settings
from slamreplay.api.service.timeouts import MAX_HEADER_BYTES, BodyTimeout
from tests.api.test_serve_lock import free_port, stop

HEADER_S, BODY_S = 1.0, 1.5  # the server's timeouts here, short so that each test takes seconds
SLACK_S = 1.5  # scheduling on a shared 2-core machine
ENV = {k: v for k, v in os.environ.items() if not k.startswith("SLAMREPLAY_")} | {
    "PYTHONUNBUFFERED": "1", "SLAMREPLAY_HEADER_TIMEOUT_S": str(HEADER_S), "SLAMREPLAY_BODY_TIMEOUT_S": str(BODY_S),
    "SLAMREPLAY_MAX_UPLOAD_BYTES": str(1 << 20)}


@pytest.fixture(scope="module")
def served(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[str, int, Path]]:
    """(base URL, port, data directory) of one server for the module."""
    data = tmp_path_factory.mktemp("hostile") / "data"
    log = data.parent / "server.log"
    port = free_port()
    with open(log, "ab") as out:
        proc = subprocess.Popen([sys.executable, "-m", "slamreplay.api.cli", "serve", "--workers", "1", "--port",
                                 str(port), "--data-dir", str(data)], stdout=out, stderr=subprocess.STDOUT, env=ENV)
    base = f"http://127.0.0.1:{port}"
    deadline = give_up_at(60)
    while True:
        assert proc.poll() is None, log.read_text()
        try:
            if httpx.get(f"{base}/healthz", timeout=1).status_code == 200:
                break
        except httpx.TransportError:
            pass
        assert time.monotonic() < deadline, log.read_text()
        time.sleep(0.1)
    try:
        yield base, port, data
    finally:
        stop(proc)


def read_until_closed(s: socket.socket, limit_s: float) -> tuple[bytes, float]:
    """Everything the server sends until it closes the connection, and when that was (seconds from now)."""
    tic = time.monotonic()
    s.settimeout(limit_s)
    data = b""
    try:
        while chunk := s.recv(65536):
            data += chunk
    except ConnectionResetError:
        pass
    return data, time.monotonic() - tic


def partials(data: Path) -> list[Path]:
    return list((data / "recordings").glob(".upload-*.partial"))


def healthz_ms(base: str) -> float:
    tic = time.perf_counter()
    assert httpx.get(f"{base}/healthz", timeout=5).status_code == 200
    return (time.perf_counter() - tic) * 1e3


def test_stalled_form_upload_is_cut_off_and_leaves_no_partial_file(served: tuple[str, int, Path]) -> None:
    """A form upload that sends half its body and stops: 408 within the body timeout, connection closed, and its
    temporary file (there while it stalled) removed."""
    _, port, data = served
    body = (b'--b0\r\nContent-Disposition: form-data; name="file"; filename="x.mcap"\r\n\r\n' + os.urandom(200_000)
            + b"\r\n--b0--\r\n")
    with socket.create_connection(("127.0.0.1", port)) as s:
        s.sendall(b"POST /recordings HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Type: multipart/form-data; boundary=b0"
                  b"\r\nContent-Length: " + str(len(body)).encode() + b"\r\n\r\n" + body[:len(body) // 2])
        time.sleep(BODY_S / 3)
        assert len(partials(data)) == 1
        answer, after_s = read_until_closed(s, BODY_S + SLACK_S + 5)
    assert answer.startswith(b"HTTP/1.1 408 "), answer[:200]
    assert b"request body timed out: no body bytes for 1.5 s" in answer
    assert after_s < BODY_S + SLACK_S
    assert partials(data) == []


def test_trickled_body_is_cut_off_by_the_rate_rule(served: tuple[str, int, Path]) -> None:
    """A raw upload whose body comes a byte every 0.3 s (never a pause as long as the body timeout) is a 408 once
    the body timeout has passed, too slow for the minimum rate; no partial file is left."""
    _, port, data = served
    with socket.create_connection(("127.0.0.1", port)) as s:
        s.sendall(b"POST /recordings HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Length: 1000\r\n\r\n")
        tic = time.monotonic()
        s.settimeout(0.3)
        answer = b""
        sending = True
        while time.monotonic() - tic < BODY_S + SLACK_S + 3 and not answer:
            try:
                if sending:
                    s.send(b"\x89")
            except OSError:  # the server closed as this byte went: its answer may still be there to read
                sending = False
            try:
                answer = s.recv(4096)
            except TimeoutError:
                continue
            except OSError:
                break
        waited = time.monotonic() - tic
        answer += read_until_closed(s, 2)[0]
    assert answer.startswith(b"HTTP/1.1 408 "), answer[:200]
    assert b"body slower than 1024 bytes/s" in answer
    assert BODY_S - 0.2 < waited < BODY_S + SLACK_S
    time.sleep(0.2)
    assert partials(data) == []


def test_slowloris_is_closed_within_the_header_timeout_while_others_are_served(
        served: tuple[str, int, Path]) -> None:
    """A header trickled a byte at a time: 408 and closed within the header timeout; meanwhile /healthz answers
    another client quickly (the median answer: a loaded machine once made one of them 741 ms)."""
    base, port, _ = served
    head = b"GET / HTTP/1.1\r\nHost: 127.0.0.1\r\nX-Slow: " + b"a" * 100
    latencies = []
    with socket.create_connection(("127.0.0.1", port)) as s:
        s.settimeout(0.15)
        tic = time.monotonic()
        answer = b""
        for i in range(len(head)):
            try:
                s.send(head[i:i + 1])
            except OSError:  # closed as this byte went: read the answer
                answer, _ = read_until_closed(s, 1)
                break
            try:
                answer = s.recv(4096)
            except TimeoutError:
                latencies.append(healthz_ms(base))
                continue
            except OSError:
                pass
            break
        closed_s = time.monotonic() - tic
        answer += read_until_closed(s, 2)[0]
    assert answer.startswith(b"HTTP/1.1 408 "), answer[:200]
    assert b"request header not complete after 1 s" in answer
    assert HEADER_S - 0.2 < closed_s < HEADER_S + SLACK_S
    # served while the slow header trickles in: half of the answers within 500 ms (a server held by it would answer
    # none before it is closed, 1 s on); one slow answer is a busy machine's, not a blocked server's
    assert latencies and sorted(latencies)[len(latencies) // 2] < 500, latencies


def test_idle_connection_is_closed_without_an_answer(served: tuple[str, int, Path]) -> None:
    """A connection that sends nothing is closed after the header timeout, with nothing written to it."""
    _, port, _ = served
    with socket.create_connection(("127.0.0.1", port)) as s:
        answer, after_s = read_until_closed(s, HEADER_S + SLACK_S + 5)
    assert answer == b""
    assert HEADER_S - 0.2 < after_s < HEADER_S + SLACK_S


def test_oversized_header_is_431_and_the_server_keeps_serving(served: tuple[str, int, Path]) -> None:
    """A header over the limit is a 431 naming it, and the next client is served."""
    base, port, _ = served
    with socket.create_connection(("127.0.0.1", port)) as s:
        s.sendall(b"GET /healthz HTTP/1.1\r\nHost: 127.0.0.1\r\nX-Big: " + b"a" * (2 * MAX_HEADER_BYTES) + b"\r\n\r\n")
        answer, _ = read_until_closed(s, 10)
    assert answer.startswith(b"HTTP/1.1 431 "), answer[:200]
    assert b"request header over 16 KiB" in answer
    healthz_ms(base)


def test_a_body_answered_before_it_was_read_cannot_hold_the_connection(served: tuple[str, int, Path]) -> None:
    """An upload refused on its declared size (413) whose client keeps trickling the body is closed within the
    header timeout of the answer (each byte used to restart uvicorn's keep-alive timer)."""
    _, port, _ = served
    with socket.create_connection(("127.0.0.1", port)) as s:
        s.sendall(b"POST /recordings HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Length: 5000000\r\n\r\n")
        s.settimeout(5)
        answer = s.recv(4096)
        tic = time.monotonic()
        closed = False
        while not closed and time.monotonic() - tic < HEADER_S + SLACK_S + 3:
            try:
                s.send(b"\x89")
                s.settimeout(0.2)
                closed = s.recv(4096) == b""
            except TimeoutError:
                continue
            except OSError:
                closed = True
        after_s = time.monotonic() - tic
    assert answer.startswith(b"HTTP/1.1 413 "), answer[:200]
    assert closed and after_s < HEADER_S + SLACK_S


def test_a_header_under_the_limit_is_served(served: tuple[str, int, Path]) -> None:
    """A large but allowed header (12 KiB of cookies) is served as usual."""
    base, _, _ = served
    assert httpx.get(f"{base}/healthz", headers={"Cookie": "c=" + "a" * 12_000}).status_code == 200


def test_timeout_settings_are_checked() -> None:
    """A zero or negative timeout is refused naming the setting, never ignored; the middleware checks its own."""
    with pytest.raises(ValidationError, match="body_timeout_s"):
        Settings.from_env({"SLAMREPLAY_BODY_TIMEOUT_S": "0"})
    with pytest.raises(ValidationError, match="header_timeout_s"):
        Settings.from_env({"SLAMREPLAY_HEADER_TIMEOUT_S": "-1"})
    assert Settings.from_env({"SLAMREPLAY_MIN_BODY_RATE": "0"}).min_body_rate == 0
    with pytest.raises(ValueError, match="idle_s must be > 0"):
        BodyTimeout(lambda *a: None, idle_s=0)
