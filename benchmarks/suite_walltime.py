"""Suite wall time: 3 pipelines x 5 seeds, serial against ``--jobs 2`` against Ray (when installed).

The suite is sim-landmarks worlds of simulator seeds 1-5 (``--duration-s`` each, 120 s by
default) through ``odometry``, ``dslam`` and ``ekfslam``: 15 cells. The recordings are made
once before timing (they are cached by content), and each timed run writes a fresh results
directory, so every cell runs: what is timed is ``slamreplay suite run`` end to end (process
start, worker start-up, replays, results). A last run over a finished results directory
times the cache (nothing re-runs).

    python benchmarks/suite_walltime.py [--duration-s 120] [--repeat 1] [--json out.json]
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

SUITE = """\
seeds = [0]
[recordings.landmarks]
sim = "sim-landmarks"
args = {{ duration-s = {duration} }}
seeds = [1, 2, 3, 4, 5]
[pipelines.odometry]
[pipelines.dslam]
[pipelines.ekfslam]
"""


def suite_run(suite: Path, out: Path, *extra: str) -> float:
    cmd = [sys.executable, "-m", "slamreplay.api.cli", "suite", "run", str(suite), "--out", str(out), "--quiet", *extra]
    tic = time.perf_counter()
    subprocess.run(cmd, check=True, cwd=Path(__file__).resolve().parents[1])
    return time.perf_counter() - tic


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--duration-s", type=float, default=120.0, help="simulated seconds per recording (default 120)")
    p.add_argument("--repeat", type=int, default=1, help="timed runs per configuration; the best is kept")
    p.add_argument("--json", metavar="PATH", help="write the figures as JSON")
    args = p.parse_args()
    with tempfile.TemporaryDirectory(prefix="suite-bench-") as tmp:
        root = Path(tmp)
        os.environ.setdefault("SLAMREPLAY_CACHE", str(root / "cache"))
        suite = root / "suite.toml"
        suite.write_text(SUITE.format(duration=args.duration_s))
        tic = time.perf_counter()
        suite_run(suite, root / "warm", "--jobs", "2")  # makes the recordings (cached) before timing
        first = time.perf_counter() - tic
        configs = [("serial", ["--jobs", "1"]), ("jobs2", ["--jobs", "2"])]
        if importlib.util.find_spec("ray") is not None:
            configs.append(("ray2", ["--executor", "ray", "--jobs", "2"]))
        figures: dict[str, float] = {}
        for name, extra in configs:
            times = [suite_run(suite, root / f"{name}-{i}", *extra) for i in range(args.repeat)]
            figures[name] = min(times)
            print(f"{name:>8}: {figures[name]:7.2f} s for 15 cells", flush=True)
        figures["cached"] = suite_run(suite, root / "serial-0")
        print(f"{'cached':>8}: {figures['cached']:7.2f} s (second run, nothing re-runs)")
        if "ray2" not in figures:
            print("    ray: not installed (pip install slamreplay[ray]); skipped")
    doc = {"cells": 15, "duration_s": args.duration_s, "first_run_with_recordings_s": round(first, 3),
           "wall_s": {k: round(v, 3) for k, v in figures.items()},
           "speedup_jobs2": round(figures["serial"] / figures["jobs2"], 3),
           "host": {"cpus": os.cpu_count(), "platform": platform.platform()}}
    if args.json:
        Path(args.json).write_text(json.dumps(doc, indent=2) + "\n")
    print(json.dumps(doc))
    return 0


if __name__ == "__main__":
    sys.exit(main())
