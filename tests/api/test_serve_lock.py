"""Real `slamreplay serve` processes on one data directory: a second server exits 2 on one line naming the first
and leaves its running job alone; after kill -9 of the first (its worker still alive, stopped) a new server
waits for that worker to end, then takes the directory over; a port in use is one line and exit 2."""

from __future__ import annotations

import asyncio
import json
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import httpx
import pytest
from patience import deadline as give_up_at

from slamreplay.api.cli.command import main
from slamreplay.api.cli.listen import listen
from slamreplay.api.service.datalock import LOCK_NAME, DataDirLock

SERVE = [sys.executable, "-m", "slamreplay.api.cli", "serve", "--workers", "1", "--log-level", "warning"]
ENV = {k: v for k, v in os.environ.items() if not k.startswith("SLAMREPLAY_")} | {"PYTHONUNBUFFERED": "1"}


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port: int = s.getsockname()[1]
        return port


def start(data: Path, log: Path) -> tuple[subprocess.Popen[bytes], str]:
    """`slamreplay serve` over ``data`` on a free port; (process, base URL) once /healthz answers."""
    port = free_port()
    with open(log, "ab") as out:
        proc = subprocess.Popen([*SERVE, "--port", str(port), "--data-dir", str(data)], stdout=out,
                                stderr=subprocess.STDOUT, env=ENV)
    base = f"http://127.0.0.1:{port}"
    deadline = give_up_at(60)
    while True:
        assert proc.poll() is None, f"server exited with {proc.returncode}:\n{log.read_text()}"
        try:
            if httpx.get(f"{base}/healthz", timeout=1).status_code == 200:
                return proc, base
        except httpx.TransportError:
            pass
        assert time.monotonic() < deadline, f"server did not come up:\n{log.read_text()}"
        time.sleep(0.1)


def stop(proc: subprocess.Popen[bytes]) -> None:
    if proc.poll() is None:
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(30)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


def running_job(base: str, recording: Path) -> str:
    """Upload ``recording``, submit a long ekfslam job and wait until a worker has started it."""
    rid = httpx.post(f"{base}/recordings", content=recording.read_bytes(), timeout=60).json()["id"]
    job_id = str(httpx.post(f"{base}/jobs", json={"recording_id": rid, "pipeline": "ekfslam"}).json()["id"])
    deadline = give_up_at(180)  # a worker process's start-up: 60 s was exceeded at a load average of 10
    while (job := httpx.get(f"{base}/jobs/{job_id}").json())["progress"] <= 0:
        assert job["status"] in ("queued", "running") and time.monotonic() < deadline, job
        time.sleep(0.1)
    return job_id


def job(base: str, job_id: str) -> dict[str, Any]:
    answer: dict[str, Any] = httpx.get(f"{base}/jobs/{job_id}").json()
    return answer


def workers_of(pid: int) -> list[int]:
    """The spawned worker processes (children running multiprocessing's spawn_main) of ``pid``."""
    found = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            ppid = int((entry / "stat").read_text().rsplit(")", 1)[1].split()[1])
            cmdline = (entry / "cmdline").read_bytes()
        except (OSError, IndexError, ValueError):
            continue
        if ppid == pid and b"spawn_main" in cmdline:
            found.append(int(entry.name))
    return found


def alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state != "Z"


