"""Read and write 2D pose graphs in g2o (``VERTEX_SE2``/``EDGE_SE2``) and TORO (``VERTEX2``/``EDGE2``) text.

g2o: ``EDGE_SE2 i j dx dy dtheta I11 I12 I13 I22 I23 I33`` (upper triangle, row-major, order
x, y, theta). TORO: ``EDGE2 i j dx dy dtheta Ixx Ixy Iyy Itt Ixt Iyt``. Both store the pose of j
in the frame of i and an *information* matrix. ``FIX id`` (g2o) names gauge vertices. Files with
edges only get their initial guess by composing odometry along a spanning tree.

``optimize_file`` is ``slamreplay graph optimize``: read a file, optimize it, write it back and, with
``--rrd``, log both graphs and chi2 per iteration to Rerun (api/cli/graph_cli.py is its argument parser).
"""

from __future__ import annotations

import hashlib
import os
import time
import uuid
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray

from slamreplay.algorithms.common.posegraph import OptimizationResult, OptimizerConfig, PoseGraph, chi2, optimize
from slamreplay.algorithms.common.posegraph_init import init_chordal, init_odometry
from slamreplay.algorithms.common.robust import Kernel
from slamreplay.recorder.files import replacing

Format = Literal["g2o", "toro"]

# g2o records that carry nothing for a 2D pose graph and are skipped.
_SKIPPED = frozenset({"PARAMS_SE2OFFSET", "VERTEX_TAG", "ROBOTLASER1", "ROBOTLASER_DATA"})
_UNSUPPORTED = ("VERTEX_XY", "EDGE_SE2_XY", "EDGE_SE2_PRIOR", "VERTEX_SE3", "EDGE_SE3", "VERTEX3", "EDGE3")
_VERTEX = {"g2o": ("VERTEX_SE2",), "toro": ("VERTEX2", "VERTEX")}
_EDGE = {"g2o": ("EDGE_SE2",), "toro": ("EDGE2", "EDGE")}


class GraphFileError(ValueError):
    """A pose-graph file that cannot be read; the message names the file and line."""


@dataclass(frozen=True, slots=True, eq=False)
class GraphFile:
    """A pose graph read from a file.

    Attributes
    ----------
    graph : PoseGraph, vertices indexed 0..n-1 in increasing file id.
    vertex_ids : (n,) int64, the file id of each vertex index.
    fixed : indices of vertices named by ``FIX`` records (empty when none).
    format : "g2o" or "toro".
    has_vertices : False when the file held edges only (poses from odometry composition).
    edge_lines : (m,) int64, the 1-based line of each edge.
    """

    graph: PoseGraph
    vertex_ids: NDArray[np.int64]
    fixed: tuple[int, ...]
    format: Format
    has_vertices: bool
    edge_lines: NDArray[np.int64]


def format_of(path: str | os.PathLike[str]) -> Format:
    """The format implied by a file name: ``.g2o`` -> g2o, ``.graph`` / ``.toro`` -> TORO."""
    suffix = Path(path).suffix.lower()
    if suffix == ".g2o":
        return "g2o"
    if suffix in (".graph", ".toro"):
        return "toro"
    raise GraphFileError(f"{path}: unknown pose-graph extension {suffix!r} (use .g2o or .graph)")


def _sniff(path: Path, lines: list[str]) -> Format:
    try:
        return format_of(path)
    except GraphFileError:
        for line in lines:
            tag = line.split(maxsplit=1)[0] if line.strip() else ""
            if tag in ("VERTEX_SE2", "EDGE_SE2"):
                return "g2o"
            if tag in ("VERTEX2", "EDGE2"):
                return "toro"
        raise


