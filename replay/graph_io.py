"""Read and write 2D pose graphs in g2o (``VERTEX_SE2``/``EDGE_SE2``) and TORO (``VERTEX2``/``EDGE2``) text.

g2o: ``EDGE_SE2 i j dx dy dtheta I11 I12 I13 I22 I23 I33`` (upper triangle, row-major, order
x, y, theta). TORO: ``EDGE2 i j dx dy dtheta Ixx Ixy Iyy Itt Ixt Iyt``. Both store the pose of j
in the frame of i and an *information* matrix. ``FIX id`` (g2o) names gauge vertices. Files with
edges only get their initial guess by composing odometry along a spanning tree.
"""

from __future__ import annotations

import os
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
from numpy.typing import NDArray

from slamreplay.algorithms.common.posegraph import PoseGraph
from slamreplay.algorithms.common.posegraph_init import init_odometry

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
    fd, tmp = tempfile.mkstemp(prefix=f".{p.name}.", suffix=".tmp", dir=p.parent)
    try:
        with os.fdopen(fd, "w") as f:
            f.write("\n".join(out) + "\n")
        os.replace(tmp, p)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
