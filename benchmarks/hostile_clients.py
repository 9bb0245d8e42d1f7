"""Hostile clients against a `slamreplay serve` on loopback: what they hold, and what others still get.

Starts `slamreplay serve` on a free 127.0.0.1 port over a temporary data directory (``--env NAME=VALUE``
passes settings to it, e.g. shorter timeouts), then runs each scenario for ``--hold-s`` seconds:

- ``slowloris``: ``--slowloris`` connections each sending one byte of an endless header every 2 s;
- ``idle``: ``--idle`` connections that connect and send nothing;
- ``stalled-upload``: ``--stalled`` form uploads (POST /recordings, multipart) that send half their
  body and stop;
- ``big-header``: ``--big-headers`` requests, one after another, whose header is 1 MB;
- ``trickle-body``: ``--trickle`` raw uploads whose body comes one byte per second.

Meanwhile a well-behaved client times GET /healthz, GET / and GET /recordings (a new connection for
each) and, every 2.5 s, the upload of a small recording. At the end of each scenario it records
how many of the hostile connections the server has closed (and what it answered them), the
server's open sockets, the ``.upload-*.partial`` files in the data directory's recordings folder and
the server's resident memory; then the hostile clients hang up and the same is read again after a
second. ``none`` is the reference: the well-behaved client alone.

Run: `.venv/bin/python benchmarks/hostile_clients.py [--hold-s 10] [--json hostile.json]`. Against
127.0.0.1 only; at most 500 connections at once and about a minute in all with the defaults.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import os
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Coroutine
from pathlib import Path
from typing import Any

import httpx

sys.path.insert(0, str(Path(__file__).resolve().parent))
from crash_suite_service import server

from slamreplay.recorder.sim.landmarks import LandmarkSimConfig, simulate_landmarks

BIG_HEADER_BYTES = 1 << 20
MAX_CONNECTIONS = 500  # the script's own bound, whatever the options say


def percentile(values: list[float], q: float) -> float:
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, round(q / 100 * (len(ordered) - 1)))] if ordered else float("nan")


def rss_mib(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return 0.0


def open_sockets(pid: int) -> int:
    """Sockets the server process holds (the listening one included)."""
    n = 0
    for fd in Path(f"/proc/{pid}/fd").iterdir():
        with contextlib.suppress(OSError):  # closed since the listing
            n += os.readlink(fd).startswith("socket:")
    return n


def partial_files(data: Path) -> list[Path]:
    return sorted((data / "recordings").glob(".upload-*.partial"))


# -- hostile clients (asyncio, in one background thread) ---------------------------------------------


class Hostile:
    """One hostile connection: its answer's status line and when the server closed it."""

    def __init__(self) -> None:
        self.opened = time.monotonic()
        self.closed_after_s: float | None = None
        self.status: str | None = None
        self.error: str | None = None


async def _watch(reader: asyncio.StreamReader, conn: Hostile) -> None:
    """Read what the server sends until it closes the connection."""
    data = b""
    try:
        while chunk := await reader.read(65536):
            data += chunk
    except OSError as err:
        conn.error = type(err).__name__
    if data:
        conn.status = data.split(b"\r\n", 1)[0].decode("latin-1")[9:12]
    conn.closed_after_s = time.monotonic() - conn.opened


async def _connection(host: str, port: int, conn: Hostile, stop: asyncio.Event,
                      send: Callable[[asyncio.StreamWriter, Hostile], Coroutine[Any, Any, None]]) -> None:
    try:
        reader, writer = await asyncio.open_connection(host, port)
    except OSError as err:
        conn.error, conn.closed_after_s = f"connect: {type(err).__name__}", 0.0
        return
    watch = asyncio.create_task(_watch(reader, conn))
    sender = asyncio.create_task(send(writer, conn))
    await asyncio.wait([watch, asyncio.create_task(stop.wait())], return_when=asyncio.FIRST_COMPLETED)
    sender.cancel()
    writer.close()
    await asyncio.gather(watch, sender, return_exceptions=True)


