"""The runs table with thousands of jobs: latency of its first page and of a filtered, sorted page.

1. Makes a temporary data directory whose store holds ``--jobs`` jobs (default 2,000) as a team's
   would: six recordings, five pipelines, every status (mostly succeeded), configs that differ,
   metric values of each succeeded job (as the server stores them when a job ends), names, tags
   and notes on some, 20 suites whose cells give about 600 jobs a variant.
2. Starts the app on a free 127.0.0.1 port (uvicorn in a thread; an executor with no worker slot,
   so nothing runs), and times ``--requests`` GETs of each view after ``--warmup`` untimed ones:
   the first page (``/runs``; and ``/``, the same table with the lists below it), a filtered and
   sorted page (pipeline and status filters, metric columns, a metric condition, sorted by a
   metric), a free-text search, and the CSV export of the filtered view (every page).
   With ``--busy N``, N processes spin on the CPU meanwhile (as N workers replaying would).
   Then grouped views (issue 41): by pipeline and recording with three metrics, by pipeline, a config key
   and the commit under an ``or`` condition, and the grouped CSV.
3. Prints p50/p95/max in ms per view and writes them with ``--json PATH``; exit 1 when a p95 of the
   pages (first, filtered and sorted, both grouped) is over ``--target-ms`` (300, issues 25 and 41).

Run: `.venv/bin/python benchmarks/web_runs_table.py [--jobs 2000] [--requests 100] [--json out.json]`.
"""

from __future__ import annotations

import argparse
import json
import random
import socket
import sqlite3
import statistics
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import httpx

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_io import write_json

RECORDINGS = ["sim.mcap", "hall-1.mcap", "hall-2.mcap", "mrclam-1.mcap", "seabed.mcap", "corridor.mcap"]
PIPELINES = {"odometry": ("ape_rmse_m", "rpe_step_trans_rmse_m"),
             "dslam": ("ape_rmse_m", "landmark_rmse_m", "landmark_nees_mean", "landmarks_mapped"),
             "ekfslam": ("ape_rmse_m", "landmark_rmse_m", "landmark_nees_mean"),
             "topometric": ("ape_rmse_m", "loop_closures", "loop_closure_precision"),
             "ifmi": ("ate_rmse_px", "registrations", "pnr_median")}
COMMITS = [f"{k:07x}" + "0" * 33 for k in (0x3F2A9C1, 0x8BE41D7, 0x1C0FFEE, 0xDEC0DE5)] + [None]
STATUSES = ["succeeded"] * 16 + ["failed", "failed", "cancelled", "interrupted"]
VIEWS = {
    "first_page": "/runs",
    "home": "/",  # the same table, and below it the recordings, the 12 newest jobs and 20 suites
    "filtered_sorted": "/runs?pipeline=dslam&status=succeeded&cols=ape_rmse_m,landmark_rmse_m,landmark_nees_mean"
                       "&where=landmark_rmse_m+<+0.1&sort=-m.landmark_rmse_m",
    "text_search": "/runs?q=baseline&sort=-m.ape_rmse_m",
    "csv_filtered": "/runs.csv?pipeline=dslam&status=succeeded&cols=ape_rmse_m,landmark_rmse_m"
                    "&where=landmark_rmse_m+<+0.1&sort=-m.landmark_rmse_m",
    # groups (issue 41): every matching run read, grouped and summed up per request
    "grouped": "/runs?group=pipeline,recording&cols=ape_rmse_m,landmark_rmse_m,landmark_nees_mean&sort=m.ape_rmse_m",
    "grouped_config": "/runs?group=pipeline,config.range_sigma_m,commit&cols=ape_rmse_m,landmark_rmse_m"
                      "&where=status+%3D+succeeded+or+seed+%3C+3&sort=m.landmark_rmse_m",
    "csv_grouped": "/runs.csv?group=pipeline,recording&cols=ape_rmse_m,landmark_rmse_m,landmark_nees_mean",
}
PAGES = ("first_page", "filtered_sorted", "grouped", "grouped_config")  # the views held to --target-ms


class IdleExecutor:
    """No worker slot: the scheduler starts no thread, so the jobs in the store stay as written."""

    slots = 0

    def start(self) -> None:
        """Nothing to start."""

    def run(self, task: Any) -> Any:
        raise AssertionError("the benchmark runs no job")

    def cancel(self, job_id: str) -> None:
        """Nothing runs."""

    def close(self) -> None:
        """Nothing to stop."""


