"""2D pose-graph back end against g2o (g2opy) and GTSAM, on the same files in one run.

For every dataset, every solver starts from the same initial guess (the file's VERTEX records, or
odometry composition for edge-only files), fixes vertex 0, and stops at a relative chi2 decrease
of 1e-6 (g2o: ``SparseOptimizerTerminateAction`` gain threshold; GTSAM: ``relativeErrorTol``).
Times are the median of ``--repeat`` runs of the optimization call alone (graph construction in
the peers' Python APIs is not timed; ours includes building its sparse structure and ordering).
chi2 is always re-evaluated with the g2o EDGE_SE2 convention on each solver's result poses; for
GTSAM, whose BetweenFactor residual is the SE(2) logarithm, its own objective is printed too.

Also measured: the chordal start, MIT's local minima per start and solver, incremental M3500
(CPU time per update with loop closures, with ``--skip-chi2`` and in exact mode, the largest pose
difference between the two after each such update, and GTSAM iSAM2's time on the same updates),
and M3500 with 10 % false loop closures (RMSE vs ground truth).

Run: ``.venv/bin/python benchmarks/posegraph.py [--data ../shared/data] [--repeat 3] [--quick]``.
Peers: ``pip install g2opy gtsam`` (each is skipped with a note when missing).
"""

from __future__ import annotations

import argparse
import itertools
import os
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
from bench_io import write_json

from slamreplay.algorithms.common import sparse_cholesky
from slamreplay.algorithms.common.posegraph import OptimizerConfig, PoseGraph, chi2, optimize
from slamreplay.algorithms.common.posegraph_analysis import aligned_position_rmse
from slamreplay.algorithms.common.posegraph_incremental import IncrementalConfig, IncrementalOptimizer
from slamreplay.algorithms.common.posegraph_init import init_chordal, init_odometry
from slamreplay.algorithms.common.robust import Kernel
from slamreplay.algorithms.common.se2 import wrap_angle
from slamreplay.algorithms.common.sparse_cholesky import SparseCholesky
from slamreplay.replay.tools.graph_io import read_graph

DATASETS = [
    ("m3500 (Vertigo)", "posegraph-m3500/manhattanOlson3500.g2o", 146.077),
    ("CSAIL_P (TORO)", "posegraph-toro-csail-fr079/CSAIL_P_toro.graph", 38.956),
    ("FR079_P (TORO)", "posegraph-toro-csail-fr079/FR079_P_toro.graph", 37.599),
    ("intel", "pose_graphs/intel.g2o", 45.005),
    ("manhattan", "pose_graphs/manhattan.g2o", 3549.04),
    ("CSAIL", "pose_graphs/CSAIL.g2o", 40.555),
    ("city10000", "pose_graphs/city10000.g2o", 511.985),
    ("MIT", "pose_graphs/MIT.g2o", float("nan")),
]
REL_TOL = 1e-6
MAX_IT = 100


def clock() -> float:
    """The benchmark's clock: CPU time of the process (all threads), not wall time, which on a machine
    shared with other jobs mostly measures their load; the same clock times ours and the peers'."""
    return time.process_time()


def solver_name() -> str:
    """The linear solver the optimizer picks: superlu, or the binding that runs CHOLMOD."""
    chol = SparseCholesky("auto")
    return str(getattr(chol, "provider", chol.backend))  # revisions before the CVXOPT binding have no provider


def plain_solver() -> str:
    """The linear solver of a plain ``pip install`` (no CHOLMOD binding): QDLDL, a core dependency, else SuperLU."""
    return "qdldl" if getattr(sparse_cholesky, "HAVE_QDLDL", False) else "superlu"


def median_time(fn: Callable[[], Any], repeat: int) -> tuple[float, Any]:
    """Median CPU time of ``repeat`` calls and the last result."""
    times, out = [], None
    for _ in range(repeat):
        t = clock()
        out = fn()
        times.append(clock() - t)
    return float(np.median(times)), out


# ---- peers ---------------------------------------------------------------------------------------

