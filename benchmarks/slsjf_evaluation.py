"""SLSJF against EKF-SLAM (issue 29's figures): Victoria Park, MRCLAM Dataset 6 robots 1-5, the paper scenario.

For each recording both pipelines run with the recording's own sensor model and no setting; SLSJF also
linearized once (``--preset paper``) where ``--paper`` is given. Prints a table per data set with the
ratios SLSJF / EKF-SLAM (landmark RMSE, robot ATE) and writes ``--json``.

Run: ``.venv/bin/python benchmarks/slsjf_evaluation.py --out /tmp/slsjf-eval --data ../shared/data
[--seeds 1 2 3] [--duration-s 1800] [--robots 1 2 3 4 5] [--skip-vp] [--paper] [--vp-band] [--batch 5]
[--batch-incremental] [--causal-every 300] [--set KEY=VALUE]
[--json out.json]``.
Run directories under ``--out`` are reused when their metrics exist (a fresh ``--out`` after a code change).
"""

from __future__ import annotations

import argparse
import json
import math
import shutil
from pathlib import Path
from typing import Any

import numpy as np
from scipy.stats import t as t_dist

from slamreplay.algorithms.common import se2
from slamreplay.recorder.importers.mrclam import import_mrclam
from slamreplay.recorder.sim import LandmarkSimConfig, simulate_landmarks
from slamreplay.replay.runs.run import run_recording

KEYS = ("landmarks_mapped", "landmark_rmse_m", "ape_rmse_m", "landmark_nees_mean", "robot_nees_mean")


def metrics(recording: Path, pipeline: str, out: Path, preset: str | None = None,
            config: dict[str, str] | None = None) -> dict[str, float]:
    if not (out / "metrics.json").exists():
        run_recording(recording, pipeline, out, seed=0, preset=preset, config=config)
    doc = json.loads((out / "metrics.json").read_text())["metrics"]
    return {k: float(v["value"]) for k, v in doc.items()}


def row(name: str, ekf: dict[str, float], sl: dict[str, float]) -> dict[str, Any]:
    ratio = {k: sl[k] / ekf[k] for k in ("landmark_rmse_m", "ape_rmse_m") if ekf.get(k)}
    print(f"  {name:<22} " + "  ".join(f"{k}={ekf.get(k, math.nan):.4g}/{sl.get(k, math.nan):.4g}" for k in KEYS)
          + "  ratios " + " ".join(f"{k}={v:.2f}" for k, v in ratio.items()))
    return {"name": name, "ekfslam": ekf, "slsjf": sl, "ratio": ratio}