@pytest.fixture(scope="module")
def recording(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """400 s of sim-landmarks: ekfslam over it takes several seconds (a job still running while we look)."""
    path = tmp_path_factory.mktemp("rec") / "long.mcap"
    assert main(["record", "sim-landmarks", "--duration-s", "400", "--seed", "1", "--out", str(path), "-q"]) == 0
    return path


@pytest.mark.slow
def test_second_server_on_a_data_dir_in_use_exits_2_naming_the_first(tmp_path: Path, recording: Path) -> None:
    """A second server on the same --data-dir prints one line naming the first (pid, address) and exits 2
    without announcing itself; the first one's running job is untouched (running, attempts 1, no note).
    Another server on the first one's port says the port is in use."""
    data = tmp_path / "data"
    first, base = start(data, tmp_path / "first.log")
    try:
        job_id = running_job(base, recording)
        t0 = time.monotonic()
        second = subprocess.run([*SERVE, "--port", str(free_port()), "--data-dir", str(data)], capture_output=True,
                                text=True, env=ENV, timeout=60)
        took = time.monotonic() - t0
        assert second.returncode == 2 and second.stdout == ""
        assert second.stderr.count("\n") == 1, second.stderr
        assert second.stderr.startswith(f"slamreplay: error: the data directory {data.resolve()} is in use by the "
                                        f"server pid {first.pid} at {base} (started ")
        assert second.stderr.rstrip().endswith("stop it or pass another --data-dir")
        assert took < 30
        after = job(base, job_id)
        assert (after["status"], after["attempts"], after["note"]) == ("running", 1, None)
        assert json.loads((data / LOCK_NAME).read_text())["pid"] == first.pid
        port = base.rsplit(":", 1)[1]
        other = subprocess.run([*SERVE, "--port", port, "--data-dir", str(tmp_path / "other")], capture_output=True,
                               text=True, env=ENV, timeout=60)
        assert (other.returncode, other.stdout) == (2, "")
        assert other.stderr == (f"slamreplay: error: port {port} on 127.0.0.1 is in use (another server?): "
                                "pass --port N\n")
        assert job(base, job_id)["attempts"] == 1
    finally:
        stop(first)


@pytest.mark.slow
def test_killed_server_is_taken_over_once_its_workers_are_gone(tmp_path: Path, recording: Path) -> None:
    """kill -9 of the server while its worker runs a job (the worker stopped, so it outlives the server): a new
    server does not take the directory while that worker lives, then takes it once the worker has ended,
    rewrites the lock with its own pid and address, re-queues the job once, and the job succeeds."""
    data = tmp_path / "data"
    first, base = start(data, tmp_path / "first.log")
    try:
        job_id = running_job(base, recording)
        workers = workers_of(first.pid)
        assert workers
        for w in workers:
            os.kill(w, signal.SIGSTOP)  # an orphan that cannot notice its server's death yet
        first.kill()
        first.wait()
    finally:
        stop(first)
    log = tmp_path / "second.log"
    port = free_port()
    with open(log, "ab") as out:
        second = subprocess.Popen([*SERVE, "--port", str(port), "--data-dir", str(data)], stdout=out,
                                  stderr=subprocess.STDOUT, env=ENV)
    try:
        time.sleep(2.0)
        assert second.poll() is None and "slamreplay serve:" not in log.read_text()  # waiting for the lock
        assert json.loads((data / LOCK_NAME).read_text())["pid"] == first.pid
        for w in workers:
            os.kill(w, signal.SIGCONT)  # it sees its server gone and exits
        base2 = f"http://127.0.0.1:{port}"
        deadline = give_up_at(60)
        while True:
            owner = json.loads((data / LOCK_NAME).read_text() or "{}")
            if owner.get("pid") == second.pid:
                assert not any(alive(w) for w in workers), "the lock changed hands while a worker of the old server ran"
                break
            assert second.poll() is None and time.monotonic() < deadline, log.read_text()
            time.sleep(0.05)
        assert owner["address"] == base2
        deadline = give_up_at(120)
        while (end := job(base2, job_id) if _up(base2) else {"status": "starting"})["status"] in (
                "starting", "queued", "running"):
            assert time.monotonic() < deadline, end
            time.sleep(0.2)
        assert (end["status"], end["attempts"]) == ("succeeded", 2) and "re-queued" in end["note"]
    finally:
        stop(second)
        for w in workers:
            if alive(w):
                os.kill(w, signal.SIGKILL)
    lock = DataDirLock(data)
    lock.acquire(wait_s=0)  # a stopped server leaves the directory free
    lock.release()


def _up(base: str) -> bool:
    try:
        return httpx.get(f"{base}/healthz", timeout=1).status_code == 200
    except httpx.TransportError:
        return False


def test_port_in_use_is_one_line_before_the_announcement(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """`serve` on a port something listens on: exit 2, one line, no announcement, the data directory let go."""
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        assert main(["serve", "--port", str(port), "--data-dir", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert err == f"slamreplay: error: port {port} on 127.0.0.1 is in use (another server?): pass --port N\n"
    lock = DataDirLock(tmp_path)
    lock.acquire(wait_s=0)
    lock.release()


def test_listening_socket_gives_connections_without_nagle_delay() -> None:
    """Connections accepted on the socket `serve` hands to uvicorn get TCP_NODELAY from asyncio, as uvicorn's own
    sockets do (without it every answer waited about 40 ms for a delayed ACK)."""
    sock = listen("127.0.0.1", 0)
    nodelay: list[int] = []

    class Probe(asyncio.Protocol):
        def connection_made(self, transport: asyncio.BaseTransport) -> None:
            nodelay.append(transport.get_extra_info("socket").getsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY))

    async def connect_once() -> None:
        server = await asyncio.get_running_loop().create_server(Probe, sock=sock)
        async with server:
            _, writer = await asyncio.open_connection(*sock.getsockname()[:2])
            for _ in range(100):
                if nodelay:
                    break
                await asyncio.sleep(0.01)
            writer.close()

    asyncio.run(connect_once())
    assert nodelay == [1]