def read_graph(path: str | os.PathLike[str]) -> GraphFile:
    """Read a g2o or TORO 2D pose graph (format from the extension, else from the first record).

    Raises
    ------
    GraphFileError
        With ``<path>:<line>: <what is wrong>`` for a malformed line (wrong field count or a
        non-number), an unknown or unsupported record, a duplicate vertex, a self-loop, an edge to
        a missing vertex, a non-positive-definite information matrix, or a file without edges.
    """
    p = Path(path)
    try:
        text = p.read_text()
    except (OSError, UnicodeDecodeError) as err:
        msg = f"{p}: cannot read: {err}"
        raise GraphFileError(msg) from err
    lines = text.splitlines()
    fmt = _sniff(p, lines)
    vids: list[int] = []
    vposes: list[list[float]] = []
    vline: dict[int, int] = {}
    edges: list[list[float]] = []
    elines: list[int] = []
    fix: list[tuple[int, int]] = []
    for no, line in enumerate(lines, 1):
        tok = line.split()
        if not tok or tok[0].startswith("#"):
            continue
        tag = tok[0]
        where = f"{p}:{no}"
        if tag in _VERTEX[fmt]:
            (vid,), vals = _record(tok, 4, 1, where)
            if vid in vline:
                raise GraphFileError(f"{where}: duplicate vertex {vid} (first defined on line {vline[vid]})")
            vline[vid] = no
            vids.append(vid)
            vposes.append(vals)
        elif tag in _EDGE[fmt]:
            (a, b), vals = _record(tok, 11, 2, where)
            if a == b:
                raise GraphFileError(f"{where}: edge from vertex {a} to itself")
            edges.append([a, b, *vals])
            elines.append(no)
        elif fmt == "g2o" and tag == "FIX":
            if len(tok) < 2:
                raise GraphFileError(f"{where}: FIX needs at least one vertex id")
            fix.extend((_int(t, where), no) for t in tok[1:])
        elif fmt == "g2o" and tag in _SKIPPED:
            continue
        elif tag in _UNSUPPORTED or tag.startswith(("VERTEX", "EDGE")):
            raise GraphFileError(f"{where}: unsupported record {tag!r}: only 2D pose graphs ({_describe(fmt)})")
        else:
            raise GraphFileError(f"{where}: unknown record {tag!r} in a {fmt} file ({_describe(fmt)})")
    if not edges:
        raise GraphFileError(f"{p}: no edges ({_describe(fmt)})")
    e = np.array(edges, dtype=np.float64)
    eline = np.array(elines, dtype=np.int64)
    ends = e[:, :2].astype(np.int64)
    has_vertices = bool(vids)
    if has_vertices:
        ids = np.array(vids, dtype=np.int64)
        missing = ~np.isin(ends, ids)
        if np.any(missing):
            k = int(np.flatnonzero(missing.any(1))[0])
            v = int(ends[k][missing[k]][0])
            raise GraphFileError(f"{p}:{eline[k]}: edge to missing vertex {v} (no vertex record with that id)")
    else:
        ids = np.unique(ends)
    order = np.argsort(ids, kind="stable")
    ids_sorted = ids[order]
    idx = np.searchsorted(ids_sorted, ends)
    if fmt == "g2o":
        u = e[:, 5:11]  # I11 I12 I13 I22 I23 I33
        info = np.stack([u[:, [0, 1, 2]], u[:, [1, 3, 4]], u[:, [2, 4, 5]]], 1)
    else:
        u = e[:, 5:11]  # Ixx Ixy Iyy Itt Ixt Iyt
        info = np.stack([u[:, [0, 1, 4]], u[:, [1, 2, 5]], u[:, [4, 5, 3]]], 1)
    if not np.all(np.isfinite(e)):
        k = int(np.flatnonzero(~np.isfinite(e).all(1))[0])
        raise GraphFileError(f"{p}:{eline[k]}: non-finite number in edge")
    try:
        ok = np.linalg.eigvalsh(info)[:, 0] > 0.0
    except np.linalg.LinAlgError:  # pragma: no cover - eigvalsh on finite symmetric input
        ok = np.zeros(len(info), dtype=bool)
    if not np.all(ok):
        k = int(np.flatnonzero(~ok)[0])
        raise GraphFileError(f"{p}:{eline[k]}: information matrix is not positive definite")
    fixed = []
    for vid, no in fix:
        k = int(np.searchsorted(ids_sorted, vid))
        if k >= ids_sorted.size or ids_sorted[k] != vid:
            raise GraphFileError(f"{p}:{no}: FIX of missing vertex {vid}")
        fixed.append(k)
    poses = np.zeros((ids_sorted.size, 3))
    if has_vertices:
        vp = np.array(vposes, dtype=np.float64)
        if not np.all(np.isfinite(vp)):
            k = int(np.flatnonzero(~np.isfinite(vp).all(1))[0])
            raise GraphFileError(f"{p}:{vline[vids[k]]}: non-finite number in vertex")
        poses = vp[order]
    graph = PoseGraph(poses, idx[:, 0], idx[:, 1], e[:, 2:5], info)
    if not has_vertices:
        try:
            graph = graph.with_poses(init_odometry(graph, fixed[0] if fixed else 0))
        except ValueError as err:
            msg = f"{p}: cannot compose an initial guess from the edges: {err}"
            raise GraphFileError(msg) from err
    return GraphFile(graph, ids_sorted, tuple(fixed), fmt, has_vertices, eline)


def _describe(fmt: Format) -> str:
    return "expected VERTEX_SE2, EDGE_SE2 or FIX" if fmt == "g2o" else "expected VERTEX2 or EDGE2"


def _int(tok: str, where: str) -> int:
    try:
        return int(tok)
    except ValueError as err:
        msg = f"{where}: vertex id {tok!r} is not an integer"
        raise GraphFileError(msg) from err


