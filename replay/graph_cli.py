"""``slamreplay graph optimize``: read a pose-graph file, optimize it, write it back, log it to Rerun."""

from __future__ import annotations

import hashlib
import os
import time
import uuid
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from slamreplay.algorithms.common.posegraph import OptimizationResult, OptimizerConfig, PoseGraph, chi2, optimize
from slamreplay.algorithms.common.posegraph_init import init_chordal, init_odometry
from slamreplay.algorithms.common.robust import Kernel
from slamreplay.replay.graph_io import GraphFileError, format_of, read_graph, write_graph

SOLVERS = ("gn", "lm")
INITS = ("odometry", "chordal", "file")
ROBUST = ("none", "dcs", "huber", "cauchy")


def optimize_file(
    in_path: str | os.PathLike[str],
    out_path: str | os.PathLike[str],
    *,
    solver: str = "gn",
    init: str = "odometry",
    robust: str = "dcs",
    rrd_path: str | os.PathLike[str] | None = None,
) -> dict[str, Any]:
    """Optimize a g2o / TORO pose graph file and write the result in the output's format.

    Parameters
    ----------
    in_path : ``.g2o`` or ``.graph`` (TORO) file.
    out_path : destination, format from its extension; written atomically (temp file + rename).
    solver : "gn" (Gauss-Newton) or "lm" (Levenberg-Marquardt).
    init : "odometry" (compose measurements along a spanning tree, sequential edges first),
        "chordal" (LAGO-style linear orientations then positions) or "file" (the file's VERTEX
        records; odometry composition when the file has none).
    robust : "dcs" (Dynamic Covariance Scaling on loop closures, Phi graduated down to 1, then a
        chi-square gate and a plain re-solve without the rejected closures), "huber", "cauchy" (same
        gate and re-solve) or "none" (plain least squares on every edge).
    rrd_path : optional Rerun recording of the graph before/after and chi2 per iteration.

    Returns
    -------
    dict with ``vertices``, ``edges``, ``chi2_initial`` (plain g2o chi2 at the initial guess),
    ``chi2_final`` (plain g2o chi2 over the kept edges: every edge when ``edges_rejected`` is 0),
    ``edges_rejected`` (loop closures the inlier gate dropped; they stay in the output file),
    ``iterations``, ``status`` ("converged", "max_iterations", "diverged") and
    ``time_s`` (initialization plus optimization, without file I/O).

    Raises
    ------
    ValueError
        For a bad argument (named in the message); ``GraphFileError`` (a ValueError) for a bad file,
        including a graph the optimizer cannot take (e.g. vertices no edge connects).
    """
    if solver not in SOLVERS:
        raise ValueError(f"solver must be one of {SOLVERS}, got {solver!r}")
    if init not in INITS:
        raise ValueError(f"init must be one of {INITS}, got {init!r}")
    if robust not in ROBUST:
        raise ValueError(f"robust must be one of {ROBUST}, got {robust!r}")
    out = Path(out_path)
    fmt_out = format_of(out)
    gf = read_graph(in_path)
    gauge: tuple[int, ...] = gf.fixed or (0,)
    cfg = OptimizerConfig(method=solver, kernel=Kernel(robust), gauge=gauge if len(gauge) > 1 else gauge[0])
    t0 = time.perf_counter()
    graph = gf.graph
    try:
        if init == "odometry":
            graph = graph.with_poses(init_odometry(graph, gauge[0]))
        elif init == "chordal":
            graph = graph.with_poses(init_chordal(graph, gauge[0]))
        result = optimize(graph, cfg)
    except ValueError as err:  # arguments are checked above: what is left is the file's graph
        msg = f"{in_path}: {err}"
        raise GraphFileError(msg) from err
    elapsed = time.perf_counter() - t0
    optimized = graph.with_poses(result.poses)
    write_graph(out, optimized, gf.vertex_ids, gf.fixed, fmt_out)
    if rrd_path is not None:
        _log_rrd(Path(rrd_path), Path(in_path), graph, optimized, result, f"{solver}/{init}/{robust}")
    return {
        "vertices": graph.n_vertices,
        "edges": graph.n_edges,
        "chi2_initial": chi2(graph),
        "chi2_final": result.chi2_final,
        "edges_rejected": result.edges_rejected,
        "iterations": result.iterations,
        "status": result.status.value,
        "time_s": elapsed,
    }


def _segments(graph: PoseGraph) -> NDArray[np.float32]:
    """Edges as 2D segments (m, 2, 2)."""
    return np.stack([graph.poses[graph.i, :2], graph.poses[graph.j, :2]], 1).astype(np.float32)


def _log_rrd(path: Path, source: Path, before: PoseGraph, after: PoseGraph, result: OptimizationResult,
             config: str) -> None:
    """Write one recording: both graphs (static) and chi2 per iteration; temp file then rename."""
    import rerun as rr  # deferred: only --rrd needs Rerun
    import rerun.blueprint as rrb

    from slamreplay.replay import views
    from slamreplay.replay.observer import deterministic_batcher

    digest = hashlib.sha256(source.read_bytes()).hexdigest()
    rec_id = uuid.uuid5(uuid.NAMESPACE_URL, f"slamreplay/graph-optimize/{digest}/{config}")
    bounds = views.extend_bounds(views.extend_bounds(None, before.poses[:, :2]), after.poses[:, :2])
    blueprint = views.layout(views.tab(
        "Pose graph", rrb.Vertical(views.map_view("Initial", "world/graph/initial", bounds),
                                   views.map_view("Optimized", "world/graph/optimized", bounds)),
        views.series_view("chi2 per iteration", "metrics/chi2"), columns=[3, 2]))
    tmp = path.with_name(f".{path.name}.tmp")
    rec = rr.RecordingStream(views.app_id("graph"), recording_id=rec_id, send_properties=False,
                             batcher_config=deterministic_batcher())
    rec.set_log_time_enabled(False)
    rec.save(tmp)
    rec.send_blueprint(blueprint, make_active=True, make_default=True)
    try:
        loop = np.abs(before.i - before.j) != 1
        colors = np.where(loop[:, None], [views.ACCEPTED], [views.TRUTH]).astype(np.uint8)
        for name, g in (("initial", before), ("optimized", after)):
            rec.log(f"world/graph/{name}", views.MAP_FLIP, static=True)
            rec.log(f"world/graph/{name}/edges", rr.LineStrips2D(_segments(g), colors=colors, radii=-0.5),
                    static=True)
            vertices = rr.Points2D(g.poses[:, :2].astype(np.float32), radii=-1.5)
            rec.log(f"world/graph/{name}/vertices", vertices, static=True)
        k = np.arange(result.chi2_history.size, dtype=np.int64)
        rec.send_columns("metrics/chi2", indexes=[rr.TimeColumn("iteration", sequence=k)],
                         columns=rr.Scalars.columns(scalars=result.chi2_history))
    finally:
        rec.disconnect()
    os.replace(tmp, path)
