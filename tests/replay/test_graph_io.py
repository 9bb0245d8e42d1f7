"""g2o and TORO pose-graph files: round trips, conventions, and every bad-file error."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from slamreplay.algorithms.common.posegraph import PoseGraph, chi2
from slamreplay.replay.tools.graph_io import GraphFileError, format_of, read_graph, write_graph

G2O = """# a comment
VERTEX_SE2 10 0 0 0
VERTEX_SE2 20 1.0 0.1 0.2
VERTEX_SE2 30 2.0 0.3 0.4

FIX 10
EDGE_SE2 10 20 1.0 0.0 0.1 100 1 2 200 3 300
EDGE_SE2 20 30 1.0 0.1 0.2 100 0 0 100 0 100
EDGE_SE2 10 30 2.0 0.2 0.3 50 0 0 50 0 50
"""


def write(tmp_path: Path, text: str, name: str = "g.g2o") -> Path:
    path = tmp_path / name
    path.write_text(text)
    return path


def test_read_g2o_maps_ids_information_and_fix(tmp_path: Path) -> None:
    """Vertex ids map to indices in id order; the upper triangle fills a symmetric matrix."""
    gf = read_graph(write(tmp_path, G2O))
    assert gf.format == "g2o" and gf.has_vertices and gf.fixed == (0,)
    np.testing.assert_array_equal(gf.vertex_ids, [10, 20, 30])
    np.testing.assert_array_equal(gf.graph.i, [0, 1, 0])
    np.testing.assert_array_equal(gf.graph.j, [1, 2, 2])
    np.testing.assert_array_equal(gf.graph.information[0], [[100, 1, 2], [1, 200, 3], [2, 3, 300]])
    np.testing.assert_array_equal(gf.edge_lines, [7, 8, 9])


def test_toro_information_order(tmp_path: Path) -> None:
    """TORO stores xx xy yy tt xt yt."""
    text = "VERTEX2 0 0 0 0\nVERTEX2 1 1 0 0\nEDGE2 0 1 1 0 0 100 1 200 300 2 3\n"
    gf = read_graph(write(tmp_path, text, "g.graph"))
    assert gf.format == "toro"
    np.testing.assert_array_equal(gf.graph.information[0], [[100, 1, 2], [1, 200, 3], [2, 3, 300]])


@pytest.mark.parametrize("name", ["out.g2o", "out.graph"])
def test_write_read_round_trip_is_exact(tmp_path: Path, name: str) -> None:
    """Writing then reading gives the same arrays bit for bit, ids and FIX included."""
    gf = read_graph(write(tmp_path, G2O))
    out = tmp_path / name
    write_graph(out, gf.graph, gf.vertex_ids, gf.fixed)
    back = read_graph(out)
    for field in ("poses", "i", "j", "measurements", "information"):
        np.testing.assert_array_equal(getattr(back.graph, field), getattr(gf.graph, field))
    np.testing.assert_array_equal(back.vertex_ids, gf.vertex_ids)
    assert back.fixed == (gf.fixed if name.endswith(".g2o") else ())
    assert [p.name for p in tmp_path.iterdir() if p.name.endswith(".tmp")] == []


def test_edges_only_file_is_initialized_from_odometry(tmp_path: Path) -> None:
    """Without VERTEX records, poses come from composing the edges (the first vertex at 0)."""
    text = "EDGE_SE2 0 1 1 0 1.5707963267948966 1 0 0 1 0 1\nEDGE_SE2 1 2 1 0 0 1 0 0 1 0 1\n"
    gf = read_graph(write(tmp_path, text))
    assert not gf.has_vertices
    np.testing.assert_allclose(gf.graph.poses, [[0, 0, 0], [1, 0, np.pi / 2], [1, 1, np.pi / 2]], atol=1e-12)
    assert chi2(gf.graph) == pytest.approx(0.0, abs=1e-20)


def test_format_from_content_when_extension_unknown(tmp_path: Path) -> None:
    """An unknown extension is resolved from the first record."""
    assert read_graph(write(tmp_path, G2O, "g.txt")).format == "g2o"
    assert format_of("x.graph") == "toro" and format_of("x.G2O") == "g2o"


def test_write_refuses_unknown_extension_and_bad_ids(tmp_path: Path) -> None:
    """The output format must be known; vertex_ids must match the graph."""
    g = PoseGraph(np.zeros((2, 3)), [0], [1], [[1, 0, 0]], np.eye(3)[None])
    with pytest.raises(GraphFileError, match=r"unknown pose-graph extension '\.txt'"):
        write_graph(tmp_path / "out.txt", g)
    with pytest.raises(ValueError, match="vertex_ids must have shape"):
        write_graph(tmp_path / "out.g2o", g, np.array([1, 2, 3]))


BAD = [
    ("VERTEX_SE2 0 0 0\n", r"g\.g2o:1: malformed VERTEX_SE2: expected 4 fields, got 3"),
    ("VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 0 0 0\nEDGE_SE2 0 1 1 0 0 1 0 0 1 0\n",
     r"g\.g2o:3: malformed EDGE_SE2: expected 11 fields, got 10"),
    ("VERTEX_SE2 0 0 x 0\n", r"g\.g2o:1: malformed VERTEX_SE2: could not convert string to float: 'x'"),
    ("VERTEX_SE2 a 0 0 0\n", r"g\.g2o:1: vertex id 'a' is not an integer"),
    ("VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 0 0 0\nEDGE_SE2 0 1.5 1 0 0 1 0 0 1 0 1\n", r"g\.g2o:3: vertex id '1\.5'"),
    ("VERTEX_SE2 0 0 0 0\nVERTEX_SE2 0 1 0 0\n", r"g\.g2o:2: duplicate vertex 0 \(first defined on line 1\)"),
    ("VERTEX_SE2 0 0 0 0\nEDGE_SE2 0 0 1 0 0 1 0 0 1 0 1\n", r"g\.g2o:2: edge from vertex 0 to itself"),
    ("VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 0 0 0\n\nEDGE_SE2 0 7 1 0 0 1 0 0 1 0 1\n",
     r"g\.g2o:4: edge to missing vertex 7"),
    ("VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 0 0 0\nEDGE_SE2 0 1 1 0 0 1 2 0 1 0 1\n",
     r"g\.g2o:3: information matrix is not positive definite"),
    ("VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 0 0 0\nEDGE_SE2 0 1 1 0 0 -1 0 0 1 0 1\n",
     r"g\.g2o:3: information matrix is not positive definite"),
    ("VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 0 0 0\nEDGE_SE2 0 1 nan 0 0 1 0 0 1 0 1\n",
     r"g\.g2o:3: non-finite number in edge"),
    ("VERTEX_SE2 0 inf 0 0\nVERTEX_SE2 1 0 0 0\nEDGE_SE2 0 1 1 0 0 1 0 0 1 0 1\n",
     r"g\.g2o:1: non-finite number in vertex"),
    ("VERTEX_SE2 0 0 0 0\nFOO 1 2 3\n", r"g\.g2o:2: unknown record 'FOO' in a g2o file \(expected VERTEX_SE2"),
    ("VERTEX_SE2 0 0 0 0\nVERTEX_XY 1 0 0\n", r"g\.g2o:2: unsupported record 'VERTEX_XY': only 2D pose graphs"),
    ("VERTEX2 0 0 0 0\n", r"g\.g2o:1: unsupported record 'VERTEX2'"),
    ("VERTEX_SE2 0 0 0 0\nFIX\n", r"g\.g2o:2: FIX needs at least one vertex id"),
    ("VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 0 0 0\nFIX 4\nEDGE_SE2 0 1 1 0 0 1 0 0 1 0 1\n",
     r"g\.g2o:3: FIX of missing vertex 4"),
    ("VERTEX_SE2 0 0 0 0\n# no edges\n", r"g\.g2o: no edges"),
    ("EDGE_SE2 0 1 1 0 0 1 0 0 1 0 1\nEDGE_SE2 2 3 1 0 0 1 0 0 1 0 1\n",
     r"g\.g2o: cannot compose an initial guess from the edges: graph is not connected"),
]


@pytest.mark.parametrize(("text", "match"), BAD, ids=[m.split(": ", 1)[-1][:40] for _, m in BAD])
def test_bad_g2o_files_name_the_line(tmp_path: Path, text: str, match: str) -> None:
    """Each kind of bad file raises GraphFileError naming the file, the line and the problem."""
    with pytest.raises(GraphFileError, match=match):
        read_graph(write(tmp_path, text))


def test_bad_toro_files_name_the_line(tmp_path: Path) -> None:
    """TORO errors too: wrong field count, foreign records, missing vertex."""
    cases = [
        ("VERTEX2 0 0 0 0\nVERTEX2 1 0 0 0\nEDGE2 0 1 1 0 0 1 0 1 1 0\n", r"g\.graph:3: malformed EDGE2: expected 11"),
        ("VERTEX2 0 0 0 0\nEDGE_SE2 0 1 1 0 0 1 0 0 1 0 1\n", r"g\.graph:2: unsupported record 'EDGE_SE2'"),
        ("VERTEX2 0 0 0 0\nFIX 0\n", r"g\.graph:2: unknown record 'FIX' in a toro file"),
        ("VERTEX2 0 0 0 0\nEDGE2 0 3 1 0 0 1 0 1 1 0 0\n", r"g\.graph:2: edge to missing vertex 3"),
        ("VERTEX2 0 0 0 0\nVERTEX2 1 0 0 0\nEDGE2 0 1 1 0 0 1 0 1 0 0 0\n",
         r"g\.graph:3: information matrix is not positive definite"),
    ]
    for text, match in cases:
        with pytest.raises(GraphFileError, match=match):
            read_graph(write(tmp_path, text, "g.graph"))


def test_unreadable_and_unknown_files(tmp_path: Path) -> None:
    """A missing file and an extension-less file without records are GraphFileErrors too."""
    with pytest.raises(GraphFileError, match=r"missing\.g2o: cannot read"):
        read_graph(tmp_path / "missing.g2o")
    with pytest.raises(GraphFileError, match=r"unknown pose-graph extension '\.txt'"):
        read_graph(write(tmp_path, "# nothing\n", "g.txt"))
    (tmp_path / "bin.g2o").write_bytes(b"\xff\xfe\x00")
    with pytest.raises(GraphFileError, match=r"bin\.g2o: cannot read"):
        read_graph(tmp_path / "bin.g2o")


def test_shared_datasets_read_with_reference_initial_chi2(shared_data: Path) -> None:
    """M3500 (g2o) and CSAIL / FR079 (TORO) read with the sizes and initial chi2 of their READMEs."""
    m = read_graph(shared_data / "posegraph-m3500/manhattanOlson3500.g2o")
    assert (m.graph.n_vertices, m.graph.n_edges) == (3500, 5598)
    assert chi2(m.graph) == pytest.approx(2.56643e6, rel=1e-5)
    c = read_graph(shared_data / "posegraph-toro-csail-fr079/CSAIL_P_toro.graph")
    assert (c.graph.n_vertices, c.graph.n_edges) == (1045, 1172)
    assert chi2(c.graph) == pytest.approx(1.31065e6, rel=1e-5)
    f = read_graph(shared_data / "posegraph-toro-csail-fr079/FR079_P_toro.graph")
    assert (f.graph.n_vertices, f.graph.n_edges) == (989, 1217)
    assert chi2(f.graph) == pytest.approx(8502.77, rel=1e-5)
    e = read_graph(shared_data / "pose_graphs/CSAIL.g2o")
    assert not e.has_vertices and (e.graph.n_vertices, e.graph.n_edges) == (1045, 1172)
