"""Service load and faults: a `slamreplay serve` on loopback holding many uploads and queued jobs.

1. Starts `slamreplay serve` on a free 127.0.0.1 port over a temporary data directory (or uses
   ``--url`` of a server already running; the kill phase is then skipped).
2. ``--uploads`` different small simulated recordings uploaded at once, one thread each; meanwhile
   ``--slow`` slow uploads (the body trickles in over seconds: not listed until complete) and
   ``--dropped`` uploads whose client goes away mid-body (never listed, no file left).
3. ``--jobs`` odometry jobs submitted at once (spread over the recordings, seeds differ), while
   ``--pollers`` threads time ``GET /jobs/{id}`` for random jobs and a thread samples the resident
   memory of the server process (and, apart, of its workers) every half second.
4. With ``--kill-at F`` (default 0.5): when a fraction F of the jobs has ended, the server is
   killed with SIGKILL mid-job and started again on the same data directory; polling goes on.
5. Checks, exit 1 when one fails: every job ends (succeeded, or failed/interrupted with a
   reason; none queued or running), no job lost (each id answers) or run twice (attempts 1,
   except the jobs running at the kill: re-queued once, attempts 2; each succeeded job's
   manifest names its own job id), p95 of ``GET /jobs/{id}`` while jobs run under ``--p95-ms``,
   every upload stored, no partial upload listed or left on disk.

Run: `.venv/bin/python benchmarks/service_load.py [--jobs 1000] [--uploads 200] [--workers 2]`.
Against 127.0.0.1 only; every thread and request count is bounded by the options.
"""

from __future__ import annotations

import argparse
import hashlib
import os
import random
import signal
import socket
import statistics
import sys
import tempfile
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any
from urllib.parse import urlparse

import httpx

sys.path.insert(0, str(Path(__file__).resolve().parent))
from crash_suite_service import alive, children, server

from slamreplay.recorder.sim.landmarks import LandmarkSimConfig, simulate_landmarks

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))  # patience: deadlines scaled by load
from patience import deadline as give_up_at


def percentile(values: list[float], q: float) -> float:
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, round(q / 100 * (len(ordered) - 1)))]


def rss_mib(pid: int) -> float:
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    except OSError:
        pass
    return 0.0


def make_recordings(out: Path, n: int) -> list[Path]:
    """``n`` different small recordings (landmarks, odometry, scans; seeds differ)."""
    cfg = LandmarkSimConfig(duration_s=10.0, landmarks=12, stationary_s=1.0)
    paths = []
    for seed in range(n):
        p = out / f"r{seed}.mcap"
        simulate_landmarks(p, cfg, seed=seed)
        paths.append(p)
    return paths