def vp_band(vp: Path, data_dir: Path, out: Path) -> dict[str, Any]:
    """The tree NEES band on Victoria Park, where the reference is the batch optimum of the same measurements.

    GTSAM's optimum (the file's weights, ``landmark_reference.victoria_park_reference``), its own joint covariance
    ``P_ref`` (first order, under the measured noise: ``landmark_reference.reference_covariance``) and each filter's
    final joint covariance ``P`` of the 151 trees give the band of a consistent filter's mean NEES, its errors from
    that optimum having covariance ``P - P_ref`` (``metrics.mean_nees_band``); when ``P - P_ref`` is not positive
    semi-definite there is none, and why is printed.

    GTSAM's optimum weighs the measurements as GTSAM does, not with the noise the filters are given, so it is not
    the efficient estimate under their model. The optimum under their noise (``landmark_reference.optimum_under``;
    the recording's reference, ``landmark_reference.recording_reference``, when the filters are given the recording's
    sensor model) is: printed are its distance from GTSAM's, each filter's tree RMSE and mean tree NEES against it,
    the upper end a consistent filter's NEES stays below there (its errors have covariance ``P - P_opt``, below
    ``P``: the upper end of the band against the truth), and ``P`` over ``P_opt`` whitened (min / median / max
    eigenvalue).
    """
    from slamreplay.recorder.importers.victoria_park import read_victoria_park
    from slamreplay.replay.evaluation.landmark_reference import (
        measured_scales,
        optimum_under,
        reference_covariance,
        victoria_park_reference,
    )
    from slamreplay.replay.evaluation.metrics import marginal_blocks, mean_nees_band
    from slamreplay.replay.pipelines.ekfslam import EkfSlamPipeline
    from slamreplay.replay.pipelines.landmark_slam import landmark_scores
    from slamreplay.replay.pipelines.slsjf import SlsjfPipeline

    data = read_victoria_park(data_dir)
    print("Victoria Park: GTSAM's optimum and its covariance (1-3 minutes)")
    poses, landmarks, _ = victoria_park_reference(data)
    p_ref = reference_covariance(data, poses, landmarks, measured_scales(data, poses, landmarks))
    result: dict[str, Any] = {}
    opt: dict[str, Any] = {}  # the optimum under the noise the filters are given (landmark_reference.optimum_under)
    kept: dict[str, Any] = {}
    for base in (EkfSlamPipeline, SlsjfPipeline):

        class Keep(base):  # type: ignore[misc, valid-type]
            def finalize(self) -> None:
                super().finalize()
                kept[self.name] = self

        band_run = out / f"vp-{base.name}-band"  # run again: the filter's final covariance is not in the run
        shutil.rmtree(band_run, ignore_errors=True)
        run_recording(vp, Keep, band_run, seed=0)
        pipe = kept[base.name]
        order = [pipe.filter.by_id[int(i)] for i in data.landmark_ids]
        k = len(order)
        rot = np.kron(np.eye(k), se2.rot(pipe.T[2]))  # the map frame's joint covariance, in the world frame
        joint = rot @ pipe.observed_joint_covariance(order) @ rot.T
        blocks = marginal_blocks(joint)
        trees = pipe.to_world_xy(pipe.filter.estimates())
        pairs = [(f, t) for t, f in enumerate(order)]
        nees = landmark_scores(trees, landmarks, pairs, lambda _, b=blocks: b)["landmark_nees_mean"]
        row: dict[str, Any] = {"landmark_nees_mean": nees, "band_if_reference_were_truth": mean_nees_band(joint)}
        w = np.linalg.eigvalsh(joint - p_ref)
        row["directions_below_reference"] = int(np.sum(w < 0))
        row["trace_ratio_filter_to_reference_median"] = float(np.median(
            np.trace(blocks, axis1=1, axis2=2) / np.trace(marginal_blocks(p_ref), axis1=1, axis2=2)))
        try:
            row["band"] = mean_nees_band(joint, reference_cov=p_ref)
        except ValueError as err_:
            row["band"], row["why_no_band"] = None, str(err_)
        ratio = row["trace_ratio_filter_to_reference_median"]  # the reference: GTSAM's optimum, here
        print(f"  {base.name}: tree NEES against GTSAM's optimum {nees:.3g}; band against it: "
              + (f"[{row['band'][0]:.3g}, {row['band'][1]:.3g}]" if row["band"] else f"none ({row['why_no_band']})")
              + f"; tree covariance / the reference's (trace, median) {ratio:.2f}")
        if not opt:  # the filters' noise is the recording's sensor model: known once a pipeline has read it
            cfg = pipe.config
            _, opt["landmarks"], opt["cov"] = optimum_under(data, cfg.odometry_noise(), cfg.range_sigma_m,
                                                            cfg.bearing_sigma_rad, poses, landmarks)
            own = landmark_scores(opt["landmarks"], landmarks, [(t, t) for t in range(k)],
                                  lambda _: marginal_blocks(opt["cov"]))
            result["declared_optimum"] = {
                "tree_rmse_from_reference_m": own["landmark_rmse_m"],
                "tree_nees_against_reference": own["landmark_nees_mean"],
                "noise": {"odometry": str(cfg.odometry_noise()), "range_sigma_m": cfg.range_sigma_m,
                          "bearing_sigma_rad": cfg.bearing_sigma_rad}}
            print(f"  the optimum under the noise the filters are given: {own['landmark_rmse_m']:.3g} m "
                  f"(tree RMSE) from GTSAM's optimum, whose tree NEES against it is "
                  f"{own['landmark_nees_mean']:.3g}")
        against = landmark_scores(trees, opt["landmarks"], pairs, lambda _, b=blocks: b)
        chol = np.linalg.cholesky(opt["cov"])
        ratios = np.linalg.eigvalsh(np.linalg.solve(chol, np.linalg.solve(chol, joint).T))  # P_opt^-1/2 P P_opt^-T/2
        row["against_declared_optimum"] = {
            "tree_rmse_m": against["landmark_rmse_m"], "tree_nees": against["landmark_nees_mean"],
            "upper": mean_nees_band(joint)[1],
            "covariance_ratio_min_median_max": [float(ratios.min()), float(np.median(ratios)), float(ratios.max())]}
        a = row["against_declared_optimum"]
        print(f"  {base.name} against that optimum: tree RMSE {a['tree_rmse_m']:.3g} m, tree NEES {a['tree_nees']:.3g} "
              f"(a consistent filter's is below {a['upper']:.3g}); its covariance over the optimum's, whitened: "
              + " / ".join(f"{v:.2f}" for v in a["covariance_ratio_min_median_max"]) + " (min / median / max)")
        result[base.name] = row
    return result