def fill(db: Path, n: int, rng: random.Random) -> None:
    """``n`` jobs with realistic rows, in one transaction."""
    now = time.time() - n * 60
    recs = [(f"{i:064x}", name) for i, name in enumerate(RECORDINGS, 1)]
    conn = sqlite3.connect(db)
    with conn:
        conn.executemany("INSERT INTO recordings VALUES (?, ?, 1000, '[]', 100, 0, 1000000000, ?)",
                         [(rid, name, now) for rid, name in recs])
        jobs, tags, cells = [], [], []
        for i in range(n):
            job_id = f"{rng.getrandbits(128):032x}"
            pipeline = rng.choice(list(PIPELINES))
            status = rng.choice(STATUSES)
            created = now + i * 60
            started, finished = created + rng.uniform(0, 5), None
            finished = started + rng.uniform(2, 300)
            config = {} if rng.random() < 0.5 else {"range_sigma_m": rng.choice([0.05, 0.1, 0.2])}
            if pipeline == "dslam" and rng.random() < 0.3:
                config["sparsify"] = rng.choice([True, False])
            metrics = None
            if status == "succeeded":
                metrics = json.dumps({m: round(rng.lognormvariate(-2.5, 1.0), 6) for m in PIPELINES[pipeline]})
            error = {"failed": "sim.mcap: topic /camera/image, which pipeline ifmi needs, is not in the recording\n"
                               "pass a topic map", "cancelled": "cancelled by request",
                     "interrupted": "interrupted by a server stop after 2 attempts"}.get(status)
            name = rng.choice(["baseline", "tuned sigma", "paper run", None, None, None])
            note = "before the data-association fix" if rng.random() < 0.1 else None
            jobs.append((job_id, rng.choice(recs)[0], pipeline, json.dumps(config), rng.randrange(10), status,
                         1.0 if status == "succeeded" else 0.4, error, note, 1, created, started, finished,
                         None if name is None else f"{name} {i}", metrics, rng.choice(COMMITS)))
            for tag in rng.sample(["paper", "nightly", "v1", "v2", "regression", "mrclam"], rng.randrange(3)):
                tags.append((job_id, tag))
            if rng.random() < 0.3:
                cells.append((f"{i % 20:032x}", i, json.dumps({"variant": rng.choice(["default", "tuned"])}), job_id))
        conn.executemany("INSERT INTO jobs (id, recording_id, pipeline, config, seed, status, progress, error, note, "
                         "attempts, created, started, finished, name, metrics, git_commit) "
                         "VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?)", jobs)
        conn.executemany("INSERT INTO job_tags VALUES (?, ?)", tags)
        conn.executemany("INSERT INTO suite_cells VALUES (?, ?, ?, ?, 0)", cells)
        conn.executemany("INSERT INTO suites VALUES (?, ?, 'toml', '', ?)",
                         [(f"{k:032x}", f"nightly-{k}", now) for k in range(20)])
    conn.close()


def spin() -> None:
    """A stand-in for a worker replaying a recording: all of one core, until terminated."""
    while True:
        pass


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port: int = s.getsockname()[1]
        return port


def percentile(values: list[float], q: float) -> float:
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, round(q / 100 * (len(ordered) - 1)))]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--jobs", type=int, default=2000)
    ap.add_argument("--requests", type=int, default=100, help="timed requests per view")
    ap.add_argument("--warmup", type=int, default=5)
    ap.add_argument("--target-ms", type=float, default=300.0)
    ap.add_argument("--busy", type=int, default=0, help="processes spinning on the CPU while timing (workers)")
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()

    import uvicorn

    from slamreplay.api.app import create_app
    from slamreplay.api.service.settings import Settings

    with tempfile.TemporaryDirectory(prefix="runs-table-") as tmp:
        port = free_port()
        settings = Settings(data_dir=Path(tmp), workers=1, allowed_hosts=("127.0.0.1",))
        app = create_app(settings, executor=IdleExecutor())  # type: ignore[arg-type]
        tic = time.perf_counter()
        fill(settings.db_path, args.jobs, random.Random(25))
        fill_s = time.perf_counter() - tic
        server = uvicorn.Server(uvicorn.Config(app, host="127.0.0.1", port=port, log_level="warning"))
        thread = threading.Thread(target=server.run, daemon=True)
        thread.start()
        base = f"http://127.0.0.1:{port}"
        with httpx.Client(base_url=base, timeout=30) as client:
            deadline = time.monotonic() + 30
            while True:
                try:
                    client.get("/healthz")
                    break
                except httpx.TransportError:
                    if time.monotonic() > deadline:
                        raise
                    time.sleep(0.1)
            figures: dict[str, Any] = {"jobs": args.jobs, "requests": args.requests, "fill_s": round(fill_s, 3),
                                       "busy_processes": args.busy, "target_p95_ms": args.target_ms, "views": {}}
            import multiprocessing

            spinners = [multiprocessing.get_context("spawn").Process(target=spin, daemon=True)
                        for _ in range(args.busy)]
            for proc in spinners:
                proc.start()
            for view, url in VIEWS.items():
                for _ in range(args.warmup):
                    r = client.get(url)
                    assert r.status_code == 200, (url, r.status_code, r.text[:300])
                times = []
                for _ in range(args.requests):
                    t0 = time.perf_counter()
                    r = client.get(url)
                    times.append((time.perf_counter() - t0) * 1e3)
                    assert r.status_code == 200
                rows = (r.text.count("\n") - 1 if url.startswith("/runs.csv")
                        else r.text.count('<tr class="group"') or r.text.count('<tr id="run-'))
                figures["views"][view] = {"url": url, "rows": rows, "bytes": len(r.content),
                                          "p50_ms": round(statistics.median(times), 2),
                                          "p95_ms": round(percentile(times, 95), 2), "max_ms": round(max(times), 2)}
            for proc in spinners:
                proc.terminate()
                proc.join(5)
        server.should_exit = True
        thread.join(10)

    busy = f", {args.busy} processes busy meanwhile" if args.busy else ""
    print(f"runs table with {args.jobs} jobs (store filled in {fill_s:.2f} s), {args.requests} requests per view"
          f"{busy}:")
    for view, f in figures["views"].items():
        print(f"  {view:16s} p50 {f['p50_ms']:7.1f} ms  p95 {f['p95_ms']:7.1f} ms  max {f['max_ms']:7.1f} ms  "
              f"({f['rows']} rows, {f['bytes'] / 1024:.0f} KiB)")
    worst = max(figures["views"][v]["p95_ms"] for v in PAGES)
    figures["pass"] = worst < args.target_ms
    print(f"p95 of the {len(PAGES)} pages ({', '.join(PAGES)}): {worst:.1f} ms against a target of "
          f"{args.target_ms:.0f} ms: {'met' if figures['pass'] else 'MISSED'}")
    if args.json:
        write_json(args.json, figures)
    return 0 if figures["pass"] else 1


if __name__ == "__main__":
    sys.exit(main())