def g2o_solver(method: str) -> Callable[[PoseGraph], Callable[[], np.ndarray]] | None:
    """A g2o runner factory, or None when g2opy is missing."""
    try:
        import g2opy as g2o
    except ImportError:
        return None

    def prepare(g: PoseGraph) -> Callable[[], np.ndarray]:
        def run() -> np.ndarray:
            opt = g2o.SparseOptimizer()
            solver = g2o.BlockSolverSE2(g2o.LinearSolverEigenSE2())
            alg = (g2o.OptimizationAlgorithmGaussNewton(solver) if method == "gn"
                   else g2o.OptimizationAlgorithmLevenberg(solver))
            opt.set_algorithm(alg)
            for k, p in enumerate(g.poses):
                v = g2o.VertexSE2()
                v.set_id(k)
                v.set_estimate(g2o.SE2(*p))
                v.set_fixed(k == 0)
                opt.add_vertex(v)
            for k in range(g.n_edges):
                e = g2o.EdgeSE2()
                e.set_vertex(0, opt.vertex(int(g.i[k])))
                e.set_vertex(1, opt.vertex(int(g.j[k])))
                e.set_measurement(g2o.SE2(*g.measurements[k]))
                e.set_information(g.information[k])
                opt.add_edge(e)
            term = g2o.SparseOptimizerTerminateAction()
            term.set_gain_threshold(REL_TOL)
            term.set_max_iterations(MAX_IT)
            opt.add_post_iteration_action(term)
            t = clock()
            opt.initialize_optimization()
            opt.optimize(MAX_IT)
            run.elapsed = clock() - t  # type: ignore[attr-defined]
            out = np.empty((g.n_vertices, 3))
            for k in range(g.n_vertices):
                est = opt.vertex(k).estimate()
                out[k, :2] = est.translation()
                out[k, 2] = est.rotation().angle()
            return out

        return run

    return prepare


def gtsam_solver(method: str) -> Callable[[PoseGraph], Callable[[], np.ndarray]] | None:
    """A GTSAM runner factory (GN or LM), or None when gtsam is missing."""
    try:
        import gtsam
    except ImportError:
        return None

    def prepare(g: PoseGraph) -> Callable[[], np.ndarray]:
        graph = gtsam.NonlinearFactorGraph()
        graph.add(gtsam.PriorFactorPose2(0, gtsam.Pose2(*g.poses[0]), gtsam.noiseModel.Isotropic.Sigma(3, 1e-6)))
        for k in range(g.n_edges):
            graph.add(gtsam.BetweenFactorPose2(int(g.i[k]), int(g.j[k]), gtsam.Pose2(*g.measurements[k]),
                                               gtsam.noiseModel.Gaussian.Information(g.information[k])))
        initial = gtsam.Values()
        for k, p in enumerate(g.poses):
            initial.insert(k, gtsam.Pose2(*p))

        def run() -> np.ndarray:
            t = clock()
            if method == "gn":
                params = gtsam.GaussNewtonParams()
                params.setRelativeErrorTol(REL_TOL)
                params.setMaxIterations(MAX_IT)
                result = gtsam.GaussNewtonOptimizer(graph, initial, params).optimize()
            else:
                lm = gtsam.LevenbergMarquardtParams()
                lm.setRelativeErrorTol(REL_TOL)
                lm.setMaxIterations(MAX_IT)
                result = gtsam.LevenbergMarquardtOptimizer(graph, initial, lm).optimize()
            run.elapsed = clock() - t  # type: ignore[attr-defined]
            run.own_chi2 = 2.0 * graph.error(result)  # type: ignore[attr-defined]  # GTSAM's Logmap residual
            return np.asarray(gtsam.utilities.extractPose2(result))

        return run

    return prepare


def timed_peer(prepare: Callable[[PoseGraph], Callable[[], np.ndarray]], g: PoseGraph,
               repeat: int) -> tuple[float, np.ndarray | str]:
    """Median of the peer's own optimization time (construction excluded) and its poses, or the
    first line of the exception it raised (GTSAM throws IndeterminateSystem on some graphs)."""
    run = prepare(g)
    times, poses = [], None
    for _ in range(repeat):
        try:
            poses = run()
        except RuntimeError as err:  # a peer's failure is a result to report, not a crash
            return float("nan"), str(err).strip().splitlines()[0]
        times.append(run.elapsed)  # type: ignore[attr-defined]
    assert poses is not None
    timed_peer.own_chi2 = getattr(run, "own_chi2", None)  # type: ignore[attr-defined]
    return float(np.median(times)), poses


