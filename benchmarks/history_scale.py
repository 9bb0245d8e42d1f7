"""History at scale: ``slamreplay history`` over the last N commits of this repository, what preparing them costs.

A clone of this repository (so that its worktrees never land in the checkout's ``git worktree list``) runs a
2-cell suite (one 30 s ``sim-landmarks`` recording through ``odometry`` and ``dslam``) at each of the last N
first-parent commits of its HEAD (default 100), twice into one fresh cache: *cold* (every worktree made, each
environment of dependencies built once, downloads from pip's cache if it has them) and *warm* (everything
reused; the cells run again into a new history directory). For each pass it times every revision's
preparation (``prepare_revision``) and every cell (the revision's ``slamreplay run``, start-up included) and
reports the per-commit overhead beyond the cells' own time: the preparation (median, p90) and the wall time
not spent in cells (history prepares the next commit while earlier cells run), plus disk per commit and of the
whole cache. Beside it, the old approach (a virtual environment per commit: ``python -m venv`` and ``pip install
-e``) measured on a small sample of the same commits. Commits whose cells fail at their own code are the
history's result, counted, not the benchmark's failure.

    python benchmarks/history_scale.py [--commits 100] [--jobs 1] [--old-sample 2] [--json out.json]

Targets (issue 39): median overhead <= 10 s and <= 50 MB per commit when dependencies are unchanged; the whole
cache for 100 commits <= 10 GB.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]
MB = 1 << 20
SUITE = """[recordings.landmarks]
path = "{path}"

[pipelines.odometry]