def batch_optimum(recording: Path, out: Path, incremental: bool = False, causal_every: int = 0) -> dict[str, Any]:
    """The full least-squares optimum of a landmark recording (every scan a pose), scored as the filters are.

    EKF-SLAM replays the recording once to collect what a filter is given: the odometry between scans, composed
    with its noise model's covariance, and each scan's sightings with their sigmas; those make a pose-landmark
    graph (``landmark_graph.LandmarkGraph``, known ids) solved by Levenberg-Marquardt (``optimize``) started from
    EKF-SLAM's own estimate (its pose after each scan, its final map); with ``incremental`` by ``solve_incremental``
    from dead reckoning instead (about 25 minutes for an 1800 s paper-scenario recording of 9,000 poses, against
    well under a minute). Its landmark RMSE tells what the best estimate from these measurements achieves: a filter
    nearer the truth than that on one seed is lucky, not better.

    ``causal_every`` > 0: the same for the robot. A filter's pose at a scan can use only the measurements up to it,
    so its yardstick is not the optimum's pose there (smoothed by later sightings) but the last pose of the optimum
    of the measurements up to that scan (``landmark_graph.optimize`` on the graph cut there, warm-started from the
    previous cut). That is computed at every ``causal_every``-th scan, and the position error there of that causal
    optimum, of EKF-SLAM and of SLSJF (run again, its defaults) is returned as an RMSE over those scans.
    """
    from slamreplay.algorithms.common.landmark_graph import (
        LandmarkGraph,
        LsqConfig,
        _subgraph,
        optimize,
        solve_incremental,
    )
    from slamreplay.algorithms.common.rangebearing import scan_sigmas
    from slamreplay.algorithms.slsjf.filter import compose_cov
    from slamreplay.replay.pipelines.ekfslam import EkfSlamPipeline
    from slamreplay.replay.pipelines.slsjf import SlsjfPipeline

    steps: list[tuple[np.ndarray, np.ndarray]] = []  # (increment since the last scan, its covariance) per scan
    scans: list[tuple[np.ndarray, np.ndarray, np.ndarray, float, float]] = []
    filtered: list[np.ndarray] = []  # EKF-SLAM's pose after each scan: where Levenberg-Marquardt starts
    kept: dict[str, Any] = {}

    class Recorder:
        """The EKF-SLAM filter, and what it was given."""

        def __init__(self, inner: Any) -> None:
            self.inner, self.acc, self.cov = inner, np.zeros(3), np.zeros((3, 3))

        def __getattr__(self, name: str) -> Any:
            return getattr(self.inner, name)

        def predict(self, u: Any) -> None:
            u = np.asarray(u, np.float64)
            self.cov = compose_cov(self.acc, self.cov, u, self.inner.config.odometry_noise.covariance(u))
            self.acc = se2.compose(self.acc, u)
            self.inner.predict(u)

        def observe(self, r: Any, b: Any, ids: Any = None, sr: float = 0.0, sb: float = 0.0) -> Any:
            steps.append((self.acc, self.cov))
            self.acc, self.cov = np.zeros(3), np.zeros((3, 3))
            cfg = self.inner.config
            scans.append((np.asarray(r, np.float64), np.asarray(b, np.float64), np.asarray(ids, np.int64),
                          *scan_sigmas(sr, sb, cfg.default_range_sigma_m, cfg.default_bearing_sigma_rad)))
            result = self.inner.observe(r, b, ids, sr, sb)
            filtered.append(np.array(self.inner.pose, np.float64))
            return result

    truth: list[np.ndarray] = []  # the true pose at each scan, in the filter's frame (NaN where unknown)

    class Collect(EkfSlamPipeline):
        def make_filter(self, mode: str) -> Any:
            return Recorder(super().make_filter(mode))

        def _robot_nees(self, t: int, res: Any) -> None:  # called once per scan, after it
            at = self._truth_pose_at(t)
            truth.append(np.full(3, np.nan) if at is None else se2.between(self.T, at))
            super()._robot_nees(t, res)

        def finalize(self) -> None:
            super().finalize()
            kept["pipe"] = self

    shutil.rmtree(out, ignore_errors=True)  # a scratch run, replaced each time
    run_recording(recording, Collect, out, seed=0)
    pipe = kept["pipe"]
    ids = sorted({int(i) for _, _, scan_ids, _, _ in scans for i in scan_ids.tolist()})
    index = {i: k for k, i in enumerate(ids)}
    n = len(scans)
    obs = [(k, index[int(i)], (r[j], b[j]), np.diag([1 / sr**2, 1 / sb**2]))
           for k, (r, b, scan_ids, sr, sb) in enumerate(scans) for j, i in enumerate(scan_ids.tolist())]
    graph = LandmarkGraph(n, len(ids), np.arange(n - 1), np.arange(1, n), np.array([u for u, _ in steps[1:]]),
                          np.array([np.linalg.inv(c + 1e-12 * np.eye(3)) for _, c in steps[1:]]),
                          np.array([o[0] for o in obs]), np.array([o[1] for o in obs]), np.array([o[2] for o in obs]),
                          np.array([o[3] for o in obs]))
    # the graph's first pose is the first scan's, at the origin; the filter's frame holds it at steps[0]
    start = steps[0][0]
    ekf = pipe.filter  # EKF-SLAM's estimate in the graph's frame: where Levenberg-Marquardt starts
    init_poses = np.array([se2.between(start, p) for p in filtered])
    init_lms = se2.transform_points(se2.inverse(start), ekf.estimates()[[ekf.by_id[i] for i in ids]])
    res = (solve_incremental(graph, LsqConfig()) if incremental
           else optimize(graph, init_poses, init_lms, LsqConfig()))
    world = pipe.to_world_xy(se2.transform_points(start, res.landmarks))
    lookup = {int(i): k for k, i in enumerate(pipe.truth_ids.tolist())}
    err = np.array([world[index[i]] - pipe.truth_xy[lookup[i]] for i in ids if i in lookup])
    result = {"landmark_rmse_m": float(np.sqrt(np.mean(np.sum(err**2, axis=1)))), "mean_error_m": err.mean(0).tolist(),
              "chi2": float(res.chi2), "poses": n, "iterations": res.iterations, "converged": bool(res.converged)}
    if causal_every <= 0:
        return result
    slsjf_poses: list[np.ndarray] = []

    class Track(SlsjfPipeline):
        def _robot_nees(self, t: int, res: Any) -> None:
            slsjf_poses.append(np.array(res.pose, np.float64))
            super()._robot_nees(t, res)

    track_dir = out.parent / f"{out.name}-slsjf"
    shutil.rmtree(track_dir, ignore_errors=True)
    run_recording(recording, Track, track_dir, seed=0)
    poses, lms = init_poses, init_lms  # the warm start, replaced cut by cut
    first_seen = np.full(len(ids), n)
    np.minimum.at(first_seen, graph.obs_landmark, graph.obs_pose)
    errors: dict[str, list[float]] = {"causal_optimum": [], "ekfslam": [], "slsjf": []}
    for end in range(causal_every - 1, n, causal_every):
        if not np.all(np.isfinite(truth[end])):
            continue
        sub = _subgraph(graph, end + 1, first_seen <= end)
        cut = optimize(sub.graph, poses[:end + 1], lms[sub.landmarks], LsqConfig())
        poses[:end + 1], lms[sub.landmarks] = cut.poses, cut.landmarks
        for name, xy in (("causal_optimum", se2.compose(start, cut.poses[end])[:2]), ("ekfslam", filtered[end][:2]),
                         ("slsjf", slsjf_poses[end][:2])):
            errors[name].append(float(np.hypot(*(xy - truth[end][:2]))))
    result["causal"] = {name: float(np.sqrt(np.mean(np.square(e)))) for name, e in errors.items()}
    result["causal"]["scans"] = len(errors["ekfslam"])
    return result


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--data", type=Path, default=Path(__file__).resolve().parents[2] / "shared" / "data")
    ap.add_argument("--seeds", type=int, nargs="*", default=list(range(1, 20)))
    ap.add_argument("--duration-s", type=float, default=1800.0)
    ap.add_argument("--robots", type=int, nargs="*", default=[1, 2, 3, 4, 5])
    ap.add_argument("--skip-vp", action="store_true")
    ap.add_argument("--paper", action="store_true", help="also SLSJF linearized once (--preset paper)")
    ap.add_argument("--batch", type=int, nargs="*", default=[], metavar="SEED",
                    help="paper-scenario seeds whose full batch optimum to compute (2-3 minutes each)")
    ap.add_argument("--batch-incremental", action="store_true",
                    help="--batch grown from dead reckoning (solve_incremental), not from EKF-SLAM's estimate: slow")
    ap.add_argument("--causal-every", type=int, default=0, metavar="K",
                    help="with --batch: also the robot against the optimum of the measurements up to each K-th scan")
    ap.add_argument("--vp-band", action="store_true",
                    help="Victoria Park: the tree NEES band against the reference, itself an estimate (a few minutes)")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="an SLSJF setting for every SLSJF run (repeatable; EKF-SLAM runs as it is)")
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    bad = [kv for kv in args.set if "=" not in kv]
    if bad:
        ap.error(f"--set takes KEY=VALUE, got {bad[0]!r}")
    sets = dict(kv.split("=", 1) for kv in args.set)  # SLSJF's settings; its runs are kept apart by them
    tag = "".join(f"-{k}={v}" for k, v in sorted(sets.items()))
    out: dict[str, Any] = {"victoria_park": [], "mrclam": [], "sim": []}
    print("each cell: ekfslam/slsjf")
    vp = args.out / "victoria-park.mcap"
    if not args.skip_vp and vp.exists():  # `slamreplay record victoria-park DATA/victoria-park-isam --out` it first
        print("Victoria Park (against the batch optimum)")
        out["victoria_park"].append(row("victoria-park", metrics(vp, "ekfslam", args.out / "vp-ekfslam"),
                                        metrics(vp, "slsjf", args.out / f"vp-slsjf{tag}", config=sets)))
        if args.paper:
            out["victoria_park"].append(row("victoria-park paper", metrics(vp, "ekfslam", args.out / "vp-ekfslam"),
                                            metrics(vp, "slsjf", args.out / "vp-slsjf-paper", "paper")))
    mrclam = args.data / "mrclam-dataset6"
    if mrclam.is_dir() and args.robots:
        print("MRCLAM Dataset 6")
        for r in args.robots:
            rec = args.out / f"mrclam{r}.mcap"
            if not rec.exists():
                import_mrclam(mrclam, r, rec)
            out["mrclam"].append(row(f"robot {r}", metrics(rec, "ekfslam", args.out / f"mrclam{r}-ekfslam"),
                                     metrics(rec, "slsjf", args.out / f"mrclam{r}-slsjf{tag}", config=sets)))
    if args.seeds:
        print(f"Paper scenario ({args.duration_s:g} s)")
        for s in args.seeds:
            rec = args.out / f"sim{s}.mcap"
            if not rec.exists():
                simulate_landmarks(rec, LandmarkSimConfig(duration_s=args.duration_s), seed=s)
            out["sim"].append(row(f"seed {s}", metrics(rec, "ekfslam", args.out / f"sim{s}-ekfslam"),
                                  metrics(rec, "slsjf", args.out / f"sim{s}-slsjf{tag}", config=sets)))
        nees = [r["slsjf"]["landmark_nees_mean"] for r in out["sim"] if "landmark_nees_mean" in r["slsjf"]]
        if len(nees) >= 2:
            # The seeds are independent draws of the same scenario: the 95 % interval of their mean NEES from their own
            # spread (Student's t). A consistent filter's per-seed mean NEES has expectation 2, so the band the mean
            # over seeds must fall in is 2 -/+ that half-width.
            half = float(t_dist.ppf(0.975, len(nees) - 1) * np.std(nees, ddof=1) / np.sqrt(len(nees)))
            mean = float(np.mean(nees))
            out["sim_landmark_nees"] = {"mean_over_seeds": mean, "band_95": [2.0 - half, 2.0 + half],
                                        "inside": bool(abs(mean - 2.0) <= half), "seeds": len(nees)}
            print(f"  SLSJF landmark NEES, mean over {len(nees)} seeds: {mean:.3f}; band of a consistent filter "
                  f"(2 -/+ t * sd / sqrt(n)): [{2.0 - half:.3f}, {2.0 + half:.3f}]"
                  f" -> {'inside' if abs(mean - 2.0) <= half else 'OUTSIDE'}")
        for name in ("landmark_rmse_m", "ape_rmse_m"):
            bound = 1.5 if name == "landmark_rmse_m" else 1.2
            ratios = [r["ratio"][name] for r in out["sim"] if name in r["ratio"]]
            over = [r["name"] for r in out["sim"] if r["ratio"].get(name, 0.0) > bound]
            if ratios:
                print(f"  {name} SLSJF / EKF-SLAM over {len(ratios)} seeds: median {np.median(ratios):.2f}, geometric "
                      f"mean {float(np.exp(np.mean(np.log(ratios)))):.2f}; above {bound}x: {', '.join(over) or 'none'}")
    for s in args.batch:
        rec = args.out / f"sim{s}.mcap"
        if rec.exists():
            print(f"  seed {s}: the batch optimum of the same measurements (slow) ...")
            opt = batch_optimum(rec, args.out / f"sim{s}-batch", args.batch_incremental, args.causal_every)
            out.setdefault("sim_batch_optimum", {})[s] = opt
            print(f"  seed {s}: batch optimum landmark RMSE {opt['landmark_rmse_m']:.4g} m, mean error "
                  f"({opt['mean_error_m'][0]:.3f}, {opt['mean_error_m'][1]:.3f}) m")
            if "causal" in opt:
                c = opt["causal"]
                print(f"  seed {s}: robot position RMSE at {c['scans']} scans: the optimum of the measurements up to "
                      f"each {c['causal_optimum']:.4g} m, EKF-SLAM {c['ekfslam']:.4g} m, SLSJF {c['slsjf']:.4g} m")
    if args.vp_band and vp.exists():
        out["victoria_park_band"] = vp_band(vp, args.data / "victoria-park-isam", args.out)
    if args.json:
        args.json.write_text(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
