"""D-SLAM against EKF-SLAM per-step time as the map grows: the O(N) claim of D-SLAM section 3.3.

Worlds are ``sim-landmarks`` landmark grids of N landmarks (3 m spacing: the same density, on a
square that grows with N). For each N, in a fresh subprocess (so that memory is measured per size):

1. warm-up, untimed: D-SLAM drives a lawnmower over the whole world (lanes 6 m apart, one
   180-degree, 5 m scan every 0.5 m, the simulator's noise levels, five stationary scans first
   for phase I) and so maps all N landmarks;
2. settling, untimed: at the end of the last lane the robot slows to the paper scenario's pace
   (0.2 m/s, 5 scans/s: 0.04 m per scan) and makes a U-turn of radius 1.5 m into the mapped
   area; ``--settle`` scans;
3. timed: the next ``--steps`` scans, driving back between the last two lanes: a robot working
   in a mapped area, re-observing features mapped on its way out (the steady state). Each step
   is one odometry prediction and one scan, timed with ``time.perf_counter``.

EKF-SLAM (up to the sizes the time and memory budgets allow) runs the same timed scans, started
from D-SLAM's map and pose at the start of the timed segment with a dense covariance (the cost of
an EKF step does not depend on the covariance's values, and an EKF warm-up over tens of thousands
of scans at O(N^2) each would take hours). EKF-SLAM stops at the first size whose covariance
would exceed ``--ekf-max-gb`` or after a size whose mean step exceeded ``--ekf-max-step-s``;
within a size it times at most ``--ekf-budget-s`` seconds of steps (at least 10 steps).

Each size runs with single-threaded BLAS (both filters alike). Step times are wall clock and,
because the machine may be shared, also the process's CPU time. Printed per size: mapped
features, per-step mean and p95 (ms) of D-SLAM and EKF-SLAM, their ratio, D-SLAM's per-stage
times (ms per step), the recovery methods used in the timed segment, the memory (D-SLAM's
arrays, and the process's resident memory after D-SLAM and at its peak) and the warm-up time;
then the exponent b of a least-squares fit ``log t = log a + b log N`` of D-SLAM's step time,
and the same fit for its memory. Run:
``.venv/bin/python benchmarks/dslam_scaling.py [--sizes 250 1000 4000 16000] [--steps 300]``
(about 20 minutes with the defaults on two cores; ``--check`` adds an exact solve at the end of
each timed segment to report how far the recovered state is from ``I^-1 i``).

``--durations 1800 7200`` instead runs D-SLAM (the default configuration, final relinearisation
on) over the paper scenario (``sim-landmarks`` defaults, that many seconds, ``--seed``), each in a
fresh process that reads the recording message by message, and reports the memory as the run
grows: the growth of the process's resident memory over the run and of its peak (``ru_maxrss``,
a high-water mark, so reading the recording can hide the filter's growth), the process's resident
memory before D-SLAM and its peak (absolute), D-SLAM's arrays (information matrix, recovery,
covariance cache and summary: what the filter holds), the final
relinearisation's summary (entries, bytes) against the bytes the previous design's log of every
measurement would hold, and the per-scan time of all scans, of the scans that close a loop (a
feature unseen for ``loop_closure_gap_scans`` re-observed) and of the 25 scans after each. A
memory that does not grow with the duration is O(map), not O(time).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import resource
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from slamreplay.algorithms.common import se2
from slamreplay.algorithms.common.association import AssociationConfig
from slamreplay.algorithms.common.motion import OdometryNoise
from slamreplay.algorithms.dslam import DSlam, DSlamConfig
from slamreplay.algorithms.dslam.recovery import direct
from slamreplay.algorithms.ekfslam import EkfSlam, EkfSlamConfig
from slamreplay.recorder.sim.landmarks import LandmarkSimConfig, landmark_positions

STEP_M, LANE_M, RANGE_M = 0.5, 6.0, 5.0
SIGMA_R, SIGMA_B = 0.05, math.radians(1.0)
NOISE = OdometryNoise(0.02, 0.02, 0.05)
NO_OUTLIERS = AssociationConfig(outlier_probability=1.0)  # simulated data has none: no outlier gate
TIMED_STEP_M = 0.04  # the paper scenario's motion between scans (0.2 m/s, 5 Hz)
TURN_RADIUS_M = 1.5
SINGLE_THREAD = {"OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}  # both filters alike


def lawnmower(side: float) -> np.ndarray:
    """Poses (n, 3) every 0.5 m along lanes 6 m apart covering [1, side - 1]^2, five stationary ones first."""
    ys = np.arange(1.0, side - 1.0 - LANE_M, LANE_M)
    poses = [np.array([1.0, ys[0], 0.0])] * 5  # standing still: phase I
    for k, y in enumerate(ys):
        x0, x1 = (1.0, side - 1.0) if k % 2 == 0 else (side - 1.0, 1.0)
        heading = 0.0 if x1 > x0 else math.pi
        for x in np.arange(x0, x1, math.copysign(STEP_M, x1 - x0)):  # a straight lane
            poses.append(np.array([x, y, heading]))
        if k + 1 < len(ys):  # a half-circle turn of radius LANE_M / 2 to the next lane
            sign = 1.0 if x1 > x0 else -1.0
            for a in np.arange(0.0, math.pi, STEP_M / (LANE_M / 2)):
                poses.append(np.array([x1 + sign * 0.5 * LANE_M * math.sin(a), y + 0.5 * LANE_M * (1 - math.cos(a)),
                                       heading + sign * a]))
    return np.asarray(poses)


def way_back(last: np.ndarray, count: int) -> np.ndarray:
    """``count`` poses 0.04 m apart from ``last``: a U-turn of radius 1.5 m away from the world's edge, then straight.

    The last lane is the one farthest up (largest y): the turn goes down, into the mapped area.
    """
    x, y, heading = last
    forward = np.array([math.cos(heading), math.sin(heading)])
    turn = -1.0 if forward[0] > 0 else 1.0  # clockwise when heading +x, so that the robot moves down
    out = []
    s = TIMED_STEP_M
    for k in range(1, count + 1):
        d = k * s
        arc = math.pi * TURN_RADIUS_M
        if d <= arc:
            a = d / TURN_RADIUS_M
            local = np.array([TURN_RADIUS_M * math.sin(a), turn * TURN_RADIUS_M * (1 - math.cos(a))])
            h = heading + turn * a
        else:
            local = np.array([-(d - arc), turn * 2 * TURN_RADIUS_M])
            h = heading + turn * math.pi
        c, sn = forward
        out.append(np.array([x + c * local[0] - sn * local[1], y + sn * local[0] + c * local[1], h]))
    return np.asarray(out)


@dataclass
class Scan:
    u: np.ndarray
    r: np.ndarray
    b: np.ndarray
    ids: np.ndarray


def scans(poses: np.ndarray, landmarks: np.ndarray, rng: np.random.Generator, first: np.ndarray | None = None
          ) -> list[Scan]:
    """Noisy odometry increments and 180-degree, 5 m range-bearing scans along ``poses`` (after ``first``)."""
    tree = cKDTree(landmarks)
    out = []
    prev = first
    for pose in poses:
        u = se2.between(prev, pose) if prev is not None else np.zeros(3)
        prev = pose
        if np.any(u != 0):
            d = math.hypot(u[0], u[1])
            u = u + rng.normal(0, [0.014 * math.sqrt(d), 0.014 * math.sqrt(d), 0.014 * math.sqrt(d) + 0.01 * abs(u[2])])
        ids = np.asarray(tree.query_ball_point(pose[:2], RANGE_M), dtype=np.int64)
        rel = se2.transform_points(se2.inverse(pose), landmarks[ids])
        r, b = np.hypot(rel[:, 0], rel[:, 1]), np.arctan2(rel[:, 1], rel[:, 0])
        keep = np.abs(b) <= math.pi / 2
        r = r[keep] + rng.normal(0, SIGMA_R, keep.sum())
        b = b[keep] + rng.normal(0, SIGMA_B, keep.sum())
        ok = r > 0.1
        out.append(Scan(u, r[ok], b[ok], ids[keep][ok]))
    return out


def rss_mb() -> float:
    """Current resident memory of this process (MB)."""
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * resource.getpagesize() / 2**20


def peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def timed(run_step, steps: list[Scan], budget_s: float = math.inf,  # type: ignore[no-untyped-def]
          min_steps: int = 10) -> tuple[np.ndarray, np.ndarray]:
    """Wall-clock and CPU seconds of each step (at least ``min_steps``, then until ``budget_s`` of wall clock)."""
    wall: list[float] = []
    cpu: list[float] = []
    start = time.perf_counter()
    for s in steps:
        tic, tic_cpu = time.perf_counter(), time.process_time()
        run_step(s)
        wall.append(time.perf_counter() - tic)
        cpu.append(time.process_time() - tic_cpu)
        if len(wall) >= min_steps and time.perf_counter() - start > budget_s:
            break
    return np.asarray(wall), np.asarray(cpu)


def one_size(n: int, args: argparse.Namespace) -> dict[str, object]:
    """Everything for one world size (run in its own process)."""
    cfg = LandmarkSimConfig(landmarks=n)
    landmarks = landmark_positions(cfg)
    rng = np.random.default_rng(args.seed)
    path = lawnmower(cfg.side_m)
    back = way_back(path[-1], args.settle + args.steps)
    warm = scans(path, landmarks, rng)
    tail = scans(back, landmarks, rng, first=path[-1])
    settle, test = tail[: args.settle], tail[args.settle:]
    rss0 = rss_mb()
    slam = DSlam(DSlamConfig(odometry_noise=NOISE, association_params=NO_OUTLIERS), clock=time.perf_counter)
    tic = time.perf_counter()
    for s in warm + settle:
        slam.predict(s.u)
        slam.observe(s.r, s.b, s.ids, SIGMA_R, SIGMA_B)
    warm_s = time.perf_counter() - tic
    slam.profile.clear()
    methods: dict[str, int] = {}
    refreshes = slam.covariance.refreshes

    def dslam_step(s: Scan) -> None:
        slam.predict(s.u)
        res = slam.observe(s.r, s.b, s.ids, SIGMA_R, SIGMA_B)
        if res.recovery is not None:
            methods[res.recovery.method] = methods.get(res.recovery.method, 0) + 1

    t_d, c_d = timed(dslam_step, test)
    row: dict[str, object] = {
        "N": n, "mapped": slam.n, "warmup_scans": len(warm) + len(settle), "warmup_s": warm_s,
        "dslam_mean_ms": 1e3 * t_d.mean(), "dslam_p95_ms": 1e3 * float(np.percentile(t_d, 95)),
        "dslam_max_ms": 1e3 * float(t_d.max()), "dslam_cpu_mean_ms": 1e3 * c_d.mean(),
        "dslam_cpu_p95_ms": 1e3 * float(np.percentile(c_d, 95)), "timed_steps": len(t_d), "recovery_methods": methods,
        "covariance_refreshes": slam.covariance.refreshes - refreshes,
        "vicinity_features": len(slam.covariance.features),
        "nnz_blocks_per_landmark": slam.info.nnz_blocks / slam.n,
        "dslam_array_mb": (slam.info.nbytes + slam.recovery.nbytes + slam.covariance.nbytes) / 2**20,
        "dslam_rss_growth_mb": rss_mb() - rss0, "dslam_peak_rss_mb": peak_rss_mb(),
        "stages_ms": {k: 1e3 * float(np.sum(v)) / len(t_d) for k, v in slam.profile.items()},
    }
    if args.check:
        exact = direct(slam.info, np.array(slam.info.vector)).reshape(-1, 2)
        err = np.hypot(*(exact - slam.recovery.x.reshape(-1, 2)).T)
        row["recovery_error_max_mm"] = 1e3 * float(err.max())
        row["recovery_error_median_mm"] = 1e3 * float(np.median(err))
        near = slam.vicinity(slam.pose[:2])
        row["recovery_error_vicinity_max_mm"] = 1e3 * float(err[near].max()) if near else 0.0
    ekf_gb = 8 * (3 + 2 * (slam.n + 50)) ** 2 / 2**30
    if n <= args.max_ekf and ekf_gb <= args.ekf_max_gb:
        ekf = EkfSlam(EkfSlamConfig(odometry_noise=NOISE, association_params=NO_OUTLIERS), capacity=slam.n + 50)
        k = slam.n
        ekf.dim = 3 + 2 * k
        ekf._x[:3] = slam.pose
        ekf._x[3:ekf.dim] = slam.estimates().reshape(-1)
        p = ekf.P
        p[:3, :3] = slam.pose_cov
        p[3:, 3:] = 0.002
        p[3:, 3:] += 0.01 * np.eye(2 * k)
        ekf.feature_ids = list(slam.feature_ids)
        ekf.by_id = {i: f for f, i in enumerate(slam.feature_ids)}
        ekf.max_range = slam.max_range
        def ekf_step(s: Scan) -> None:
            ekf.predict(s.u)
            ekf.observe(s.r, s.b, s.ids, SIGMA_R, SIGMA_B)

        t_e, c_e = timed(ekf_step, test, args.ekf_budget_s)
        n_e = len(t_e)
        row.update(ekf_mean_ms=1e3 * t_e.mean(), ekf_p95_ms=1e3 * float(np.percentile(t_e, 95)), ekf_steps=n_e,
                   ekf_cpu_mean_ms=1e3 * c_e.mean(), dslam_mean_same_steps_ms=1e3 * t_d[:n_e].mean(),
                   ratio=float(t_d[:n_e].mean() / t_e.mean()), cpu_ratio=float(c_d[:n_e].mean() / c_e.mean()),
                   peak_rss_mb=peak_rss_mb())
    return row


def recording(duration: float, seed: int, out: Path) -> Path:
    """The paper-scenario recording of ``duration`` s (simulated by the parent process, so that its memory
    does not count in the child's peak)."""
    from slamreplay.recorder.sim import simulate_landmarks

    rec = out / f"sim-{int(duration)}s-seed{seed}.mcap"
    if not rec.exists():
        tmp = rec.with_suffix(".partial")
        simulate_landmarks(tmp, LandmarkSimConfig(duration_s=duration), seed=seed)
        tmp.replace(rec)
    return rec


def duration_run(duration: float, seed: int, out: Path) -> dict[str, object]:
    """D-SLAM over one paper-scenario recording of ``duration`` s (module docstring; run in its own process)."""
    from slamreplay.algorithms.common.motion import between1
    from slamreplay.recorder.messages import TOPIC_ODOM, TOPIC_RANGE_BEARING
    from slamreplay.replay.engine.reader import RecordingReader

    rec = recording(duration, seed, out)
    rss0, peak0 = rss_mb(), peak_rss_mb()
    slam = DSlam(DSlamConfig(odometry_noise=NOISE))
    old_bytes = 0
    record = slam.map_log.recast

    def counted(features: list[int], z_map: np.ndarray, r_map: np.ndarray) -> None:
        nonlocal old_bytes  # what the previous design kept: z, R and the feature ids of every measurement
        old_bytes += 8 * (len(z_map) + r_map.size + len(features))
        record(features, z_map, r_map)

    slam.map_log.recast = counted  # type: ignore[method-assign]
    prev = None
    times: list[float] = []
    loops: list[int] = []
    for env in RecordingReader(rec).messages([TOPIC_ODOM, TOPIC_RANGE_BEARING]):
        msg = env.msg
        if env.topic == TOPIC_ODOM:
            odom = msg.xy_yaw  # type: ignore[union-attr]
            if prev is not None:
                slam.predict(between1(prev, odom))
            prev = odom
            continue
        tic = time.perf_counter()
        res = slam.observe(msg.ranges_m, msg.bearings_rad, msg.landmark_ids,  # type: ignore[union-attr]
                           msg.range_sigma_m, msg.bearing_sigma_rad)  # type: ignore[union-attr]
        times.append(time.perf_counter() - tic)
        if res.loop_closure:
            loops.append(len(times) - 1)
    tic = time.perf_counter()
    slam.finalize()
    final_s = time.perf_counter() - tic
    t = 1e3 * np.asarray(times)
    after = sorted({k for i in loops for k in range(i, min(len(t), i + 26))})
    log = slam.map_log
    return {"duration_s": duration, "scans": len(t), "mapped": slam.n, "loop_closures": len(loops),
            "rss_growth_mb": rss_mb() - rss0, "peak_rss_growth_mb": peak_rss_mb() - peak0,
            "rss_before_mb": rss0, "peak_rss_mb": peak_rss_mb(),
            "dslam_array_mb": (slam.info.nbytes + slam.recovery.nbytes + slam.covariance.nbytes + log.nbytes) / 2**20,
            "summary_entries": log.entries,
            "summary_kb": log.nbytes / 1e3, "measurements": len(log), "full_log_kb": old_bytes / 1e3,
            "step_mean_ms": float(t.mean()), "step_p95_ms": float(np.percentile(t, 95)),
            "loop_step_mean_ms": float(t[loops].mean()) if loops else float("nan"),
            "loop_step_max_ms": float(t[loops].max()) if loops else float("nan"),
            "after_loop_mean_ms": float(t[after].mean()) if after else float("nan"),
            "after_loop_p95_ms": float(np.percentile(t[after], 95)) if after else float("nan"),
            "finalize_s": final_s}


def fmt(v: object) -> str:
    if isinstance(v, float):
        return f"{v:.3g}" if abs(v) < 1000 else f"{v:.0f}"
    if isinstance(v, dict):
        return " ".join(f"{k}:{fmt(x)}" for k, x in v.items())
    return str(v)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--sizes", type=int, nargs="*", default=[250, 1000, 4000, 16000])
    parser.add_argument("--steps", type=int, default=300, help="timed scans per size")
    parser.add_argument("--settle", type=int, default=150, help="untimed scans at the paper's pace before timing")
    parser.add_argument("--max-ekf", type=int, default=16000, help="largest N for EKF-SLAM")
    parser.add_argument("--ekf-max-gb", type=float, default=4.0, help="largest EKF covariance (GB)")
    parser.add_argument("--ekf-max-step-s", type=float, default=2.0,
                        help="no EKF for larger N after a size with a slower mean step")
    parser.add_argument("--ekf-budget-s", type=float, default=90.0, help="EKF seconds of timed steps per size")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--check", action="store_true", help="compare the recovered state with a direct solve")
    parser.add_argument("--one", type=int, help=argparse.SUPPRESS)  # internal: run one size, print JSON
    parser.add_argument("--json", type=Path, help="also write the rows to this file")
    parser.add_argument("--durations", type=float, nargs="*",
                        help="instead: D-SLAM memory and loop-closure step times on paper-scenario runs this long (s)")
    parser.add_argument("--out", type=Path, default=Path("/tmp/dslam-scaling"), help="--durations: recordings here")
    parser.add_argument("--duration-one", type=float, help=argparse.SUPPRESS)  # internal: one duration, print JSON
    args = parser.parse_args()
    if args.one is not None:
        print(json.dumps(one_size(args.one, args)))
        return
    if args.duration_one is not None:
        print(json.dumps(duration_run(args.duration_one, args.seed, args.out)))
        return
    if args.durations:
        if any(not d > 0 for d in args.durations):
            sys.exit("--durations must be > 0 seconds")
        args.out.mkdir(parents=True, exist_ok=True)
        rows = []
        for d in args.durations:
            recording(d, args.seed, args.out)
            cmd = [sys.executable, __file__, "--duration-one", str(d), "--seed", str(args.seed), "--out", str(args.out)]
            done = subprocess.run(cmd, capture_output=True, text=True, env={**os.environ, **SINGLE_THREAD})
            if done.returncode:
                sys.exit(f"duration {d} s failed:\n{done.stderr}")
            rows.append(json.loads(done.stdout.strip().splitlines()[-1]))
            print(json.dumps(rows[-1]), flush=True)
        if args.json:
            args.json.write_text(json.dumps(rows, indent=1))
        keys = list(rows[0])
        print("\n| " + " | ".join(keys) + " |\n" + "|---" * len(keys) + "|")
        for r in rows:
            print("| " + " | ".join(fmt(r[k]) for k in keys) + " |")
        return
    rows = []
    max_ekf = args.max_ekf
    for n in args.sizes:
        cmd = [sys.executable, __file__, "--one", str(n), "--steps", str(args.steps), "--settle", str(args.settle),
               "--max-ekf", str(max_ekf), "--ekf-max-gb", str(args.ekf_max_gb), "--ekf-budget-s",
               str(args.ekf_budget_s), "--seed", str(args.seed)] + (["--check"] if args.check else [])
        done = subprocess.run(cmd, capture_output=True, text=True, env={**os.environ, **SINGLE_THREAD})
        if done.returncode:
            sys.exit(f"N = {n} failed:\n{done.stderr}")
        row = json.loads(done.stdout.strip().splitlines()[-1])
        rows.append(row)
        print(json.dumps(row), flush=True)
        if "ekf_mean_ms" in row and row["ekf_mean_ms"] > 1e3 * args.ekf_max_step_s:
            max_ekf = min(max_ekf, n)
        elif "ekf_mean_ms" not in row:
            max_ekf = min(max_ekf, n - 1)
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))
    cols = ("N", "mapped", "dslam_mean_ms", "dslam_p95_ms", "dslam_cpu_mean_ms", "ekf_mean_ms", "ekf_p95_ms",
            "ekf_cpu_mean_ms", "ekf_steps", "ratio", "cpu_ratio", "dslam_array_mb", "dslam_rss_growth_mb",
            "peak_rss_mb", "warmup_s")
    print("\n| " + " | ".join(cols) + " |")
    print("|---" * len(cols) + "|")
    for r in rows:
        print("| " + " | ".join(fmt(r.get(c, "-")) for c in cols) + " |")
    print()
    for r in rows:
        check = (f"; recovered state vs I^-1 i: max {fmt(r['recovery_error_max_mm'])} mm, vicinity max "
                 f"{fmt(r['recovery_error_vicinity_max_mm'])} mm" if "recovery_error_max_mm" in r else "")
        print(f"N = {r['N']}: stages (ms/step) {fmt(r['stages_ms'])}; recovery {fmt(r['recovery_methods'])}; "
              f"covariance refreshes {r['covariance_refreshes']}; p95 {fmt(r['dslam_p95_ms'])} ms, max "
              f"{fmt(r['dslam_max_ms'])} ms{check}")
    if len(rows) >= 2:
        ns = np.log([float(r["N"]) for r in rows])
        fits = (("dslam_mean_ms", "D-SLAM mean step time"), ("dslam_p95_ms", "D-SLAM p95 step time"),
                ("dslam_cpu_mean_ms", "D-SLAM mean step CPU time"),
                ("dslam_array_mb", "D-SLAM array memory"), ("dslam_rss_growth_mb", "D-SLAM resident memory"))
        for key, label in fits:
            slope = np.polyfit(ns, np.log([float(r[key]) for r in rows]), 1)[0]  # type: ignore[arg-type]
            print(f"{label} ~ N^{slope:.2f} over N = {rows[0]['N']}..{rows[-1]['N']}")
    for r in rows:
        if "ratio" in r:
            print(f"N = {r['N']}: D-SLAM / EKF-SLAM = {fmt(r['ratio'])} over {r['ekf_steps']} steps "
                  f"(EKF {1 / float(r['ratio']):.1f}x slower)")  # type: ignore[arg-type]


if __name__ == "__main__":
    main()