[pipelines.dslam]
"""


def git(repo: Path, *args: str) -> str:
    return subprocess.run(["git", "-C", str(repo), *args], check=True, capture_output=True, text=True).stdout.strip()


def p90(xs: list[float]) -> float:
    return sorted(xs)[min(len(xs) - 1, round(0.9 * (len(xs) - 1)))] if xs else float("nan")


def run_pass(clone: Path, suite: Path, out: Path, shas: list[str], jobs: int) -> dict[str, Any]:
    """One ``run_history`` over ``shas``: wall time, each preparation's and each cell's time, commit outcomes."""
    from slamreplay.replay.runs import history as hist
    from slamreplay.replay.runs.revisions import run_cell
    from slamreplay.replay.runs.suite import load_suite

    prepare_s: dict[str, float] = {}
    cell_s: list[float] = []
    real_prepare = hist.prepare_revision

    def prepare(repo: Path, rev: str, cache: Path, note: Any = None) -> Any:
        tic = time.perf_counter()
        try:
            return real_prepare(repo, rev, cache, note=note)
        finally:
            prepare_s[rev] = time.perf_counter() - tic

    def run(revision: Any, job: Any) -> str | None:
        tic = time.perf_counter()
        try:
            return run_cell(revision, job)
        finally:
            cell_s.append(time.perf_counter() - tic)

    hist.prepare_revision = prepare  # type: ignore[assignment]
    try:
        tic = time.perf_counter()
        history = hist.run_history(load_suite(suite), out, shas, clone, workers=jobs, run=run)
        wall = time.perf_counter() - tic
    finally:
        hist.prepare_revision = real_prepare  # type: ignore[assignment]
    statuses = [history.status.get(sha, {}).get("status", "missing") for sha in shas]
    n = len(shas)
    return {"wall_s": wall, "prepare_s": [prepare_s.get(s, 0.0) for s in shas], "cells_s": sum(cell_s),
            "cells": len(cell_s), "wall_overhead_s_per_commit": (wall - sum(cell_s) / jobs) / n,
            "statuses": {s: statuses.count(s) for s in sorted(set(statuses))}}


def old_approach(clone: Path, shas: list[str], root: Path) -> list[dict[str, float]]:
    """The old per-commit build (worktree, ``python -m venv``, ``pip install -e``) of each of ``shas``."""
    out = []
    for sha in shas:
        where = root / sha
        tic = time.perf_counter()
        subprocess.run(["git", "-C", str(clone), "worktree", "add", "-q", "--detach", str(where / "src"), sha],
                       check=True)
        with open(root / "old-build.log", "a") as log:  # pip's warnings stay out of the table
            subprocess.run([sys.executable, "-m", "venv", str(where / "venv")], check=True, stdout=log,
                           stderr=subprocess.STDOUT)
            subprocess.run([str(where / "venv" / "bin" / "python"), "-m", "pip", "install", "--quiet",
                            "--disable-pip-version-check", "-e", str(where / "src")], check=True, stdout=log,
                           stderr=subprocess.STDOUT)
        seconds = time.perf_counter() - tic
        from slamreplay.replay.runs.rev_cache import disk_usage

        out.append({"prepare_s": seconds, "disk_mb": disk_usage(where) / MB})
        subprocess.run(["git", "-C", str(clone), "worktree", "remove", "--force", str(where / "src")], check=True)
        shutil.rmtree(where, ignore_errors=True)
    return out


def disk(cache: Path) -> dict[str, Any]:
    from slamreplay.replay.runs.rev_cache import entries

    found = entries(cache)
    revs = [e.size / MB for e in found if e.kind == "revision"]
    envs = [e.size / MB for e in found if e.kind == "environment"]
    return {"revision_mb_median": statistics.median(revs) if revs else 0.0, "revision_mb_max": max(revs, default=0.0),
            "environments": len(envs), "environment_mb": envs,
            "cache_mb": sum(e.size for e in found) / MB, "revisions": len(revs)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--commits", type=int, default=100, help="the last N first-parent commits (default 100)")
    ap.add_argument("--jobs", type=int, default=1, help="cells at once (default 1)")
    ap.add_argument("--old-sample", type=int, default=2, help="commits built the old way (default 2; 0: none)")
    ap.add_argument("--json", metavar="PATH", help="write the figures as JSON")
    ap.add_argument("--keep", metavar="DIR", help="work in DIR and keep it (default: a temporary directory)")
    args = ap.parse_args()
    os.environ.pop("SLAMREPLAY_REV_PYTHON", None)  # real environments: that is what is measured
    root = Path(args.keep) if args.keep else Path(tempfile.mkdtemp(prefix="history-scale-"))
    root.mkdir(parents=True, exist_ok=True)
    os.environ["SLAMREPLAY_CACHE"] = str(root / "cache")
    os.environ.setdefault("SLAMREPLAY_CACHE_LIMIT_GB", "10")
    try:
        clone = root / "clone"
        if not clone.is_dir():
            subprocess.run(["git", "clone", "-q", str(REPO), str(clone)], check=True)
        shas = git(clone, "rev-list", "--first-parent", "--reverse", f"-{args.commits}", "HEAD").split()[-args.commits:]
        recording = root / "landmarks.mcap"
        if not recording.is_file():
            subprocess.run([sys.executable, "-m", "slamreplay.api.cli", "record", "sim-landmarks", "--duration-s",
                            "30", "--out", str(recording), "-q"], check=True)
        suite = root / "suite.toml"
        suite.write_text(SUITE.format(path=recording))
        figures: dict[str, Any] = {"commits": len(shas), "jobs": args.jobs, "first": shas[0], "last": shas[-1]}
        for name in ("cold", "warm"):
            out = root / f"hist-{name}"
            shutil.rmtree(out, ignore_errors=True)
            figures[name] = run_pass(clone, suite, out, shas, args.jobs)
            figures[name]["disk"] = disk(root / "cache")
            print(f"{name}: {figures[name]['wall_s']:.0f} s, {figures[name]['statuses']}", flush=True)
        if args.old_sample:
            figures["old"] = old_approach(clone, shas[-args.old_sample:], root / "old")
        report(figures)
        if args.json:
            Path(args.json).write_text(json.dumps(figures, indent=2) + "\n")
    finally:
        if not args.keep:
            subprocess.run([sys.executable, "-m", "slamreplay.api.cli", "cache", "prune", "--all", "-q"])
            shutil.rmtree(root, ignore_errors=True)


def report(f: dict[str, Any]) -> None:
    """The table: per pass, preparation per commit, wall overhead, disk; the old approach beside it."""
    n = f["commits"]
    print(f"\nhistory over the last {n} commits ({f['first'][:10]}..{f['last'][:10]}), 2 cells each, "
          f"--jobs {f['jobs']}; load average {os.getloadavg()[0]:.1f}")
    print(f"{'':22}{'prepare median':>15}{'p90':>9}{'max':>9}{'wall-cells/commit':>19}{'disk/commit':>13}"
          f"{'cache':>11}")
    for name in ("cold", "warm"):
        p = f[name]
        d = p["disk"]
        print(f"{'shared envs ' + name:22}{statistics.median(p['prepare_s']):>13.2f} s{p90(p['prepare_s']):>7.2f} s"
              f"{max(p['prepare_s']):>7.1f} s{p['wall_overhead_s_per_commit']:>17.2f} s"
              f"{d['revision_mb_median']:>10.1f} MB{d['cache_mb'] / 1024:>8.2f} GB")
    if "old" in f:
        old = f["old"]
        med = statistics.median(o["prepare_s"] for o in old)
        mb = statistics.median(o["disk_mb"] for o in old)
        print(f"{'old: venv per commit':22}{med:>13.2f} s{'':>9}{max(o['prepare_s'] for o in old):>7.1f} s"
              f"{'':>19}{mb:>10.1f} MB{mb * n / 1024:>8.2f} GB (x{n}, projected)")
        cold = statistics.median(f["cold"]["prepare_s"])
        print(f"ratios (old / shared, cold median): time x{med / max(cold, 1e-9):.0f}, disk per commit "
              f"x{mb / max(f['cold']['disk']['revision_mb_median'], 1e-9):.0f}")
    d = f["cold"]["disk"]
    print(f"environments: {d['environments']} ({', '.join(f'{m / 1024:.2f} GB' for m in d['environment_mb'])}); "
          f"revisions {d['revisions']}; cells {f['cold']['cells']} cold / {f['warm']['cells']} warm "
          f"({f['cold']['cells_s'] / max(f['cold']['cells'], 1):.1f} s each); commits by outcome: "
          f"{f['cold']['statuses']}")


if __name__ == "__main__":
    main()