def dropped_upload(url: str, body: bytes) -> None:
    """Send the headers and half the body of an upload, then close the connection."""
    u = urlparse(url)
    with socket.create_connection((u.hostname or "127.0.0.1", u.port or 80), timeout=10) as s:
        s.sendall(f"POST /recordings?filename=dropped.mcap HTTP/1.1\r\nHost: {u.netloc}\r\n"
                  f"Content-Type: application/octet-stream\r\nContent-Length: {len(body)}\r\n\r\n".encode())
        s.sendall(body[: len(body) // 2])
        time.sleep(0.2)


class Sampler(threading.Thread):
    """Resident memory of the server process and of its workers, every ``period_s``."""

    def __init__(self, period_s: float = 0.5) -> None:
        super().__init__(daemon=True)
        self.pid: int | None = None
        self.samples: list[tuple[float, int, float, float]] = []  # (time, pid, server MiB, workers MiB)
        self.load: list[float] = []  # the machine's 1-minute load average
        self.period_s = period_s
        self.stop = threading.Event()

    def run(self) -> None:
        while not self.stop.wait(self.period_s):
            pid = self.pid
            self.load.append(os.getloadavg()[0])
            if pid is not None and (server_mib := rss_mib(pid)) > 0:
                self.samples.append((time.monotonic(), pid, server_mib, sum(rss_mib(c) for c in children(pid))))


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--jobs", type=int, default=1000)
    p.add_argument("--uploads", type=int, default=200, help="concurrent uploads of different recordings")
    p.add_argument("--slow", type=int, default=5, help="slow uploads during the concurrent ones")
    p.add_argument("--dropped", type=int, default=5, help="uploads whose client goes away mid-body")
    p.add_argument("--workers", type=int, default=2, help="worker processes of the server this script starts")
    p.add_argument("--pollers", type=int, default=4, help="threads timing GET /jobs/{id} meanwhile")
    p.add_argument("--poll-interval-s", type=float, default=0.05, help="pause of each poller between requests")
    p.add_argument("--idle-s", type=float, default=30.0, help="polling goes on this long after the last job, "
                                                              "the workers idle: the reference latency")
    p.add_argument("--kill-at", type=float, default=0.5, help="kill -9 the server when this fraction of jobs "
                                                             "has ended, then restart it (0: never)")
    p.add_argument("--p95-ms", type=float, default=50.0, help="the bound on p95 of GET /jobs/{id}")
    p.add_argument("--url", help="use this running server instead of starting one (no kill phase)")
    p.add_argument("--token", default=os.environ.get("SLAMREPLAY_TOKEN"), help="bearer token of --url")
    args = p.parse_args(argv)
    if min(args.jobs, args.uploads) < 1 or args.jobs > 5000 or args.uploads > 1000:
        p.error("--jobs 1..5000 and --uploads 1..1000")
    report = run(args)
    for line in report["lines"]:
        print(line)
    for problem in report["problems"]:
        print(f"PROBLEM: {problem}")
    return 1 if report["problems"] else 0


def run(args: argparse.Namespace) -> dict[str, Any]:
    """The whole load run; ``lines`` to print and ``problems`` found."""
    tmp = Path(tempfile.mkdtemp(prefix="slamreplay-load-"))
    recordings = make_recordings(tmp, args.uploads + args.slow + args.dropped)
    data = tmp / "data"
    data.mkdir()
    headers = {"Authorization": f"Bearer {args.token}"} if args.token else {}
    sampler = Sampler()
    sampler.start()
    out: dict[str, Any] = {"lines": [], "problems": []}
    lines, problems = out["lines"], out["problems"]
    idle = "with the workers idle, after every job ended (the machine's own share of the latency)"
    latencies: dict[str, list[float]] = {"before the kill": [], "after the restart": [], idle: []}
    phase = ["before the kill"]
    if args.url:
        import contextlib
        ctx: Any = contextlib.nullcontext((None, httpx.Client(base_url=args.url.rstrip("/"), headers=headers)))
    else:
        ctx = server(data, tmp / "server.log", args.workers)
    limits = httpx.Limits(max_connections=args.uploads + 20, max_keepalive_connections=args.uploads + 20)
    with ctx as (proc, client0):
        url = str(client0.base_url).rstrip("/")
        sampler.pid = proc.pid if proc is not None else None
        client = httpx.Client(base_url=url, headers=headers, timeout=120, limits=limits)

        # -- uploads: concurrent, slow, dropped ---------------------------------------------------
        bodies = [r.read_bytes() for r in recordings]
        normal, slow, dropped = (bodies[:args.uploads], bodies[args.uploads:args.uploads + args.slow],
                                 bodies[args.uploads + args.slow:])
        listed_mid: list[bool] = []  # whether a slow upload was listed half-way through its own body

        def upload(body: bytes) -> tuple[int, float]:
            tic = time.perf_counter()
            r = client.post("/recordings", content=body)
            return r.status_code, time.perf_counter() - tic

        def slow_upload(body: bytes) -> int:
            own = hashlib.sha256(body).hexdigest()

            def chunks() -> Any:
                step = max(len(body) // 20, 1)
                for i in range(0, len(body), step):
                    yield body[i:i + step]
                    time.sleep(0.15)
                    if i == step * 10:  # half-way: it must not be listed yet
                        listed_mid.append(own in {r["id"] for r in client.get("/recordings").json()})
            return client.post("/recordings", content=chunks(), headers={"Content-Length": str(len(body))}
                               ).status_code

        t0 = time.perf_counter()
        with ThreadPoolExecutor(args.uploads + args.slow + args.dropped) as pool:
            slow_f = [pool.submit(slow_upload, b) for b in slow]
            drop_f = [pool.submit(dropped_upload, url, b) for b in dropped]
            answers = list(pool.map(upload, normal))
            slow_codes = [f.result() for f in slow_f]
            for f in drop_f:
                f.result()
        upload_wall = time.perf_counter() - t0
        codes = [c for c, _ in answers]
        if codes.count(201) != len(normal):
            problems.append(f"concurrent uploads answered {sorted(set(codes))}, not all 201")
        if slow_codes.count(201) != len(slow):
            problems.append(f"slow uploads answered {slow_codes}")
        slow_ids = {hashlib.sha256(b).hexdigest() for b in slow}
        if any(listed_mid):
            problems.append("a slow upload was listed before it was complete")
        time.sleep(0.5)
        listed = {r["id"] for r in client.get("/recordings").json()}
        want = {hashlib.sha256(b).hexdigest() for b in normal} | slow_ids
        if listed != want:
            problems.append(f"{len(listed)} recordings listed, {len(want)} uploaded whole "
                            f"({len({hashlib.sha256(b).hexdigest() for b in dropped} & listed)} dropped ones listed)")
        left = [f.name for f in (data / "recordings").iterdir() if f.name.startswith(".")] if not args.url else []
        if left:
            problems.append(f"partial uploads left on disk: {left}")
        up_s = [s for _, s in answers]
        lines.append(f"{len(normal)} concurrent uploads of different recordings ({len(normal[0]):,} bytes each): "
                     f"{codes.count(201)} stored in {upload_wall:.1f} s, latency median "
                     f"{statistics.median(up_s) * 1e3:.0f} ms, max {max(up_s) * 1e3:.0f} ms; {len(slow)} slow "
                     f"uploads stored and not listed half-way; {len(dropped)} dropped uploads: none listed, "
                     f"{len(left)} files left")

        # -- jobs ------------------------------------------------------------------------------
        rids = sorted(want)

        def submit(i: int) -> tuple[str, float]:
            tic = time.perf_counter()
            r = client.post("/jobs", json={"recording_id": rids[i % len(rids)], "pipeline": "odometry", "seed": i})
            r.raise_for_status()
            return r.json()["id"], time.perf_counter() - tic

        t0 = time.perf_counter()
        with ThreadPoolExecutor(50) as pool:
            submitted = list(pool.map(submit, range(args.jobs)))
        ids = [j for j, _ in submitted]
        submit_s = [s for _, s in submitted]
        lines.append(f"{args.jobs} jobs submitted from 50 threads in {time.perf_counter() - t0:.1f} s "
                     f"(POST /jobs median {statistics.median(submit_s) * 1e3:.0f} ms, "
                     f"p95 {percentile(submit_s, 95) * 1e3:.0f} ms)")

        done = threading.Event()
        lock = threading.Lock()
        base = [url]

        def poll() -> None:
            rng = random.Random()
            with httpx.Client(headers=headers, timeout=30) as c:
                while not done.is_set():
                    tic = time.perf_counter()
                    try:
                        ok = c.get(f"{base[0]}/jobs/{rng.choice(ids)}").status_code == 200
                    except httpx.TransportError:
                        ok = False  # the server is down between the kill and the restart
                    if ok:
                        with lock:
                            latencies[phase[0]].append(time.perf_counter() - tic)
                    else:
                        time.sleep(0.2)
                    time.sleep(args.poll_interval_s)

        pollers = [threading.Thread(target=poll) for _ in range(args.pollers)]
        for t in pollers:
            t.start()
        t_jobs = time.perf_counter()
        running_at_kill: set[str] = set()
        killed = False

        def active(c: httpx.Client) -> int:
            """Jobs queued or running, from /metrics (cheap: listing 1000 jobs would load the server itself)."""
            n = 0
            for line in c.get("/metrics").text.splitlines():
                if line.startswith(('slamreplay_jobs{status="queued"}', 'slamreplay_jobs{status="running"}')):
                    n += int(float(line.split()[-1]))
            return n

        restart_ctx = None
        cur = client
        try:
            deadline = time.monotonic() + 3600
            while time.monotonic() < deadline:
                ended = len(ids) - active(cur)
                if ended >= len(ids):
                    break
                if (not killed and args.kill_at > 0 and proc is not None
                        and ended >= args.kill_at * len(ids)):
                    running_at_kill = {j["id"] for j in cur.get("/jobs", params={"status": "running"}).json()}
                    workers = children(proc.pid)
                    os.kill(proc.pid, signal.SIGKILL)
                    proc.wait()
                    t_kill = time.perf_counter()
                    phase[0] = "after the restart"
                    gone = give_up_at(5)
                    while any(alive(w) for w in workers) and time.monotonic() < gone:
                        time.sleep(0.1)
                    if any(alive(w) for w in workers):
                        problems.append("worker processes outlived the killed server by 5 s")
                    restart_ctx = server(data, tmp / "server.log", args.workers)
                    proc, c2 = restart_ctx.__enter__()
                    sampler.pid = proc.pid
                    base[0] = str(c2.base_url).rstrip("/")
                    cur = httpx.Client(base_url=base[0], headers=headers, timeout=120)
                    lines.append(f"server killed (SIGKILL) after {ended} jobs had ended, "
                                 f"{len(running_at_kill)} running; restarted in {time.perf_counter() - t_kill:.1f} s")
                    killed = True
                    continue
                time.sleep(1.0)
            wall = time.perf_counter() - t_jobs
            phase[0] = idle
            time.sleep(args.idle_s)
            done.set()
            for t in pollers:
                t.join()
            final = {j: cur.get(f"/jobs/{j}").json() for j in ids}
        finally:
            done.set()
            if restart_ctx is not None:
                restart_ctx.__exit__(None, None, None)
        sampler.stop.set()

    # -- verdicts ---------------------------------------------------------------------------------
    counts: dict[str, int] = {}
    for job in final.values():
        counts[job.get("status", "lost")] = counts.get(job.get("status", "lost"), 0) + 1
    stuck = [j for j, job in final.items() if job.get("status") in ("queued", "running", None)]
    if stuck:
        problems.append(f"{len(stuck)} jobs did not end: {stuck[:3]}")
    unexplained = [j for j, job in final.items() if job.get("status") not in ("succeeded", None) and not job["error"]]
    if unexplained:
        problems.append(f"{len(unexplained)} jobs failed without a reason")
    twice = [j for j, job in final.items() if job.get("attempts", 0) > (2 if j in running_at_kill else 1)]
    if twice:
        problems.append(f"{len(twice)} jobs ran more often than they should: {twice[:3]}")
    if not args.url:
        wrong = [j for j, job in final.items() if job.get("status") == "succeeded"
                 and (job.get("manifest") or {}).get("run_id") != j]
        if wrong:
            problems.append(f"{len(wrong)} succeeded jobs whose manifest names another run")
    requeued = sum(1 for j in running_at_kill if final[j].get("attempts") == 2)
    lines.append(f"{args.jobs} jobs ended: {counts}; none lost, none stuck; attempts 1 for every job but the "
                 f"{len(running_at_kill)} running at the kill ({requeued} re-queued and run again); wall {wall:.0f} s, "
                 f"{args.jobs / wall * 60:.0f} jobs/min ({args.workers} workers, {os.cpu_count()} CPUs)")
    for name, lat in latencies.items():
        if lat:
            ms = [x * 1e3 for x in lat]
            lines.append(f"GET /jobs/{{id}} {name}{', workers busy' if name != idle else ''} ({args.pollers} pollers, "
                         f"{args.poll_interval_s * 1e3:.0f} ms pause each; machine load average "
                         f"{statistics.median(sampler.load) if sampler.load else 0:.1f} on {os.cpu_count()} CPUs): "
                         f"{len(ms)} requests, p50 {percentile(ms, 50):.1f} ms, "
                         f"p95 {percentile(ms, 95):.1f} ms, p99 {percentile(ms, 99):.1f} ms")
            if percentile(ms, 95) > args.p95_ms and name != idle:
                problems.append(f"p95 of GET /jobs/{{id}} {name}: {percentile(ms, 95):.1f} ms > {args.p95_ms} ms")
    for pid in dict.fromkeys(s[1] for s in sampler.samples):
        ss = [s for s in sampler.samples if s[1] == pid]
        if len(ss) < 4:
            continue
        q = len(ss) // 4
        first, last = statistics.median(s[2] for s in ss[q:2 * q]), statistics.median(s[2] for s in ss[-q:])
        lines.append(f"server RSS (pid {pid}, {len(ss)} samples): {ss[0][2]:.0f} MiB at the first sample, "
                     f"median {first:.0f} MiB in the 2nd quarter, {last:.0f} MiB in the last, max "
                     f"{max(s[2] for s in ss):.0f} MiB; its workers together: median "
                     f"{statistics.median(s[3] for s in ss[q:2 * q]):.0f} MiB in the 2nd quarter, "
                     f"{statistics.median(s[3] for s in ss[-q:]):.0f} MiB in the last, "
                     f"max {max(s[3] for s in ss):.0f} MiB")
        if last > first * 1.25 + 20:
            problems.append(f"server RSS grew from {first:.0f} to {last:.0f} MiB")
    return out


if __name__ == "__main__":
    sys.exit(main())
