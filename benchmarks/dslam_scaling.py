"""D-SLAM against EKF-SLAM per-step time as the map grows: the O(N) claim of D-SLAM section 3.3.

Worlds are ``sim-landmarks`` landmark grids (3 m spacing, so the same density) of N landmarks on a
growing square. The robot sweeps the world on a lawnmower path (lanes 6 m apart, one 180-degree
5 m scan every 0.5 m, the simulator's noise levels) so that it maps the whole world; the path
starts with five stationary scans (D-SLAM's phase I). For each N:

1. warm-up, untimed: D-SLAM (full algorithm, every step) over the path until every landmark is
   mapped, i.e. a map of N features;
2. timed: ``--steps`` more scans along a second sweep of the world, 0.04 m apart as in the paper
   scenario (re-observations: the steady state of a robot working in a mapped area; the robot
   is placed there with a small uncertainty), for D-SLAM and, up to ``--max-ekf`` landmarks,
   for EKF-SLAM started from the same map (D-SLAM's estimates, with a dense covariance: the cost
   of an EKF step does not depend on the covariance's values).

Prints per-step mean and p95 times, their ratio D-SLAM/EKF, D-SLAM's stage times, the memory of
D-SLAM's state per landmark, and the exponent b of a least-squares fit ``t = a N^b`` of D-SLAM's
mean step time. Run: ``.venv/bin/python benchmarks/dslam_scaling.py [--sizes 250 500 ...]
[--steps 200] [--max-ekf 4000]`` (about 15 minutes with the defaults on two cores).
"""

from __future__ import annotations

import argparse
import math
import time
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from algorithms.common import se2
from algorithms.common.association import AssociationConfig
from algorithms.common.motion import OdometryNoise
from algorithms.dslam import DSlam, DSlamConfig
from algorithms.ekfslam import EkfSlam, EkfSlamConfig
from recorder.sim.landmarks import LandmarkSimConfig, landmark_positions

STEP_M, LANE_M, RANGE_M = 0.5, 6.0, 5.0
SIGMA_R, SIGMA_B = 0.05, math.radians(1.0)
NOISE = OdometryNoise(0.02, 0.02, 0.05)
NO_OUTLIERS = AssociationConfig(outlier_probability=1.0)  # simulated data has none: no outlier gate
TIMED_STEP_M = 0.04  # timed steps: the paper scenario's motion between scans (0.2 m/s, 5 Hz)


def lawnmower(side: float, offset: float = 0.0, step: float = STEP_M) -> np.ndarray:
    """Poses (n, 3) every ``step`` along lanes 6 m apart covering [1, side - 1]^2 (lanes shifted by ``offset``)."""
    ys = np.arange(1.0 + offset, side - 1.0 - LANE_M, LANE_M)
    poses = [np.array([1.0, ys[0], 0.0])] * 5  # standing still: phase I
    for k, y in enumerate(ys):
        x0, x1 = (1.0, side - 1.0) if k % 2 == 0 else (side - 1.0, 1.0)
        heading = 0.0 if x1 > x0 else math.pi
        for x in np.arange(x0, x1, math.copysign(step, x1 - x0)):  # a straight lane
            poses.append(np.array([x, y, heading]))
        if k + 1 < len(ys):  # a half-circle turn of radius LANE_M / 2 to the next lane
            sign = 1.0 if x1 > x0 else -1.0
            for a in np.arange(0.0, math.pi, step / (LANE_M / 2)):
                poses.append(np.array([x1 + sign * 0.5 * LANE_M * math.sin(a), y + 0.5 * LANE_M * (1 - math.cos(a)),
                                       heading + sign * a]))
    return np.asarray(poses)


@dataclass
class Scan:
    u: np.ndarray
    r: np.ndarray
    b: np.ndarray
    ids: np.ndarray


def scans(poses: np.ndarray, landmarks: np.ndarray, rng: np.random.Generator) -> list[Scan]:
    """Noisy odometry increments and 180-degree, 5 m range-bearing scans along ``poses``."""
    tree = cKDTree(landmarks)
    out = []
    for k, pose in enumerate(poses):
        u = se2.between(poses[k - 1], pose) if k else np.zeros(3)
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


def dslam_bytes(slam: DSlam) -> int:
    """Bytes held by D-SLAM's map state: I (blocks and CSR), i, x, residual and the covariance snapshot."""
    info = slam.info
    base, delta = info.matrices()
    total = info._values.nbytes + info._rows.nbytes + info._cols.nbytes + info._vec.nbytes
    for m in (base, delta):
        if m is not None:
            total += m.data.nbytes + m.indices.nbytes + m.indptr.nbytes
    rec = slam.recovery
    return total + rec.x.nbytes + rec.r.nbytes + rec.inv_blocks.nbytes + slam.covariance.sigma.nbytes \
        + slam.covariance._columns.nbytes