def slowloris(host: str) -> Callable[[asyncio.StreamWriter, Hostile], Coroutine[Any, Any, None]]:
    head = f"GET / HTTP/1.1\r\nHost: {host}\r\nX-Slow: ".encode()

    async def send(w: asyncio.StreamWriter, conn: Hostile) -> None:
        i = 0
        while True:  # one byte every 2 s, the header never ends
            w.write(head[i:i + 1] if i < len(head) else b"a")
            await w.drain()
            i += 1
            await asyncio.sleep(2.0)
    return send


async def idle(w: asyncio.StreamWriter, conn: Hostile) -> None:
    await asyncio.Event().wait()


def stalled_upload(host: str, size: int) -> Callable[[asyncio.StreamWriter, Hostile], Coroutine[Any, Any, None]]:
    boundary = "hostile0boundary"
    prologue = (f'--{boundary}\r\nContent-Disposition: form-data; name="file"; filename="stall.mcap"\r\n'
                f"Content-Type: application/octet-stream\r\n\r\n").encode()
    body = prologue + os.urandom(size) + f"\r\n--{boundary}--\r\n".encode()

    async def send(w: asyncio.StreamWriter, conn: Hostile) -> None:
        w.write(f"POST /recordings HTTP/1.1\r\nHost: {host}\r\nContent-Type: multipart/form-data; "
                f"boundary={boundary}\r\nContent-Length: {len(body)}\r\n\r\n".encode())
        w.write(body[:len(body) // 2])
        await w.drain()
        await asyncio.Event().wait()  # and nothing more
    return send


def big_header(host: str) -> Callable[[asyncio.StreamWriter, Hostile], Coroutine[Any, Any, None]]:
    async def send(w: asyncio.StreamWriter, conn: Hostile) -> None:
        w.write(f"GET /healthz HTTP/1.1\r\nHost: {host}\r\nX-Big: ".encode())
        block = b"a" * 65536
        try:
            for _ in range(BIG_HEADER_BYTES // len(block)):
                w.write(block)
                await w.drain()
            w.write(b"\r\n\r\n")
            await w.drain()
        except OSError as err:  # the server answered and closed before all of it was sent
            conn.error = conn.error or type(err).__name__
        await asyncio.Event().wait()
    return send


def trickle_body(host: str) -> Callable[[asyncio.StreamWriter, Hostile], Coroutine[Any, Any, None]]:
    async def send(w: asyncio.StreamWriter, conn: Hostile) -> None:
        w.write(f"POST /recordings?filename=trickle.mcap HTTP/1.1\r\nHost: {host}\r\n"
                f"Content-Type: application/octet-stream\r\nContent-Length: 100000\r\n\r\n".encode())
        while True:
            w.write(b"\x89")
            await w.drain()
            await asyncio.sleep(1.0)
    return send


async def _hostile(host: str, port: int, kind: str, n: int, conns: list[Hostile], release: threading.Event,
                   upload_bytes: int) -> None:
    stop = asyncio.Event()
    name = f"127.0.0.1:{port}"
    senders = {"slowloris": slowloris(name), "idle": idle, "stalled-upload": stalled_upload(name, upload_bytes),
               "big-header": big_header(name), "trickle-body": trickle_body(name)}
    tasks = []
    if kind == "big-header":  # one after another, each to its answer (or a 5 s wait)
        async def serial() -> None:
            for _ in range(n):
                c = Hostile()
                conns.append(c)
                one = asyncio.Event()
                t = asyncio.create_task(_connection(host, port, c, one, senders[kind]))
                deadline = time.monotonic() + 5
                while c.closed_after_s is None and time.monotonic() < deadline:
                    await asyncio.sleep(0.05)
                one.set()
                await t
        tasks.append(asyncio.create_task(serial()))
    else:
        for _ in range(n):
            c = Hostile()
            conns.append(c)
            tasks.append(asyncio.create_task(_connection(host, port, c, stop, senders[kind])))
            await asyncio.sleep(0.002)  # a burst, but not one the kernel's accept queue has to absorb at once
    await asyncio.get_running_loop().run_in_executor(None, release.wait)
    stop.set()
    await asyncio.gather(*tasks, return_exceptions=True)


# -- the well-behaved client ----------------------------------------------------------------------------------


def probe(client: httpx.Client, until: float, recordings: list[bytes], out: dict[str, list[float]],
          errors: list[str]) -> None:
    """Time GET /healthz, /, /recordings (a new connection each) and an upload every 2.5 s until ``until``."""
    next_upload = time.monotonic()
    while time.monotonic() < until:
        paths = ["/healthz", "/", "/recordings"]
        for path in paths:
            tic = time.perf_counter()
            try:
                r = client.get(path)
                if r.status_code != 200:
                    errors.append(f"GET {path}: {r.status_code}")
                else:
                    out[path].append(time.perf_counter() - tic)
            except httpx.HTTPError as err:
                errors.append(f"GET {path}: {type(err).__name__}")
        if time.monotonic() >= next_upload and recordings:
            body = recordings.pop()
            tic = time.perf_counter()
            try:
                r = client.post("/recordings", content=body, params={"filename": "probe.mcap"})
                if r.status_code not in (200, 201):
                    errors.append(f"upload: {r.status_code}")
                else:
                    out["upload"].append(time.perf_counter() - tic)
            except httpx.HTTPError as err:
                errors.append(f"upload: {type(err).__name__}")
            next_upload += 2.5
        time.sleep(0.1)


def held(pid: int, data: Path, base_sockets: int) -> dict[str, Any]:
    return {"server_sockets": open_sockets(pid) - base_sockets, "partial_files": len(partial_files(data)),
            "partial_bytes": sum(p.stat().st_size for p in partial_files(data) if p.exists()),
            "rss_mib": round(rss_mib(pid), 1)}


def scenario(kind: str, n: int, args: argparse.Namespace, pid: int, base: str, data: Path,
             recordings: list[bytes]) -> dict[str, Any]:
    """Run one scenario; its figures."""
    port = int(base.rsplit(":", 1)[1])
    conns: list[Hostile] = []
    release = threading.Event()
    base_sockets = open_sockets(pid)
    before = held(pid, data, base_sockets)
    thread = None
    if kind != "none":
        thread = threading.Thread(target=lambda: asyncio.run(_hostile(
            "127.0.0.1", port, kind, n, conns, release, args.upload_bytes)), daemon=True)
        thread.start()
    lat: dict[str, list[float]] = {"/healthz": [], "/": [], "/recordings": [], "upload": []}
    errors: list[str] = []
    t0 = time.monotonic()
    with httpx.Client(base_url=base, timeout=30, limits=httpx.Limits(max_keepalive_connections=0)) as client:
        probe(client, t0 + args.hold_s, recordings, lat, errors)
    during = held(pid, data, base_sockets)
    closed = [c for c in conns if c.closed_after_s is not None]
    release.set()
    if thread is not None:
        thread.join(30)
    time.sleep(1.0)
    after = held(pid, data, base_sockets)
    statuses: dict[str, int] = {}
    for c in closed:
        key = c.status or ("closed" if c.error is None else c.error)
        statuses[key] = statuses.get(key, 0) + 1
    return {
        "scenario": kind, "connections": len(conns), "hold_s": args.hold_s,
        "latency_ms": {k: {"n": len(v), "p50": round(percentile(v, 50) * 1e3, 1),
                           "p95": round(percentile(v, 95) * 1e3, 1)} for k, v in lat.items()},
        "probe_errors": errors[:10], "probe_error_count": len(errors),
        "closed_by_server": len(closed),
        "closed_after_s_max": round(max((c.closed_after_s or 0) for c in closed), 1) if closed else None,
        "answers": statuses, "before": before, "at_end_of_hold": during, "after_hang_up": after,
    }


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--hold-s", type=float, default=10.0, help="how long each scenario lasts (default 10)")
    p.add_argument("--slowloris", type=int, default=200)
    p.add_argument("--idle", type=int, default=500)
    p.add_argument("--stalled", type=int, default=10, help="stalled form uploads")
    p.add_argument("--upload-bytes", type=int, default=1 << 20, help="file size of each stalled upload")
    p.add_argument("--big-headers", type=int, default=5)
    p.add_argument("--trickle", type=int, default=20, help="uploads trickling one byte a second")
    p.add_argument("--only", help="comma-separated scenarios to run (default: all)")
    p.add_argument("--env", action="append", default=[], metavar="NAME=VALUE", help="a setting of the server")
    p.add_argument("--json", type=Path, help="write the figures here")
    args = p.parse_args(argv)
    counts = {"none": 0, "slowloris": args.slowloris, "idle": args.idle, "stalled-upload": args.stalled,
              "big-header": args.big_headers, "trickle-body": args.trickle}
    if max(counts.values()) > MAX_CONNECTIONS or not 1 <= args.hold_s <= 60:
        p.error(f"at most {MAX_CONNECTIONS} connections per scenario and --hold-s 1..60")
    if args.only:
        counts = {k: v for k, v in counts.items() if k in {"none", *args.only.split(",")}}
    env = dict(e.split("=", 1) for e in args.env)
    tmp = Path(tempfile.mkdtemp(prefix="slamreplay-hostile-"))
    cfg = LandmarkSimConfig(duration_s=10.0, landmarks=12, stationary_s=1.0)
    recordings = []
    for seed in range(len(counts) * (int(args.hold_s / 2.5) + 2)):
        simulate_landmarks(tmp / f"r{seed}.mcap", cfg, seed=seed)
        recordings.append((tmp / f"r{seed}.mcap").read_bytes())
    data = tmp / "data"
    results = []
    with server(data, tmp / "server.log", 1, env) as (proc, client):
        base = str(client.base_url).rstrip("/")
        for kind, n in counts.items():
            results.append(scenario(kind, n, args, proc.pid, base, data, recordings))
    print(f"{'scenario':<15} {'conns':>5} {'healthz p50/p95 ms':>19} {'GET / p50/p95':>14} "
          f"{'upload p50/p95':>15} {'errs':>4} {'closed':>6} {'max s':>5} {'answers':<22} "
          f"{'held at end: socks/partials/RSS MiB':>36} {'after hang-up':>22}")
    for r in results:
        lat = r["latency_ms"]
        d, a = r["at_end_of_hold"], r["after_hang_up"]
        up, closed_max = lat["upload"], "-" if r["closed_after_s_max"] is None else r["closed_after_s_max"]
        print(f"{r['scenario']:<15} {r['connections']:>5} "
              f"{lat['/healthz']['p50']:>9.1f}/{lat['/healthz']['p95']:<9.1f} "
              f"{lat['/']['p50']:>6.1f}/{lat['/']['p95']:<7.1f} {up['p50']:>7.1f}/{up['p95']:<7.1f} "
              f"{r['probe_error_count']:>4} {r['closed_by_server']:>6} {closed_max:>5} "
              f"{json.dumps(r['answers']):<22} {d['server_sockets']:>14}/{d['partial_files']}/{d['rss_mib']:<10} "
              f"{a['server_sockets']:>10}/{a['partial_files']}/{a['rss_mib']}")
    if args.json:
        args.json.write_text(json.dumps({"env": env, "hold_s": args.hold_s, "cpus": os.cpu_count(),
                                         "load_average": os.getloadavg()[0], "scenarios": results}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