def peer_chi2(g: PoseGraph, poses: np.ndarray | str) -> float:
    """chi2 of a peer's result, NaN when it failed."""
    return float("nan") if isinstance(poses, str) else chi2(g, poses)


# ---- sections ------------------------------------------------------------------------------------

def batch_table(data: Path, repeat: int, names: list[str]) -> dict[str, dict[str, float]]:
    """Time and chi2 of every solver on every dataset; our GN time divided by each peer's."""
    peers = {"g2o GN": g2o_solver("gn"), "GTSAM GN": gtsam_solver("gn"), "GTSAM LM": gtsam_solver("lm")}
    for name, prep in peers.items():
        if prep is None:
            print(f"note: {name} skipped ({'g2opy' if 'g2o' in name else 'gtsam'} not installed)")
    none = OptimizerConfig(kernel=Kernel.NONE)
    lm = OptimizerConfig(method="lm", kernel=Kernel.NONE)
    plain = OptimizerConfig(kernel=Kernel.NONE, linear_solver=plain_solver())  # type: ignore[arg-type]
    cols = ["ours GN", "ours LM", "ours chordal+GN", "ours GN plain", *[p for p, f in peers.items() if f is not None]]
    provider = solver_name()
    print(f"\nlinear solver: {'SciPy SuperLU' if provider == 'superlu' else provider}; 'ours GN plain': "
          f"{plain_solver()}, the solver of a plain pip install; times are CPU ms (median of {repeat})")
    figures: dict[str, dict[str, float]] = {}
    print(f"{'dataset':<17}{'ref chi2':>10} | " + " | ".join(f"{c:>22}" for c in cols) + " | ours GN / peer")
    for label, rel, ref in DATASETS:
        if label not in names:
            continue
        g = read_graph(data / rel).graph
        cells: dict[str, tuple[float, float]] = {}
        t, r = median_time(lambda g=g: optimize(g, none), repeat)
        cells["ours GN"] = (t, r.chi2_final)
        t, r = median_time(lambda g=g: optimize(g, lm), repeat)
        cells["ours LM"] = (t, r.chi2_final)
        t, r = median_time(lambda g=g: optimize(g.with_poses(init_chordal(g)), none), repeat)
        cells["ours chordal+GN"] = (t, r.chi2_final)
        t, r = median_time(lambda g=g: optimize(g, plain), repeat)
        cells["ours GN plain"] = (t, r.chi2_final)
        own = []
        for pname, prep in peers.items():
            if prep is not None:
                t, poses = timed_peer(prep, g, repeat)
                cells[pname] = (t, peer_chi2(g, poses))
                if getattr(timed_peer, "own_chi2", None) is not None:
                    own.append(f"{pname} {timed_peer.own_chi2:.3f}")  # type: ignore[attr-defined]
        ratios = [f"{cells['ours GN'][0] / cells[p][0]:.2f}x {p}" for p in cols[4:]]
        row = " | ".join(f"{cells[c][0] * 1e3:8.1f} ms {cells[c][1]:11.3f}" for c in cols)
        print(f"{label:<17}{ref:>10.3f} | {row} | " + ", ".join(ratios))
        key = label.split(" ")[0].lower()
        figures[key] = {"ours_gn_ms": 1e3 * cells["ours GN"][0], "chi2": cells["ours GN"][1],
                        "ours_lm_ms": 1e3 * cells["ours LM"][0], "ours_gn_plain_ms": 1e3 * cells["ours GN plain"][0],
                        "chi2_plain": cells["ours GN plain"][1]}
        for pname, field in (("g2o GN", "g2o_gn"), ("GTSAM GN", "gtsam_gn"), ("GTSAM LM", "gtsam_lm")):
            if pname in cells:
                figures[key][f"{field}_ms"] = 1e3 * cells[pname][0]
                figures[key][f"{field}_chi2"] = cells[pname][1]
                figures[key][f"ours_over_{field}"] = cells["ours GN"][0] / cells[pname][0]
                figures[key][f"ours_plain_over_{field}"] = cells["ours GN plain"][0] / cells[pname][0]
        if own:
            print(f"{'':<17}{'':>10}   (GTSAM's own objective, 2 x error with its Logmap residual: {', '.join(own)})")
    return figures


