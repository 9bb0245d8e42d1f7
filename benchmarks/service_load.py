"""Service load: many concurrent job submissions against a running `slamreplay serve` on loopback.

1. Starts `slamreplay serve` on a free loopback port over a temporary data directory (or
   uses ``--url`` of a server that is already running), and uploads one small simulated
   recording (landmarks, odometry, scans: a few hundred messages).
2. Submits ``--jobs`` odometry jobs at once from as many threads (seeds differ).
3. While the workers are busy, ``--pollers`` threads keep reading ``GET /jobs/{id}`` for random
   jobs and time each answer.
4. Reports: every job's final status, submission latency, p50/p95/p99 of ``GET /jobs/{id}``
   under load, wall time and jobs per minute.

Run: `.venv/bin/python benchmarks/service_load.py [--jobs 50] [--workers 2] [--url URL --token T]`.
"""

from __future__ import annotations

import argparse
import os
import random
import signal
import socket
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import httpx

from recorder.sim.landmarks import LandmarkSimConfig, simulate_landmarks


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port: int = s.getsockname()[1]
        return port


def start_server(data_dir: Path, workers: int) -> tuple[subprocess.Popen[bytes], str]:
    port = free_port()
    env = {k: v for k, v in os.environ.items() if not k.startswith("SLAMREPLAY_")}
    proc = subprocess.Popen([sys.executable, "-m", "api.cli", "serve", "--port", str(port), "--data-dir",
                             str(data_dir), "--workers", str(workers), "--log-level", "warning"], env=env)
    url = f"http://127.0.0.1:{port}"
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:
        try:
            if httpx.get(f"{url}/healthz", timeout=1).status_code == 200:
                return proc, url
        except httpx.TransportError:
            time.sleep(0.2)
    proc.kill()
    raise SystemExit("the server did not come up within 60 s")


def percentile(values: list[float], q: float) -> float:
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, round(q / 100 * (len(ordered) - 1)))]


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--jobs", type=int, default=50)
    p.add_argument("--workers", type=int, default=2, help="worker processes of the server this script starts")
    p.add_argument("--pollers", type=int, default=4, help="threads reading GET /jobs/{id} meanwhile")
    p.add_argument("--url", help="use this running server instead of starting one")
    p.add_argument("--token", default=os.environ.get("SLAMREPLAY_TOKEN"), help="bearer token of --url")
    args = p.parse_args()

    tmp = Path(tempfile.mkdtemp(prefix="slamreplay-load-"))
    recording = tmp / "small.mcap"
    simulate_landmarks(recording, LandmarkSimConfig(duration_s=20.0, landmarks=16, stationary_s=1.0), seed=1)
    proc = None
    if args.url:
        url = args.url.rstrip("/")
    else:
        (tmp / "data").mkdir()
        proc, url = start_server(tmp / "data", args.workers)
    headers = {"Authorization": f"Bearer {args.token}"} if args.token else {}
    try:
        with httpx.Client(base_url=url, headers=headers, timeout=60) as client:
            r = client.post("/recordings", params={"filename": recording.name}, content=recording.read_bytes())
            r.raise_for_status()
            rid = r.json()["id"]
            print(f"server {url}; recording {rid[:12]}: {r.json()['message_count']} messages, "
                  f"{recording.stat().st_size:,} bytes")

            def submit(seed: int) -> tuple[str, float]:
                tic = time.perf_counter()
                resp = client.post("/jobs", json={"recording_id": rid, "pipeline": "odometry", "seed": seed})
                resp.raise_for_status()
                return resp.json()["id"], time.perf_counter() - tic

            t0 = time.perf_counter()
            with ThreadPoolExecutor(args.jobs) as pool:
                submitted = list(pool.map(submit, range(args.jobs)))
            ids = [job_id for job_id, _ in submitted]
            submit_s = [s for _, s in submitted]

            done = threading.Event()
            latencies: list[float] = []
            lock = threading.Lock()

            def poll() -> None:
                rng = random.Random()
                while not done.is_set():
                    tic = time.perf_counter()
                    client.get(f"/jobs/{rng.choice(ids)}").raise_for_status()
                    with lock:
                        latencies.append(time.perf_counter() - tic)
                    time.sleep(0.01)

            pollers = [threading.Thread(target=poll) for _ in range(args.pollers)]
            for t in pollers:
                t.start()
            statuses: dict[str, str] = {}
            while len(statuses) < len(ids):
                for job in client.get("/jobs", params={"limit": 1000}).json():
                    if job["id"] in ids and job["status"] not in ("queued", "running"):
                        statuses[job["id"]] = job["status"]
                time.sleep(0.5)
            wall = time.perf_counter() - t0
            done.set()
            for t in pollers:
                t.join()
    finally:
        if proc is not None:
            proc.send_signal(signal.SIGTERM)
            proc.wait(30)

    counts = {s: list(statuses.values()).count(s) for s in sorted(set(statuses.values()))}
    ms = [x * 1e3 for x in latencies]
    print(f"{args.jobs} jobs submitted concurrently: all ended, {counts}")
    print(f"POST /jobs latency: median {statistics.median(submit_s) * 1e3:.1f} ms, max {max(submit_s) * 1e3:.1f} ms")
    print(f"GET /jobs/{{id}} while workers were busy: {len(ms)} requests, p50 {percentile(ms, 50):.1f} ms, "
          f"p95 {percentile(ms, 95):.1f} ms, p99 {percentile(ms, 99):.1f} ms")
    print(f"wall {wall:.1f} s from first submission to last job done: {args.jobs / wall * 60:.1f} jobs/min "
          f"({args.workers} workers, {os.cpu_count()} CPUs)")
    if counts != {"succeeded": args.jobs}:
        raise SystemExit(1)


if __name__ == "__main__":
    main()
