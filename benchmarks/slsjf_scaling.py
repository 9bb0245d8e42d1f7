"""SLSJF per-step and per-join cost as the map grows, beside D-SLAM and EKF-SLAM (``dslam_scaling.py``).

The world, the warm-up and the timed scans are ``dslam_scaling.py``'s (imported from it: ``sim-landmarks``
grids of N landmarks at 3 m spacing, a lawnmower over the whole world that maps all N, then a U-turn
into the mapped area at the paper scenario's pace, 0.04 m per scan). For each N, in a fresh subprocess
with single-threaded BLAS:

1. warm-up, untimed per step: SLSJF (``linearization="once"``, the paper's composed robot) drives the
   lawnmower and the ``--settle`` scans; every join is timed, so the warm-up also gives the join cost
   as the map grows (``warmup_join_*``: the joins of the warm-up's last tenth);
2. five timed segments of ``--steps`` scans each, one after the other along the way back (a robot
   working in a mapped area: the steady state), each step one odometry prediction and one scan,
   wall clock and process CPU time; a step that ends a local map includes its join (every 30 scans
   here), whose time ``Slsjf.profile["join"]`` also gives alone:

   - ``once``: the 2008 filter (each local map linearized once), the paper's composed robot;
   - ``once_joined``: the same map with the filter's default robot (``robot_estimate="joined"``: the
     local map fused at every scan with the global map's marginal over its start frame and the features
     both hold; the global covariance columns it needs are solved once per local map);
   - ``once_pcg``: the same, the state and the covariance columns recovered by preconditioned CG
     (``state_recovery="pcg"``, D-SLAM's recovery) from its first join on, no factor held;
   - ``once_pcg_composed``: the same with the paper's composed robot (3 covariance columns per local map,
     the start frame's, instead of the joined robot's 3 + 2 per shared feature);
   - ``iterated``: I-SLSJF (every local map re-linearized at each join, Gauss-Newton), the composed
     robot, switched on for the map built so far: one untimed Gauss-Newton run first
     (``iterated_first_s``), then the timed steps, stopped after ``--iterated-budget-s`` seconds (at
     least ``MIN_JOINS`` joins). An I-SLSJF
     warm-up would re-linearize all local maps at each of the warm-up's joins (hours at N = 16,000),
     and the cost of a join depends on the map, not on how it was built. Not run (with the reason)
     when the first Gauss-Newton iteration alone exceeds the budget, or for sizes above one whose mean
     join exceeded ``--iterated-max-join-s``.

Memory: SLSJF's arrays (the local maps it holds, each its estimate and information; the running
information matrix and vector; the factor of the last join, L and U), before and after the timed
segments (the map does not grow there, the local maps do: whether memory grows with N or with the run
length), and the process's resident memory. Fitted: ``log t = log a + b log N`` for the per-step and
per-join means and for the memory.

D-SLAM and EKF-SLAM: for N up to ``--compare-max`` ``dslam_scaling.py --one N`` runs in its own
subprocess with the same seed, steps and settle (the first timed segment's scans are its timed scans),
EKF-SLAM within ``--ekf-budget-s``; ``--dslam-json FILE`` (``dslam_scaling.py --json`` output) supplies
the sizes not run; with ``--report OLD`` (an earlier ``--json`` output) nothing is measured: OLD's rows are
printed again with ``--dslam-json``'s figures beside them. Run:
``.venv/bin/python benchmarks/slsjf_scaling.py [--sizes 250 1000 4000 16000] [--steps 300] [--json OUT]``
(about 20 minutes with the defaults on two cores, most of it the warm-up at N = 16,000).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
from bench_io import write_json
from dslam_scaling import (
    NO_OUTLIERS,
    NOISE,
    SIGMA_B,
    SIGMA_R,
    SINGLE_THREAD,
    Scan,
    fmt,
    lawnmower,
    peak_rss_mb,
    rss_mb,
    scans,
    timed,
    way_back,
)

from slamreplay.algorithms.ekfslam import EkfSlamConfig
from slamreplay.algorithms.slsjf import GlobalMap, Slsjf, SlsjfConfig
from slamreplay.recorder.sim.landmarks import LandmarkSimConfig, landmark_positions

HERE = Path(__file__).resolve().parent
MIN_JOINS = 2  # the iterated segment times at least this many joins
VARIANTS = ("once", "once_joined", "once_pcg", "once_pcg_composed", "iterated")
SEGMENTS = len(VARIANTS)  # timed segments of --steps scans, one per variant, one after the other


def map_bytes(gm: GlobalMap) -> dict[str, float]:
    """SLSJF's arrays (MB): the local maps held, the running information (once), the last factor (direct
    recovery) or the preconditioner and the covariance columns kept as initial guesses (PCG), the state."""
    maps = sum(m.z.nbytes + m.W.nbytes + m.features.nbytes for m in gm.maps)
    info = gm._info  # the running information matrix (SLSJF): private, read for the measurement only
    info_b = 0 if info is None else info.data.nbytes + info.indices.nbytes + info.indptr.nbytes
    f = gm._factor
    factor = 0 if f is None else (f.L.nnz + f.U.nnz) * 12 + 2 * f.L.shape[0] * 8  # values, indices, perms
    pcg = 0
    if gm.recovery == "pcg" and gm._precondition is not None:
        pcg = gm._precondition.nbytes + sum(c.nbytes for c in (*gm._warm.values(), *gm._fresh.values()))
    mb = 2.0**20
    total = maps + info_b + gm._vector.nbytes + factor + pcg + gm.x.nbytes
    return {"local_maps_mb": maps / mb, "information_mb": (info_b + gm._vector.nbytes) / mb, "factor_mb": factor / mb,
            "pcg_mb": pcg / mb, "state_mb": gm.x.nbytes / mb, "total_mb": total / mb}


def stats(prefix: str, wall: np.ndarray, cpu: np.ndarray | None = None) -> dict[str, float]:
    """Mean and p95 (ms) of per-item seconds; NaN when there are none."""
    if len(wall) == 0:
        return {f"{prefix}_mean_ms": math.nan, f"{prefix}_p95_ms": math.nan, f"{prefix}_count": 0}
    out = {f"{prefix}_mean_ms": 1e3 * float(wall.mean()), f"{prefix}_p95_ms": 1e3 * float(np.percentile(wall, 95)),
           f"{prefix}_count": len(wall)}
    if cpu is not None:
        out[f"{prefix}_cpu_mean_ms"] = 1e3 * float(cpu.mean())
    return out


def segment(slam: Slsjf, steps: list[Scan], name: str, budget_s: float = math.inf,
            min_steps: int = 10) -> dict[str, Any]:
    """Time ``steps`` (dslam_scaling.timed): per step, per join, per step without a join."""
    slam.profile.clear()
    joined: list[bool] = []

    def step(s: Scan) -> None:
        slam.predict(s.u)
        joined.append(slam.observe(s.r, s.b, s.ids, SIGMA_R, SIGMA_B).joined)

    wall, cpu = timed(step, steps, budget_s, min_steps)
    joins = np.asarray(slam.profile.get("join", []))
    plain = ~np.asarray(joined, bool)
    parts = {k: 1e3 * float(np.sum(slam.profile.get(k, []))) / max(1, len(joins))
             for k in ("global_join", "start_covariance", "columns")}  # ms per local map
    return {**stats(f"{name}_step", wall, cpu), **stats(f"{name}_join", joins),
            **{f"{name}_{k}_per_local_map_ms": v for k, v in parts.items()},
            **stats(f"{name}_nojoin_step", wall[plain]), f"{name}_iterations": slam.map.iterations[-len(joins):]
            if len(joins) else []}


def iterated_switch(slam: Slsjf, budget_s: float) -> tuple[float, str]:
    """Switch the global map to I-SLSJF and converge it once (untimed by the segment); (seconds, reason not run)."""
    gm = slam.map
    gm.linearization = "iterated"
    gm._pattern = None
    tic = time.perf_counter()
    a, g = gm._assemble([gm._linearize(m) for m in gm.maps])  # one Gauss-Newton iteration's work, timed alone
    gm._factorize(a).solve(g)
    one = time.perf_counter() - tic
    if one > budget_s:
        return one, f"one Gauss-Newton iteration takes {fmt(one)} s (budget {fmt(budget_s)} s)"
    gm._gauss_newton()
    slam.config = replace(slam.config, linearization="iterated", robot_estimate="composed")
    slam._start_pose = gm.pose(slam.start)  # the filter's copies of the start frame, after the map moved
    slam._start_cov = gm.pose_covariance(slam.start)
    slam._columns = {}
    return time.perf_counter() - tic, ""


def one_size(n: int, args: argparse.Namespace) -> dict[str, Any]:
    """Everything for one world size (run in its own process)."""
    cfg = LandmarkSimConfig(landmarks=n)
    landmarks = landmark_positions(cfg)
    rng = np.random.default_rng(args.seed)
    path = lawnmower(cfg.side_m)
    back = way_back(path[-1], args.settle + SEGMENTS * args.steps)
    warm = scans(path, landmarks, rng)
    tail = scans(back, landmarks, rng, first=path[-1])
    settle, tests = tail[: args.settle], [tail[args.settle + k * args.steps:args.settle + (k + 1) * args.steps]
                                          for k in range(SEGMENTS)]
    rss0 = rss_mb()
    local = EkfSlamConfig(odometry_noise=NOISE, association_params=NO_OUTLIERS)
    slam = Slsjf(SlsjfConfig(local=local, linearization="once", robot_estimate="composed"), clock=time.perf_counter)
    tic = time.perf_counter()
    for s in warm + settle:
        slam.predict(s.u)
        slam.observe(s.r, s.b, s.ids, SIGMA_R, SIGMA_B)
    warm_s = time.perf_counter() - tic
    warm_joins = np.asarray(slam.profile["join"])
    gm = slam.map
    before = map_bytes(gm)
    row: dict[str, Any] = {
        "N": n, "mapped": slam.n, "warmup_scans": len(warm) + len(settle), "warmup_s": warm_s,
        "warmup_joins_s": float(warm_joins.sum()), "local_maps": len(gm.maps), "state_dim": gm.dim,
        "information_nnz": int(gm._info.nnz) if gm._info is not None else 0,
        "factor_nnz": int(gm._factor.L.nnz + gm._factor.U.nnz) if gm._factor is not None else 0,
        **stats("warmup_join", warm_joins[-max(1, len(warm_joins) // 10):]),
        **{f"arrays_{k}": v for k, v in before.items()}, "rss_growth_mb": rss_mb() - rss0,
    }
    maps0 = len(gm.maps)
    row.update(segment(slam, tests[0], "once"))
    slam.config = replace(slam.config, robot_estimate="joined")  # the default robot, from here on
    row.update(segment(slam, tests[1], "once_joined"))
    after = map_bytes(gm)
    row.update({f"arrays_after_{k}": v for k, v in after.items()}, mapped_after=slam.n,
               local_maps_after=len(gm.maps), rss_after_once_mb=rss_mb() - rss0)
    row["mb_per_local_map"] = (after["total_mb"] - before["total_mb"]) / max(1, len(gm.maps) - maps0)
    gm.recovery = "pcg"  # D-SLAM's recovery from the next join on (the factor is dropped there)
    row.update(segment(slam, tests[2], "once_pcg"))
    row.update({f"arrays_pcg_{k}": v for k, v in map_bytes(gm).items()}, once_pcg_fallbacks=gm.fallbacks,
               once_pcg_state_iterations=float(np.mean(gm.pcg_iterations)) if gm.pcg_iterations else math.nan,
               once_pcg_column_iterations=float(np.mean(gm.column_iterations)) if gm.column_iterations else math.nan)
    slam.config = replace(slam.config, robot_estimate="composed")  # the paper's robot: 3 columns per local map
    row.update(segment(slam, tests[3], "once_pcg_composed"))
    gm.recovery = "direct"
    if n > args.iterated_max_n:
        row["iterated_not_run"] = f"I-SLSJF at N = {args.iterated_max_n} was over its budget"
    else:
        first_s, reason = iterated_switch(slam, args.iterated_budget_s)
        row["iterated_first_s"] = first_s
        if reason:
            row["iterated_not_run"] = reason
        else:
            row.update(segment(slam, tests[4], "iterated", args.iterated_budget_s,
                               min_steps=MIN_JOINS * slam.config.local_map_scans + 1))
            row["arrays_iterated_total_mb"] = map_bytes(gm)["total_mb"]
    row.update(rss_end_mb=rss_mb() - rss0, peak_rss_mb=peak_rss_mb())
    return row


def compare_row(n: int, args: argparse.Namespace) -> dict[str, Any]:
    """D-SLAM and EKF-SLAM at N from ``dslam_scaling.py --one`` (its own process), same seed and scans."""
    cmd = [sys.executable, str(HERE / "dslam_scaling.py"), "--one", str(n), "--steps", str(args.steps), "--settle",
           str(args.settle), "--ekf-budget-s", str(args.ekf_budget_s), "--seed", str(args.seed)]
    done = subprocess.run(cmd, capture_output=True, text=True, env={**os.environ, **SINGLE_THREAD})
    if done.returncode:
        return {"compare_error": done.stderr.strip().splitlines()[-1] if done.stderr.strip() else "failed"}
    return dict(json.loads(done.stdout.strip().splitlines()[-1]))


COMPARED = ("dslam_mean_ms", "dslam_p95_ms", "dslam_cpu_mean_ms", "ekf_mean_ms", "ekf_p95_ms", "ekf_steps",
            "dslam_array_mb", "dslam_rss_growth_mb", "compare_error")


def beside(row: dict[str, Any], other: dict[str, Any], source: str) -> None:
    """Add D-SLAM's and EKF-SLAM's figures (a ``dslam_scaling.py`` row) to ``row``."""
    if other:
        row.update({k: other[k] for k in COMPARED if k in other})
        row["compare_source"] = source


def fit(rows: list[dict[str, Any]], key: str) -> float:
    """Exponent b of ``log t = log a + b log N`` over the rows that have ``key`` (NaN with fewer than two)."""
    pts = [(float(r["N"]), float(r[key])) for r in rows if isinstance(r.get(key), (int, float))
           and math.isfinite(float(r[key])) and float(r[key]) > 0]
    if len(pts) < 2:
        return math.nan
    ns, ts = np.log(np.array(pts)).T
    return float(np.polyfit(ns, ts, 1)[0])


def report(rows: list[dict[str, Any]]) -> dict[str, float]:
    """Print the tables, the fits and the ratios; return the fits."""
    cols = ("N", "mapped", "local_maps", "once_step_mean_ms", "once_step_p95_ms", "once_join_mean_ms",
            "once_join_p95_ms", "once_joined_step_mean_ms", "once_joined_step_p95_ms", "once_pcg_step_mean_ms",
            "once_pcg_join_mean_ms", "once_pcg_composed_step_mean_ms", "once_pcg_composed_join_mean_ms",
            "arrays_pcg_total_mb", "iterated_step_mean_ms",
            "iterated_step_p95_ms", "iterated_join_mean_ms", "iterated_join_p95_ms", "iterated_join_count",
            "dslam_mean_ms", "dslam_p95_ms", "ekf_mean_ms", "arrays_total_mb", "arrays_local_maps_mb",
            "arrays_factor_mb", "mb_per_local_map", "rss_growth_mb", "peak_rss_mb", "warmup_s")
    print("\n| " + " | ".join(cols) + " |\n" + "|---" * len(cols) + "|")
    for r in rows:
        print("| " + " | ".join(fmt(r.get(c, "-")) for c in cols) + " |")
    print("\nA step's mean includes the joins (one step in 30 ends a local map); its p95 does not see them.\n")
    fits = {}
    for key in ("once_step_mean_ms", "once_step_p95_ms", "once_nojoin_step_mean_ms", "once_join_mean_ms",
                "warmup_join_mean_ms", "once_joined_step_mean_ms", "once_joined_nojoin_step_mean_ms",
                "once_pcg_step_mean_ms", "once_pcg_join_mean_ms", "once_pcg_composed_step_mean_ms",
                "once_pcg_global_join_per_local_map_ms", "once_global_join_per_local_map_ms", "arrays_pcg_total_mb",
                "iterated_step_mean_ms", "iterated_join_mean_ms", "arrays_total_mb", "arrays_factor_mb",
                "rss_growth_mb", "dslam_mean_ms", "ekf_mean_ms"):
        fits[key] = b = fit(rows, key)
        if math.isfinite(b):
            print(f"{key} ~ N^{b:.2f}")
    print()
    for r in rows:
        notes = []
        if "iterated_not_run" in r:
            notes.append(f"I-SLSJF not run: {r['iterated_not_run']}")
        elif "iterated_first_s" in r:
            notes.append(f"I-SLSJF switch-over Gauss-Newton {fmt(r['iterated_first_s'])} s, timed "
                         f"{r.get('iterated_step_count')} steps, iterations per join {r.get('iterated_iterations')}")
        notes.append(f"arrays {fmt(r['arrays_total_mb'])} MB (factor {fmt(r['arrays_factor_mb'])}, information "
                     f"{fmt(r['arrays_information_mb'])}, local maps {fmt(r['arrays_local_maps_mb'])}), then "
                     f"+{fmt(r['arrays_after_total_mb'] - r['arrays_total_mb'])} MB over "
                     f"{r['local_maps_after'] - r['local_maps']} more local maps with the map unchanged")
        for k in ("once_joined", "once_pcg", "once_pcg_composed"):
            if f"{k}_global_join_per_local_map_ms" in r:
                notes.append(f"{k} per local map: global join {fmt(r[f'{k}_global_join_per_local_map_ms'])} ms, "
                             f"start covariance {fmt(r[f'{k}_start_covariance_per_local_map_ms'])} ms, robot's "
                             f"columns {fmt(r[f'{k}_columns_per_local_map_ms'])} ms")
        if "once_pcg_state_iterations" in r:
            notes.append(f"PCG iterations: state {fmt(r['once_pcg_state_iterations'])}, covariance columns "
                         f"{fmt(r['once_pcg_column_iterations'])}, fallbacks {r['once_pcg_fallbacks']}")
        if "dslam_mean_ms" in r:
            ratios = [f"{v} {fmt(r[f'{k}_step_mean_ms'] / r['dslam_mean_ms'])}" for k, v in
                      (("once", "once"), ("once_joined", "joined"), ("once_pcg", "PCG"), ("iterated", "iterated"))
                      if f"{k}_step_mean_ms" in r]
            notes.append(f"SLSJF / D-SLAM mean step ({r['compare_source']}): " + ", ".join(ratios))
        if "ekf_mean_ms" in r:
            notes.append(f"EKF-SLAM / SLSJF once mean step {fmt(r['ekf_mean_ms'] / r['once_step_mean_ms'])}")
        print(f"N = {r['N']}: " + "; ".join(notes))
    return fits


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--sizes", type=int, nargs="*", default=[250, 1000, 4000, 16000])
    parser.add_argument("--steps", type=int, default=300, help="timed scans per segment (three segments per size)")
    parser.add_argument("--settle", type=int, default=150, help="untimed scans at the paper's pace before timing")
    parser.add_argument("--iterated-budget-s", type=float, default=120.0, help="I-SLSJF seconds of timed steps")
    parser.add_argument("--iterated-max-join-s", type=float, default=20.0,
                        help="no I-SLSJF for larger N after a size with a slower mean join")
    parser.add_argument("--iterated-max-n", type=int, default=10**9, help=argparse.SUPPRESS)  # set by the parent
    parser.add_argument("--compare-max", type=int, default=1000, help="largest N for D-SLAM and EKF-SLAM here")
    parser.add_argument("--ekf-budget-s", type=float, default=30.0, help="EKF seconds of timed steps per size")
    parser.add_argument("--dslam-json", type=Path, help="dslam_scaling.py --json output for the other sizes")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--one", type=int, help=argparse.SUPPRESS)  # internal: run one size, print JSON
    parser.add_argument("--json", type=Path, help="also write everything to this file")
    parser.add_argument("--report", type=Path, help="measure nothing: print this earlier --json output again")
    args = parser.parse_args()
    if args.steps < 1 or any(n < 1 for n in args.sizes):
        sys.exit("--steps and --sizes must be >= 1")
    if args.one is not None:
        print(json.dumps(one_size(args.one, args)))
        return
    known = {int(r["N"]): r for r in json.loads(args.dslam_json.read_text())} if args.dslam_json else {}
    if args.report:
        rows = json.loads(args.report.read_text())["rows"]
        for row in rows:
            if row.get("compare_source") != "this run":
                beside(row, known.get(int(row["N"]), {}), str(args.dslam_json))
        fits = report(rows)
        if args.json:
            write_json(args.json, {"rows": rows, "exponents": fits, "report_of": str(args.report)})
        return
    rows = []
    max_iterated = 10**9
    for n in args.sizes:
        cmd = [sys.executable, __file__, "--one", str(n), "--steps", str(args.steps), "--settle", str(args.settle),
               "--iterated-budget-s", str(args.iterated_budget_s), "--iterated-max-join-s",
               str(args.iterated_max_join_s), "--iterated-max-n", str(max_iterated), "--seed", str(args.seed)]
        done = subprocess.run(cmd, capture_output=True, text=True, env={**os.environ, **SINGLE_THREAD})
        if done.returncode:
            sys.exit(f"N = {n} failed:\n{done.stderr}")
        row = json.loads(done.stdout.strip().splitlines()[-1])
        if row.get("iterated_join_mean_ms", 0.0) > 1e3 * args.iterated_max_join_s or "iterated_not_run" in row:
            max_iterated = min(max_iterated, n)
        if n <= args.compare_max:
            beside(row, compare_row(n, args), "this run")
        else:
            beside(row, known.get(n, {}), str(args.dslam_json))
        rows.append(row)
        print(json.dumps(row), flush=True)
    fits = report(rows)
    if args.json:
        write_json(args.json, {"rows": rows, "exponents": fits, "steps": args.steps, "seed": args.seed})


if __name__ == "__main__":
    main()
