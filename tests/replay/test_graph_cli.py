"""``optimize_file``: the function behind ``slamreplay graph optimize``."""

from __future__ import annotations

import re
import subprocess
from pathlib import Path

import numpy as np
import pytest

from slamreplay.algorithms.common.posegraph import PoseGraph, chi2
from slamreplay.algorithms.common.se2 import between, compose
from slamreplay.replay.runs.rrd_compare import rerun_cli
from slamreplay.replay.tools.graph_io import GraphFileError, optimize_file, read_graph, write_graph

KEYS = {"vertices", "edges", "chi2_initial", "chi2_final", "edges_rejected", "iterations", "status", "time_s"}


def small_graph_file(tmp_path: Path, name: str = "in.g2o") -> Path:
    """A noisy square-ish loop of 12 poses with 3 loop closures, written to ``name``."""
    rng = np.random.default_rng(0)
    truth = np.zeros((12, 3))
    for k in range(11):
        truth[k + 1] = compose(truth[k], [1.0, 0.0, np.pi / 6 if k % 3 == 2 else 0.0])
    i, j = np.r_[np.arange(11), 0, 3, 6], np.r_[np.arange(1, 12), 11, 9, 11]
    z = between(truth[i], truth[j]) + rng.normal(0, 0.01, (i.size, 3))
    g = PoseGraph(truth + rng.normal(0, 0.3, truth.shape) * (np.arange(12) > 0)[:, None], i, j, z,
                  np.broadcast_to(np.eye(3) * 1e4, (i.size, 3, 3)))
    path = tmp_path / name
    write_graph(path, g, np.arange(100, 112))
    return path


@pytest.mark.parametrize(("solver", "init", "robust"), [("gn", "odometry", "dcs"), ("lm", "chordal", "none"),
                                                        ("gn", "file", "huber"), ("lm", "odometry", "cauchy")])
def test_optimize_file_summary_and_output(tmp_path: Path, solver: str, init: str, robust: str) -> None:
    """The summary has the documented keys; the output reads back at the optimized chi2."""
    src = small_graph_file(tmp_path)
    out = tmp_path / "out.g2o"
    s = optimize_file(src, out, solver=solver, init=init, robust=robust)
    assert set(s) == KEYS
    assert (s["vertices"], s["edges"], s["status"], s["edges_rejected"]) == (12, 14, "converged", 0)
    assert s["chi2_final"] < s["chi2_initial"] and s["iterations"] >= 1 and s["time_s"] > 0
    back = read_graph(out)
    np.testing.assert_array_equal(back.vertex_ids, np.arange(100, 112))
    assert chi2(back.graph) == pytest.approx(s["chi2_final"], rel=1e-12)


def test_output_format_follows_extension_and_rrd_is_written(tmp_path: Path) -> None:
    """g2o in, TORO out; the .rrd appears whole (no temporary left) and twice gives the same summary."""
    src = small_graph_file(tmp_path)
    out, rrd = tmp_path / "out.graph", tmp_path / "run.rrd"
    a = optimize_file(src, out, rrd_path=rrd)
    assert read_graph(out).format == "toro"
    assert rrd.stat().st_size > 1000
    assert sorted(p.name for p in tmp_path.iterdir()) == ["in.g2o", "out.graph", "run.rrd"]
    b = optimize_file(src, out, rrd_path=rrd)
    assert {k: v for k, v in a.items() if k != "time_s"} == {k: v for k, v in b.items() if k != "time_s"}


def test_rrd_holds_the_graphs_and_chi2_and_is_deterministic(tmp_path: Path) -> None:
    """Both graphs and one chi2 per iteration are in the recording; a second run has equal content."""
    cli = rerun_cli()
    if cli is None:
        pytest.skip("rerun executable not found")
    src = small_graph_file(tmp_path)
    a, b = tmp_path / "a.rrd", tmp_path / "b.rrd"
    s = optimize_file(src, tmp_path / "out.g2o", rrd_path=a)
    optimize_file(src, tmp_path / "out.g2o", rrd_path=b)
    printed = subprocess.run([cli, "rrd", "print", str(a)], capture_output=True, text=True, check=True).stdout
    rows = {m.group(2): int(m.group(1)) for m in re.finditer(r"with (\d+) rows .* - (/\S+) - data columns", printed)}
    assert rows["/metrics/chi2"] == s["iterations"] + 1
    assert {"/world/graph/initial/edges", "/world/graph/initial/vertices", "/world/graph/optimized/edges",
            "/world/graph/optimized/vertices"} <= set(rows)
    assert subprocess.run([cli, "rrd", "compare", str(a), str(b)], capture_output=True).returncode == 0


