"""End to end: a real `slamreplay serve` process on a free loopback port; upload, run, poll, download, diff;
then a stop with jobs still queued, a restart, and every job finishes."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import httpx
import pytest
from conftest import write_tiny_recording
from patience import deadline as give_up_at

TOKEN = "e2e-token"


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        port: int = s.getsockname()[1]
        return port


@contextmanager
def server(data_dir: Path, log: Path) -> Iterator[httpx.Client]:
    """Run `slamreplay serve` with 2 workers and a token; yield a client once /healthz answers; stop it with SIGTERM."""
    port = free_port()
    cmd = [sys.executable, "-m", "slamreplay.api.cli", "serve", "--port", str(port), "--data-dir", str(data_dir),
           "--workers", "2", "--log-level", "warning"]
    env = {k: v for k, v in os.environ.items() if not k.startswith("SLAMREPLAY_")}
    env |= {"SLAMREPLAY_TOKEN": TOKEN, "PYTHONUNBUFFERED": "1"}
    with open(log, "ab") as out:
        proc = subprocess.Popen(cmd, stdout=out, stderr=subprocess.STDOUT, env=env)
    base = f"http://127.0.0.1:{port}"
    try:
        deadline = give_up_at(60)
        while True:
            assert proc.poll() is None, f"server exited with {proc.returncode}:\n{log.read_text()}"
            try:
                if httpx.get(f"{base}/healthz", timeout=1).status_code == 200:
                    break
            except httpx.TransportError:
                pass
            assert time.monotonic() < deadline, f"server did not come up:\n{log.read_text()}"
            time.sleep(0.2)
        with httpx.Client(base_url=base, headers={"Authorization": f"Bearer {TOKEN}"}, timeout=30) as client:
            yield client
    finally:
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(30)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
            raise AssertionError(f"server ignored SIGTERM:\n{log.read_text()}") from None


def wait_all(client: httpx.Client, job_ids: list[str], timeout_s: float = 120.0) -> dict[str, dict[str, Any]]:
    """Poll until every job has ended; their final states."""
    deadline = time.monotonic() + timeout_s
    done: dict[str, dict[str, Any]] = {}
    while len(done) < len(job_ids):
        assert time.monotonic() < deadline, f"jobs still not done: {set(job_ids) - set(done)}"
        for job_id in set(job_ids) - set(done):
            job = client.get(f"/jobs/{job_id}").json()
            assert 0.0 <= job["progress"] <= 1.0
            if job["status"] not in ("queued", "running"):
                done[job_id] = job
        time.sleep(0.2)
    return done


@pytest.mark.slow
def test_serve_run_diff_restart(tmp_path: Path) -> None:
    """Upload, run two jobs, download the .rrd, diff them; stop with jobs queued, restart, all jobs succeed."""
    recording = write_tiny_recording(tmp_path / "tiny.mcap")
    data = tmp_path / "data"
    data.mkdir()
    log = tmp_path / "server.log"
    with server(data, log) as client:
        assert client.get("/recordings", headers={"Authorization": "Bearer wrong"}).status_code == 401
        with open(recording, "rb") as f:
            r = client.post("/recordings", params={"filename": "tiny.mcap"}, content=f)
        assert r.status_code == 201, r.text
        rid = r.json()["id"]
        first = [client.post("/jobs", json={"recording_id": rid, "pipeline": "odometry", "seed": s}).json()["id"]
                 for s in (0, 1)]
        states = wait_all(client, first)
        assert {s["status"] for s in states.values()} == {"succeeded"}, states
        rrd = client.get(f"/jobs/{first[0]}/rrd")
        assert rrd.status_code == 200 and rrd.content == (data / "runs" / first[0] / "run.rrd").read_bytes()
        diff = client.get("/diff", params={"a": first[0], "b": first[1]}).json()
        assert diff["worse"] == [] and {"field": "seed", "a": 0, "b": 1} in diff["changes"]
        assert client.get("/diff.rrd", params={"a": first[0], "b": first[1]}).status_code == 200

        more = [client.post("/jobs", json={"recording_id": rid, "pipeline": "odometry", "seed": s}).json()["id"]
                for s in range(2, 6)]
        queued = [j["id"] for j in client.get("/jobs", params={"status": "queued"}).json()]
    assert queued, "the server was meant to stop while jobs were still queued"

    with server(data, log) as client:
        states = wait_all(client, first + more)
        assert {s["status"] for s in states.values()} == {"succeeded"}, states
        for job_id in more:
            assert (data / "runs" / job_id / "metrics.json").is_file()
        requeued = [s for s in states.values() if s["note"]]
        assert all(s["attempts"] == 2 and "re-queued" in s["note"] for s in requeued)
        prom = client.get("/metrics").text
        assert 'slamreplay_jobs{status="succeeded"} 6' in prom and "slamreplay_queue_length 0" in prom
    assert "Traceback" not in log.read_text(), log.read_text()