def mit_minima(data: Path) -> None:
    """Where each start and solver ends on MIT (several local minima from odometry)."""
    g = read_graph(data / "pose_graphs/MIT.g2o").graph
    print("\nMIT minima (chi2, g2o convention):")
    starts = {"odometry": g.with_poses(init_odometry(g)), "chordal": g.with_poses(init_chordal(g))}
    for sname, gs in starts.items():
        for method in ("gn", "lm"):
            r = optimize(gs, OptimizerConfig(method=method, kernel=Kernel.NONE, max_iterations=300))
            print(f"  ours {method.upper()} from {sname:<9}: {r.chi2_final:10.3f} "
                  f"({r.iterations} it, {r.status.value})")
    for pname, prep in (("g2o GN", g2o_solver("gn")), ("g2o LM", g2o_solver("lm")),
                        ("GTSAM GN", gtsam_solver("gn")), ("GTSAM LM", gtsam_solver("lm"))):
        if prep is not None:
            for sname, gs in starts.items():
                _, poses = timed_peer(prep, gs, 1)
                what = f"raised: {poses}" if isinstance(poses, str) else f"{chi2(g, poses):10.3f}"
                print(f"  {pname} from {sname:<9}: {what}")


def isam2_updates(g: PoseGraph, order: np.ndarray, bounds: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """GTSAM's iSAM2 (default ISAM2Params) fed the same updates: CPU time of each update that carries loop
    closures, and its final poses; None without gtsam. A new vertex starts at its placing edge composed
    onto the current estimate of the vertex it links to, as in ours."""
    try:
        import gtsam
    except ImportError:
        return None
    isam = gtsam.ISAM2(gtsam.ISAM2Params())
    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    graph.add(gtsam.PriorFactorPose2(0, gtsam.Pose2(*g.poses[0]), gtsam.noiseModel.Isotropic.Sigma(3, 1e-6)))
    values.insert(0, gtsam.Pose2(*g.poses[0]))
    isam.update(graph, values)
    known = {0}
    costs = []
    for a, b in itertools.pairwise(bounds):
        k = order[a:b]
        if k.size == 0:
            continue
        graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        for e in k:
            i, j = int(g.i[e]), int(g.j[e])
            z = gtsam.Pose2(*g.measurements[e])
            graph.add(gtsam.BetweenFactorPose2(i, j, z, gtsam.noiseModel.Gaussian.Information(g.information[e])))
            for new, old, rel in ((j, i, z), (i, j, z.inverse())):
                if new not in known and old in known:
                    base = values.atPose2(old) if values.exists(old) else isam.calculateEstimatePose2(old)
                    values.insert(new, base.compose(rel))
                    known.add(new)
        t = clock()
        isam.update(graph, values)
        dt = clock() - t
        if k.size > values.size():  # edges beyond the ones placing new vertices: loop closures
            costs.append(dt)
    est = isam.calculateEstimate()
    return np.array(costs), np.asarray(gtsam.utilities.extractPose2(est))


def incremental_m3500(data: Path, every: int, iterations: int, skip_chi2: float) -> dict[str, float]:
    """Replay M3500 vertex by vertex; time the updates that carry loop closures, ours and iSAM2's.

    Ours runs twice in lockstep, each update timed on its own: with ``skip_chi2`` (the measured
    configuration) and exact (``skip_chi2 = 0``: one Gauss-Newton step after every update with loop
    closures); after every such update the largest position and heading difference between the two
    is recorded (the per-update accuracy of skipping)."""
    g = read_graph(data / "posegraph-m3500/manhattanOlson3500.g2o").graph
    opt = OptimizerConfig(kernel=Kernel.NONE, max_iterations=iterations, rel_tol=1e-5)
    inc = IncrementalOptimizer(IncrementalConfig(opt, skip_chi2=skip_chi2))
    exact = IncrementalOptimizer(IncrementalConfig(opt, skip_chi2=0.0)) if skip_chi2 > 0.0 else None
    newest = np.maximum(g.i, g.j)
    order = np.argsort(newest, kind="stable")
    bounds = np.searchsorted(newest[order], np.arange(1, g.n_vertices + 1, every))
    costs, exact_costs, closures, iters, solved, dpos, dth = [], [], 0, 0, 0, [], []
    total = 0.0
    for a, b in itertools.pairwise(bounds):
        k = order[a:b]
        if k.size == 0:
            continue
        t = clock()
        res = inc.step(g.i[k], g.j[k], g.measurements[k], g.information[k])
        dt = clock() - t
        total += dt
        if exact is not None:
            t = clock()
            exact.step(g.i[k], g.j[k], g.measurements[k], g.information[k])
            if res.loop_closures:
                exact_costs.append(clock() - t)
                d = inc.poses - exact.poses
                dpos.append(float(np.hypot(d[:, 0], d[:, 1]).max()))
                dth.append(float(np.abs(wrap_angle(d[:, 2])).max()))
        if res.loop_closures:
            costs.append(dt)
            closures += res.loop_closures
            iters += res.iterations
            solved += res.iterations > 0
    k = order[bounds[-1]:]
    if k.size:
        inc.step(g.i[k], g.j[k], g.measurements[k], g.information[k])
        if exact is not None:
            exact.step(g.i[k], g.j[k], g.measurements[k], g.information[k])
    c = np.array(costs)
    final = chi2(g, inc.poses)
    print(f"\nincremental M3500 ({every} vertex/update; GN <= {iterations} it/update, no kernel, "
          f"skip_chi2 {skip_chi2:g}), CPU time:")
    print(f"  {c.size} updates with loop closures ({closures} closures), {solved} re-optimized, total {total:.1f} s")
    print(f"  per loop-closure update: median {np.median(c) * 1e3:.2f} ms, mean {c.mean() * 1e3:.2f} ms, "
          f"max {c.max() * 1e3:.1f} ms, last 100 mean {c[-100:].mean() * 1e3:.1f} ms; "
          f"per loop closure {c.sum() / closures * 1e3:.2f} ms; {iters / c.size:.2f} GN it/update")
    print(f"  final chi2 {final:.3f} (batch optimum 146.077)")
    figures = {"ours_update_median_ms": float(np.median(c) * 1e3), "ours_update_mean_ms": float(c.mean() * 1e3),
               "ours_final_chi2": final, "closure_updates": int(c.size), "skip_chi2": skip_chi2,
               "updates_reoptimized": int(solved)}
    if exact is not None:
        ec = np.array(exact_costs)
        print(f"  exact (skip_chi2 0), same updates: median {np.median(ec) * 1e3:.2f} ms, "
              f"mean {ec.mean() * 1e3:.2f} ms; final chi2 {chi2(g, exact.poses):.3f}")
        print(f"  skipping vs exact after each closure update: largest position difference max {max(dpos):.3f} m, "
              f"median {np.median(dpos):.4f} m; heading max {max(dth):.3f} rad, median {np.median(dth):.4f} rad")
        figures.update({"exact_update_median_ms": float(np.median(ec) * 1e3),
                        "exact_update_mean_ms": float(ec.mean() * 1e3), "exact_final_chi2": chi2(g, exact.poses),
                        "vs_exact_max_position_m": max(dpos), "vs_exact_median_position_m": float(np.median(dpos)),
                        "vs_exact_max_heading_rad": max(dth), "vs_exact_median_heading_rad": float(np.median(dth))})
    peer = isam2_updates(g, order, bounds) if every == 1 else None
    if peer is not None:
        pc, poses = peer
        print(f"  GTSAM iSAM2 (default parameters), same updates: median {np.median(pc) * 1e3:.2f} ms, "
              f"mean {pc.mean() * 1e3:.2f} ms per loop-closure update ({pc.size}); final chi2 {chi2(g, poses):.3f}; "
              f"ours / iSAM2: median {np.median(c) / np.median(pc):.2f}x, mean {c.mean() / pc.mean():.2f}x")
        figures.update({"isam2_update_median_ms": float(np.median(pc) * 1e3),
                        "isam2_update_mean_ms": float(pc.mean() * 1e3), "isam2_final_chi2": chi2(g, poses),
                        "ours_over_isam2": float(np.median(c) / np.median(pc)),
                        "ours_over_isam2_mean": float(c.mean() / pc.mean())})
    return figures


def robustness_m3500(data: Path) -> None:
    """10 % random false loop closures (seed 2013): position RMSE vs ground truth per kernel."""
    root = data / "posegraph-m3500"
    g = read_graph(root / "manhattanOlson3500.g2o").graph
    truth = np.loadtxt(root / "manhattanOlson3500_nodes_groundTruth.dat")
    rng = np.random.default_rng(2013)
    k = round(0.1 * g.n_edges)
    a = rng.integers(0, g.n_vertices, k)
    b = (a + rng.integers(2, g.n_vertices - 1, k)) % g.n_vertices
    z = np.column_stack([rng.uniform(-10, 10, k), rng.uniform(-10, 10, k), rng.uniform(-np.pi, np.pi, k)])
    info = g.information[np.flatnonzero(np.abs(g.i - g.j) != 1)[0]]
    bad = PoseGraph(g.poses, np.r_[g.i, a], np.r_[g.j, b], np.r_[g.measurements, z],
                    np.r_[g.information, np.broadcast_to(info, (k, 3, 3))])
    clean = optimize(g, OptimizerConfig(kernel=Kernel.NONE))
    print(f"\nM3500 + {k} false loop closures (10 %): position RMSE vs ground truth after SE(2) alignment")
    print(f"  clean, no kernel: {aligned_position_rmse(clean.poses, truth):.4f} m")
    dcs_only = OptimizerConfig(graduated=False, inlier_gate=None)  # the pre-gate DCS: phi = 1 throughout
    runs = [("dcs (default)", OptimizerConfig()), ("dcs phi=1 only", dcs_only),
            ("cauchy", OptimizerConfig(kernel=Kernel.CAUCHY)), ("huber", OptimizerConfig(kernel=Kernel.HUBER)),
            ("none", OptimizerConfig(kernel=Kernel.NONE, max_iterations=30))]
    false = np.arange(g.n_edges, bad.n_edges)
    for name, cfg in runs:
        t = clock()
        r = optimize(bad, cfg)
        dt = clock() - t
        print(f"  outliers, {name:<15}: {aligned_position_rmse(r.poses, truth):8.4f} m "
              f"({r.iterations} it, {r.status.value}, {dt:.1f} s; rejected {r.edges_rejected}, "
              f"of them false {int((~r.inliers[false]).sum())}/{k})")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, default=Path(os.environ.get("SLAMREPLAY_DATA", "../shared/data")))
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--quick", action="store_true",
                        help="batch table on m3500, intel and city10000, and the incremental M3500 only")
    parser.add_argument("--json", type=Path, metavar="PATH", help="also write the figures as JSON to PATH")
    parser.add_argument("--skip", nargs="*", default=[], choices=["batch", "mit", "incremental", "robust"])
    parser.add_argument("--every", type=int, default=1, help="vertices per incremental update")
    parser.add_argument("--inc-iterations", type=int, default=1, help="GN iterations per incremental update")
    parser.add_argument("--skip-chi2", type=float, default=IncrementalConfig().skip_chi2,
                        help="incremental: IncrementalConfig.skip_chi2 (default: its default; 0: exact mode)")
    args = parser.parse_args()
    if args.repeat < 1 or args.every < 1 or args.inc_iterations < 1:
        parser.error("--repeat, --every and --inc-iterations must be >= 1")
    if not (args.skip_chi2 >= 0.0 and np.isfinite(args.skip_chi2)):
        parser.error("--skip-chi2 must be finite and >= 0")
    if not args.data.is_dir():
        parser.error(f"--data {args.data} is not a directory (the shared data sets: ../shared/data)")
    names = ["m3500 (Vertigo)", "intel", "city10000"] if args.quick else [d[0] for d in DATASETS]
    if args.quick:
        args.skip = sorted({*args.skip, "mit", "robust"})
    figures: dict[str, Any] = {"benchmark": "posegraph", "repeat": args.repeat, "clock": "process CPU time",
                               "linear_solver": solver_name(), "plain_linear_solver": plain_solver()}
    if "batch" not in args.skip:
        figures["datasets"] = batch_table(args.data, args.repeat, names)
    if "mit" not in args.skip:
        mit_minima(args.data)
    if "incremental" not in args.skip:
        figures["incremental_m3500"] = incremental_m3500(args.data, args.every, args.inc_iterations, args.skip_chi2)
    if "robust" not in args.skip:
        robustness_m3500(args.data)
    if args.json:
        write_json(args.json, figures)

if __name__ == "__main__":
    main()