def timed(run_step, steps: list[Scan]) -> np.ndarray:  # type: ignore[no-untyped-def]
    out = []
    for s in steps:
        tic = time.perf_counter()
        run_step(s)
        out.append(time.perf_counter() - tic)
    return np.asarray(out)


def bench(n: int, timed_steps: int, max_ekf: int, seed: int) -> dict[str, float]:
    cfg = LandmarkSimConfig(landmarks=n)
    landmarks = landmark_positions(cfg)
    rng = np.random.default_rng(seed)
    warm = scans(lawnmower(cfg.side_m), landmarks, rng)
    slam = DSlam(DSlamConfig(odometry_noise=NOISE, association_params=NO_OUTLIERS), clock=time.perf_counter)
    tic = time.perf_counter()
    for s in warm:
        slam.predict(s.u)
        slam.observe(s.r, s.b, s.ids, SIGMA_R, SIGMA_B)
    warm_s = time.perf_counter() - tic
    second = lawnmower(cfg.side_m, offset=LANE_M / 2, step=TIMED_STEP_M)[5:]
    second = second[len(second) // 3:len(second) // 3 + timed_steps]
    start = lawnmower(cfg.side_m)[0]  # the map frame is the robot's start pose
    # jump (untimed) to the second sweep: the robot is told where it is, with a small uncertainty
    slam.pose, slam.pose_cov = se2.between(start, second[0]), np.diag([0.01, 0.01, 0.001])
    test = scans(np.concatenate([second[:1], second]), landmarks, rng)[1:]
    slam.profile.clear()
    t_d = timed(lambda s: (slam.predict(s.u), slam.observe(s.r, s.b, s.ids, SIGMA_R, SIGMA_B)), test)
    row = {"N": n, "mapped": slam.n, "warmup_steps": len(warm), "warmup_s": warm_s, "dslam_mean_ms": 1e3 * t_d.mean(),
           "dslam_p95_ms": 1e3 * np.percentile(t_d, 95), "bytes_per_landmark": dslam_bytes(slam) / slam.n,
           "nnz_blocks_per_landmark": slam.info.nnz_blocks / slam.n}
    for stage, values in slam.profile.items():
        row[f"{stage}_ms_per_step"] = 1e3 * float(np.sum(values)) / len(test)
    if n <= max_ekf:
        ekf = EkfSlam(EkfSlamConfig(odometry_noise=NOISE, association_params=NO_OUTLIERS), capacity=slam.n + 200)
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
        t_e = timed(lambda s: (ekf.predict(s.u), ekf.observe(s.r, s.b, s.ids, SIGMA_R, SIGMA_B)), test)
        row.update(ekf_mean_ms=1e3 * t_e.mean(), ekf_p95_ms=1e3 * np.percentile(t_e, 95),
                   ratio=t_d.mean() / t_e.mean())
        del ekf
    return row


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--sizes", type=int, nargs="*", default=[250, 500, 1000, 2000, 4000, 8000, 16000])
    parser.add_argument("--steps", type=int, default=200)
    parser.add_argument("--max-ekf", type=int, default=4000)
    parser.add_argument("--seed", type=int, default=1)
    args = parser.parse_args()
    rows = []
    cols = ("N", "mapped", "dslam_mean_ms", "dslam_p95_ms", "ekf_mean_ms", "ekf_p95_ms", "ratio",
            "recover_ms_per_step", "covariance_ms_per_step", "localize_ms_per_step", "bytes_per_landmark",
            "nnz_blocks_per_landmark", "warmup_steps", "warmup_s")
    print("| " + " | ".join(cols) + " |")
    print("|---" * len(cols) + "|")
    for n in args.sizes:
        row = bench(n, args.steps, args.max_ekf, args.seed)
        rows.append(row)
        print("| " + " | ".join(f"{row[c]:.4g}" if isinstance(row.get(c), float) else str(row.get(c, "-"))
                                for c in cols) + " |", flush=True)
    ns = np.array([r["N"] for r in rows], dtype=float)
    td = np.array([r["dslam_mean_ms"] for r in rows])
    if len(rows) >= 2:
        slope = np.polyfit(np.log(ns), np.log(td), 1)[0]
        print(f"\nD-SLAM mean step time ~ N^{slope:.2f} over N = {int(ns[0])}..{int(ns[-1])}")
    for r in rows:
        if "ratio" in r:
            print(f"N = {r['N']}: D-SLAM / EKF-SLAM = {r['ratio']:.4f} (EKF {1 / r['ratio']:.1f}x slower)")


if __name__ == "__main__":
    main()