def _record(tok: list[str], count: int, n_ids: int, where: str) -> tuple[list[int], list[float]]:
    """Split a record's fields into ``n_ids`` integer ids and the remaining floats."""
    if len(tok) - 1 != count:
        raise GraphFileError(f"{where}: malformed {tok[0]}: expected {count} fields, got {len(tok) - 1}")
    ids = [_int(t, where) for t in tok[1 : 1 + n_ids]]
    try:
        return ids, [float(t) for t in tok[1 + n_ids :]]
    except ValueError as err:
        msg = f"{where}: malformed {tok[0]}: {err}"
        raise GraphFileError(msg) from err


def write_graph(path: str | os.PathLike[str], graph: PoseGraph, vertex_ids: NDArray[np.int64] | None = None,
                fixed: tuple[int, ...] = (), fmt: Format | None = None) -> None:
    """Write a pose graph atomically (temporary file in the same folder, then ``os.replace``).

    Parameters
    ----------
    path : destination; the format comes from ``fmt`` or else the extension (.g2o / .graph).
    graph : PoseGraph
    vertex_ids : (n,) ids to write for vertex indices (default 0..n-1).
    fixed : vertex indices written as ``FIX`` records (g2o only).
    """
    p = Path(path)
    fmt = fmt or format_of(p)
    ids = np.arange(graph.n_vertices) if vertex_ids is None else np.asarray(vertex_ids, dtype=np.int64)
    if ids.shape != (graph.n_vertices,):
        raise ValueError(f"vertex_ids must have shape ({graph.n_vertices},), got {ids.shape}")
    vtag, etag = ("VERTEX_SE2", "EDGE_SE2") if fmt == "g2o" else ("VERTEX2", "EDGE2")
    w = graph.information
    if fmt == "g2o":
        cols = [w[:, 0, 0], w[:, 0, 1], w[:, 0, 2], w[:, 1, 1], w[:, 1, 2], w[:, 2, 2]]
    else:
        cols = [w[:, 0, 0], w[:, 0, 1], w[:, 1, 1], w[:, 2, 2], w[:, 0, 2], w[:, 1, 2]]
    out = [f"{vtag} {v} {x!r} {y!r} {t!r}" for v, (x, y, t) in zip(ids.tolist(), graph.poses.tolist(), strict=True)]
    if fmt == "g2o":
        out += [f"FIX {int(ids[k])}" for k in fixed]
    ev = np.column_stack([graph.measurements, *cols]).tolist()
    out += [
        f"{etag} {a} {b} " + " ".join(repr(x) for x in row)
        for a, b, row in zip(ids[graph.i].tolist(), ids[graph.j].tolist(), ev, strict=True)
    ]
    with replacing(p) as tmp:
        tmp.write_text("\n".join(out) + "\n")


# ---------------------------------------------------------------------------------------
# slamreplay graph optimize

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

    from slamreplay.replay.engine import views
    from slamreplay.replay.engine.observer import deterministic_batcher, send_static

    digest = hashlib.sha256(source.read_bytes()).hexdigest()
    rec_id = uuid.uuid5(uuid.NAMESPACE_URL, f"slamreplay/graph-optimize/{digest}/{config}")
    bounds = views.extend_bounds(views.extend_bounds(None, before.poses[:, :2]), after.poses[:, :2])
    blueprint = views.layout(views.tab(
        "Pose graph", rrb.Vertical(views.map_view("Initial", "world/graph/initial", bounds),
                                   views.map_view("Optimized", "world/graph/optimized", bounds)),
        views.series_view("chi2 per iteration", "metrics/chi2"), columns=[3, 2]))
    rec = rr.RecordingStream(views.app_id("graph"), recording_id=rec_id, send_properties=False,
                             batcher_config=deterministic_batcher())
    rec.set_log_time_enabled(False)
    with replacing(path) as tmp:  # an error removes the half-written file
        rec.save(tmp)
        rec.send_blueprint(blueprint, make_active=True, make_default=True)
        try:
            loop = np.abs(before.i - before.j) != 1
            colors = np.where(loop[:, None], [views.ACCEPTED], [views.TRUTH]).astype(np.uint8)
            for name, g in (("initial", before), ("optimized", after)):
                send_static(rec, f"world/graph/{name}", views.MAP_FLIP)
                send_static(rec, f"world/graph/{name}/edges", rr.LineStrips2D(_segments(g), colors=colors, radii=-0.5))
                send_static(rec, f"world/graph/{name}/vertices",
                            rr.Points2D(g.poses[:, :2].astype(np.float32), radii=-1.5))
            k = np.arange(result.chi2_history.size, dtype=np.int64)
            rec.send_columns("metrics/chi2", indexes=[rr.TimeColumn("iteration", sequence=k)],
                             columns=rr.Scalars.columns(scalars=result.chi2_history))
        finally:
            rec.disconnect()