def test_bad_arguments_name_the_argument(tmp_path: Path) -> None:
    """Unknown solver, init or kernel are ValueErrors naming the argument; nothing is written."""
    src = small_graph_file(tmp_path)
    for kwargs, match in [({"solver": "dogleg"}, "solver must be one of"), ({"init": "tree"}, "init must be one of"),
                          ({"robust": "tukey"}, "robust must be one of")]:
        with pytest.raises(ValueError, match=match):
            optimize_file(src, tmp_path / "out.g2o", **kwargs)
    with pytest.raises(GraphFileError, match="unknown pose-graph extension"):
        optimize_file(src, tmp_path / "out.json")
    bad = tmp_path / "bad.g2o"
    bad.write_text("VERTEX_SE2 0 0 0 0\nEDGE_SE2 0 9 1 0 0 1 0 0 1 0 1\n")
    with pytest.raises(GraphFileError, match=r"bad\.g2o:2: edge to missing vertex 9"):
        optimize_file(bad, tmp_path / "out.g2o")
    island = tmp_path / "island.g2o"
    island.write_text("VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 1 0 0\nVERTEX_SE2 2 5 0 0\nEDGE_SE2 0 1 1 0 0 1 0 0 1 0 1\n")
    with pytest.raises(GraphFileError, match=r"island\.g2o: graph is not connected: vertex 2 is unreachable"):
        optimize_file(island, tmp_path / "out.g2o")
    with pytest.raises(GraphFileError, match=r"island\.g2o: graph has 2 connected components"):
        optimize_file(island, tmp_path / "out.g2o", init="file")
    assert not (tmp_path / "out.g2o").exists()


def test_csail_toro_optimum_through_the_file_api(shared_data: Path, tmp_path: Path) -> None:
    """CSAIL (TORO) from the file's guess, without a kernel and with the default (DCS): chi2 38.956."""
    src = shared_data / "posegraph-toro-csail-fr079/CSAIL_P_toro.graph"
    s = optimize_file(src, tmp_path / "csail.g2o", init="file", robust="none")
    assert s["status"] == "converged" and s["chi2_final"] == pytest.approx(38.956, rel=1e-4)
    assert s["chi2_initial"] == pytest.approx(1.31065e6, rel=1e-5)
    d = optimize_file(src, tmp_path / "csail_dcs.g2o", init="file")
    assert d["status"] == "converged" and d["edges_rejected"] == 0
    assert d["chi2_final"] == pytest.approx(38.956, rel=1e-4)


def test_default_rejects_a_false_loop_closure_and_reports_it(tmp_path: Path) -> None:
    """A wrong closure added to the file: the default drops it; chi2_final is over the kept edges."""
    good = read_graph(small_graph_file(tmp_path, "good.g2o")).graph
    g = PoseGraph(good.poses, np.r_[good.i, 2], np.r_[good.j, 8], np.r_[good.measurements, [[4.0, -3.0, 1.0]]],
                  np.r_[good.information, good.information[:1]])
    src = tmp_path / "bad.g2o"
    write_graph(src, g, np.arange(100, 112))
    s = optimize_file(src, tmp_path / "out.g2o")
    clean = optimize_file(tmp_path / "good.g2o", tmp_path / "clean.g2o")
    assert s["edges"] == 15 and s["edges_rejected"] == 1 and s["status"] == "converged"
    assert s["chi2_final"] == pytest.approx(clean["chi2_final"], rel=1e-6)
    out = read_graph(tmp_path / "out.g2o").graph  # every edge is written back, the rejected one too
    assert out.n_edges == 15 and chi2(out) > 100 * s["chi2_final"]
