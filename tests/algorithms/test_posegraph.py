"""Pose-graph optimizer: Jacobians, known optima, robust kernels, covariances, incremental mode, datasets."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import scipy.sparse as sp
from hypothesis import given, settings
from hypothesis import strategies as st

import slamreplay.algorithms.common.sparse_cholesky as sc
from slamreplay.algorithms.common.posegraph import (
    OptimizerConfig,
    PoseGraph,
    Status,
    chi2,
    edge_errors,
    linearize,
    optimize,
)
from slamreplay.algorithms.common.posegraph_analysis import aligned_position_rmse, marginal_covariances
from slamreplay.algorithms.common.posegraph_incremental import IncrementalConfig, IncrementalOptimizer
from slamreplay.algorithms.common.posegraph_init import init_chordal, init_odometry, spanning_tree
from slamreplay.algorithms.common.robust import Kernel, weights_and_cost
from slamreplay.algorithms.common.se2 import between, compose, from_matrix, to_matrix, wrap_angle
from slamreplay.replay.tools.graph_io import read_graph

NONE = OptimizerConfig(kernel=Kernel.NONE)
angle = st.floats(-np.pi, np.pi, allow_nan=False)
coord = st.floats(-50.0, 50.0, allow_nan=False)
pose = st.tuples(coord, coord, angle)


def random_graph(
    rng: np.random.Generator, n: int = 30, loops: int = 10, noise: float = 0.02
) -> tuple[PoseGraph, np.ndarray]:
    """A seeded random walk with noisy odometry and loop closures; returns (graph, true poses)."""
    steps = np.column_stack([rng.uniform(0.5, 1.5, n - 1), rng.normal(0, 0.2, n - 1), rng.normal(0, 0.4, n - 1)])
    truth = np.zeros((n, 3))
    for k in range(n - 1):
        truth[k + 1] = compose(truth[k], steps[k])
    a = rng.integers(0, n - 3, loops)
    b = a + rng.integers(2, 8, loops).clip(max=n - 1 - a)
    i, j = np.r_[np.arange(n - 1), a], np.r_[np.arange(1, n), b]
    z = between(truth[i], truth[j]) + rng.normal(0, noise, (i.size, 3))
    info = np.broadcast_to(np.diag([1 / noise**2, 1 / noise**2, 1 / noise**2]), (i.size, 3, 3))
    g = PoseGraph(np.zeros((n, 3)), i, j, z, info)
    return g.with_poses(init_odometry(g)), truth


def numeric_jacobians(p: np.ndarray, i: np.ndarray, j: np.ndarray, z: np.ndarray, h: float = 1e-6) -> tuple:
    """Central finite differences of the edge errors w.r.t. the two endpoint poses."""
    out = []
    for end in (i, j):
        jac = np.zeros((i.size, 3, 3))
        for c in range(3):
            dp, dm = p.copy(), p.copy()
            dp[end, c] += h
            dm[end, c] -= h
            ep, em = linearize(dp, i, j, z, jacobians=False)[0], linearize(dm, i, j, z, jacobians=False)[0]
            jac[:, :, c] = (ep - em).T / (2 * h)
        out.append(jac)
    return tuple(out)


@settings(max_examples=60, deadline=None)
@given(pi=pose, pj=pose, z=st.tuples(st.floats(-5, 5), st.floats(-5, 5), st.floats(-3.0, 3.0)))
def test_jacobians_match_finite_differences(pi: tuple, pj: tuple, z: tuple) -> None:
    """Analytic de/dX_i and de/dX_j equal central differences (away from the angle wrap)."""
    p = np.array([pi, pj], dtype=float)
    i, j, zz = np.array([0]), np.array([1]), np.array([z], dtype=float)
    e = linearize(p, i, j, zz, jacobians=False)[0]
    if abs(abs(e[2, 0]) - np.pi) < 1e-3:  # the wrap makes e discontinuous there
        return
    _, ji, jj = linearize(p, i, j, zz)
    ni, nj = numeric_jacobians(p, i, j, zz)
    np.testing.assert_allclose(ji.transpose(2, 0, 1), ni, atol=1e-6 * (1 + np.abs(p).max()))
    np.testing.assert_allclose(jj.transpose(2, 0, 1), nj, atol=1e-6 * (1 + np.abs(p).max()))


@settings(max_examples=60, deadline=None)
@given(pi=pose, pj=pose, z=pose)
def test_error_is_g2o_edge_se2_convention(pi: tuple, pj: tuple, z: tuple) -> None:
    """e = t2v(Z^-1 X_i^-1 X_j) computed with homogeneous matrices, angle wrapped."""
    g = PoseGraph(np.array([pi, pj]), [0], [1], [z], [np.eye(3)])
    m = np.linalg.inv(to_matrix(z)) @ np.linalg.inv(to_matrix(pi)) @ to_matrix(pj)
    e, ref = edge_errors(g)[0], from_matrix(m)
    np.testing.assert_allclose(e[:2], ref[:2], atol=1e-7)
    assert abs(wrap_angle(e[2] - ref[2])) < 1e-7 and -np.pi <= e[2] < np.pi


@settings(max_examples=30, deadline=None)
@given(t=pose, seed=st.integers(0, 2**16))
def test_chi2_invariant_under_global_rigid_transform(t: tuple, seed: int) -> None:
    """Moving every pose by the same rigid transform leaves every edge error unchanged."""
    g, _ = random_graph(np.random.default_rng(seed), n=12, loops=4)
    moved = compose(np.asarray(t, dtype=float), g.poses)
    assert chi2(g, moved) == pytest.approx(chi2(g), rel=1e-6, abs=1e-9)


def test_square_loop_with_consistent_measurements_reaches_zero() -> None:
    """A square whose measurements agree is recovered exactly from a perturbed guess (chi2 0)."""
    truth = np.array([[0, 0, 0], [2, 0, np.pi / 2], [2, 2, np.pi], [0, 2, -np.pi / 2]], dtype=float)
    i, j = np.array([0, 1, 2, 3]), np.array([1, 2, 3, 0])
    guess = truth + np.array([[0, 0, 0], [0.3, -0.2, 0.2], [-0.4, 0.3, -0.3], [0.2, 0.2, 0.25]])
    g = PoseGraph(guess, i, j, between(truth[i], truth[j]), np.broadcast_to(np.eye(3) * 10, (4, 3, 3)))
    for method in ("gn", "lm"):
        r = optimize(g, OptimizerConfig(method=method, kernel=Kernel.NONE))
        assert r.status is Status.CONVERGED
        assert r.chi2_final < 1e-20
        np.testing.assert_allclose(r.poses[:, :2], truth[:, :2], atol=1e-10)
        np.testing.assert_allclose(wrap_angle(r.poses[:, 2] - truth[:, 2]), 0, atol=1e-10)


def test_three_node_graph_reaches_its_analytic_optimum() -> None:
    """Chain 0-1-2 (1 m each) and closure 0-2 of 2.3 m: optimum x1 = 1.1, x2 = 2.2, chi2 = 0.03."""
    z = np.array([[1, 0, 0], [1, 0, 0], [2.3, 0, 0]], dtype=float)
    g = PoseGraph([[0, 0, 0], [0.5, 0.4, 0.3], [3, -0.5, -0.2]], [0, 1, 0], [1, 2, 2], z,
                  np.broadcast_to(np.eye(3), (3, 3, 3)))
    r = optimize(g, OptimizerConfig(kernel=Kernel.NONE, rel_tol=0.0, step_tol=1e-14))
    np.testing.assert_allclose(r.poses, [[0, 0, 0], [1.1, 0, 0], [2.2, 0, 0]], atol=1e-8)  # cost ~ sqrt(eps)
    assert r.chi2_final == pytest.approx(0.03, rel=1e-10)
    assert r.chi2_history[0] == pytest.approx(r.chi2_initial) and r.chi2_history[-1] == pytest.approx(0.03)


def test_gn_and_lm_agree_and_gauge_stays() -> None:
    """GN and LM reach the same optimum on a noisy random graph; the gauge pose never moves."""
    g, _ = random_graph(np.random.default_rng(3), n=60, loops=25)
    gn = optimize(g, NONE)
    lm = optimize(g, OptimizerConfig(method="lm", kernel=Kernel.NONE))
    assert gn.status is lm.status is Status.CONVERGED
    assert lm.chi2_final == pytest.approx(gn.chi2_final, rel=1e-6)
    np.testing.assert_allclose(lm.poses, gn.poses, atol=1e-5)
    other = optimize(g, OptimizerConfig(kernel=Kernel.NONE, gauge=7))
    np.testing.assert_array_equal(other.poses[7], g.poses[7])
    np.testing.assert_array_equal(gn.poses[0], g.poses[0])


def test_status_max_iterations_and_diverged(monkeypatch: pytest.MonkeyPatch) -> None:
    """An exhausted budget is MAX_ITERATIONS; a failed factorization is DIVERGED, never an exception."""
    g, _ = random_graph(np.random.default_rng(4), n=40, loops=15, noise=0.05)
    g = g.with_poses(g.poses + np.random.default_rng(0).normal(0, 0.5, g.poses.shape) * (np.arange(40) > 0)[:, None])
    r = optimize(g, OptimizerConfig(kernel=Kernel.NONE, max_iterations=1, rel_tol=0.0, step_tol=0.0))
    assert r.status is Status.MAX_ITERATIONS and r.iterations == 1
    monkeypatch.setattr(sc.SparseCholesky, "factor", lambda self, h: False)
    r = optimize(g, NONE)
    assert r.status is Status.DIVERGED
    np.testing.assert_array_equal(r.poses, g.poses)  # the best estimate seen: the initial one


def test_optimize_deterministic() -> None:
    """Same input, same bits."""
    g, _ = random_graph(np.random.default_rng(5), n=50, loops=20)
    a, b = optimize(g), optimize(g)
    np.testing.assert_array_equal(a.poses, b.poses)
    np.testing.assert_array_equal(a.chi2_history, b.chi2_history)


def test_robust_kernels_weights_and_costs() -> None:
    """DCS weight is s^2 with s = min(1, 2 Phi / (Phi + chi2)); weights are d rho / d chi2."""
    u = np.array([0.0, 0.5, 1.0, 3.0, 100.0])
    w, rho = weights_and_cost(Kernel.DCS, u, 1.0)
    np.testing.assert_allclose(w, np.minimum(1, 2 / (1 + u)) ** 2)
    np.testing.assert_allclose(rho[:3], u[:3])
    for kernel in Kernel:
        x = np.linspace(0.01, 50, 200)
        w, _ = weights_and_cost(kernel, x, 2.0)
        h = 1e-6
        d = (weights_and_cost(kernel, x + h, 2.0)[1] - weights_and_cost(kernel, x - h, 2.0)[1]) / (2 * h)
        np.testing.assert_allclose(w, d, rtol=1e-5, atol=1e-8)
    with pytest.raises(ValueError, match="parameter must be finite and > 0"):
        weights_and_cost(Kernel.HUBER, u, 0.0)


@pytest.mark.parametrize(("kernel", "bound"), [(Kernel.DCS, 2.0), (Kernel.CAUCHY, 2.0), (Kernel.HUBER, 20.0)])
def test_robust_kernel_rejects_a_false_loop_closure(kernel: Kernel, bound: float) -> None:
    """One wrong loop closure bends the plain solution; DCS and Cauchy keep the truth, Huber (not
    redescending) only limits the damage."""
    g, truth = random_graph(np.random.default_rng(6), n=40, loops=12, noise=0.01)
    bad = PoseGraph(g.poses, np.r_[g.i, 5], np.r_[g.j, 30], np.r_[g.measurements, [[3.0, -2.0, 1.0]]],
                    np.r_[g.information, g.information[:1]])
    plain = aligned_position_rmse(optimize(bad, NONE).poses, truth)
    robust = optimize(bad, OptimizerConfig(kernel=kernel, kernel_parameter=1.0))
    clean = aligned_position_rmse(optimize(g, NONE).poses, truth)
    assert aligned_position_rmse(robust.poses, truth) < min(bound * clean, 0.2 * plain)
    assert robust.weights[-1] < 0.01 and np.all(robust.weights[: g.n_edges - 12] == 1.0)


def test_marginal_covariances_match_the_dense_inverse() -> None:
    """Blocks of H^-1 from selected-column solves equal the dense inverse of J^T Omega J."""
    g, _ = random_graph(np.random.default_rng(7), n=25, loops=8)
    g = g.with_poses(optimize(g, NONE).poses)
    _, ji, jj = linearize(g.poses, g.i, g.j, g.measurements)
    jac = np.zeros((3 * g.n_edges, 3 * g.n_vertices))
    for k in range(g.n_edges):
        jac[3 * k : 3 * k + 3, 3 * g.i[k] : 3 * g.i[k] + 3] = ji[:, :, k]
        jac[3 * k : 3 * k + 3, 3 * g.j[k] : 3 * g.j[k] + 3] = jj[:, :, k]
    w = np.zeros((3 * g.n_edges, 3 * g.n_edges))
    for k in range(g.n_edges):
        w[3 * k : 3 * k + 3, 3 * k : 3 * k + 3] = g.information[k]
    cov = np.linalg.inv((jac.T @ w @ jac)[3:, 3:])
    sel = np.array([0, 3, 24, 11])
    got = marginal_covariances(g, sel, NONE, batch=2)
    np.testing.assert_array_equal(got[0], 0.0)
    for row, v in enumerate(sel[1:], 1):
        np.testing.assert_allclose(got[row], cov[3 * v - 3 : 3 * v, 3 * v - 3 : 3 * v], rtol=1e-8)


def test_initializations() -> None:
    """Odometry composes the chain exactly; chordal recovers consistent graphs exactly."""
    rng = np.random.default_rng(8)
    g, truth = random_graph(rng, n=30, loops=10, noise=1e-9)
    np.testing.assert_allclose(init_odometry(g), truth, atol=1e-6)
    np.testing.assert_allclose(init_chordal(g), truth, atol=1e-6)
    parent, edge, _ = spanning_tree(g)
    assert parent[0] == 0 and edge[0] == -1 and np.all(np.abs(g.i[edge[1:]] - g.j[edge[1:]]) == 1)


def test_incremental_matches_batch() -> None:
    """Feeding the graph vertex by vertex, then a final update, ends at the batch optimum."""
    g, _ = random_graph(np.random.default_rng(9), n=50, loops=20)
    inc = IncrementalOptimizer(IncrementalConfig(OptimizerConfig(kernel=Kernel.NONE, max_iterations=3)))
    newest = np.maximum(g.i, g.j)
    closures = 0
    for v in range(1, g.n_vertices):
        k = np.flatnonzero(newest == v)
        res = inc.step(g.i[k], g.j[k], g.measurements[k], g.information[k])
        closures += res.loop_closures
        assert res.n_vertices == v + 1 and (res.iterations > 0) == (res.loop_closures > 0)
    assert closures == g.n_edges - (g.n_vertices - 1)  # every vertex is placed by exactly one edge
    batch = optimize(g, NONE)
    assert chi2(g, inc.poses) == pytest.approx(batch.chi2_final, rel=1e-4)
    with pytest.raises(ValueError, match="new vertex 50 is not linked"):
        inc.step([52], [53], [[1.0, 0, 0]], [np.eye(3)])
    with pytest.raises(ValueError, match="at least one edge"):
        inc.step([], [], np.zeros((0, 3)), np.zeros((0, 3, 3)))
    with pytest.raises(ValueError, match="optimizer.gauge must be 0"):
        IncrementalConfig(OptimizerConfig(gauge=3))
    with pytest.raises(ValueError, match="first_pose must be a finite"):
        IncrementalOptimizer(first_pose=(0.0, 1.0))


def test_cholmod_backend_wiring(monkeypatch: pytest.MonkeyPatch) -> None:
    """The CHOLMOD path (analyze once, refactor in place) gives the SuperLU answer (fake sksparse)."""
    calls = {"analyze": 0, "factor": 0}

    class FakeFactor:
        def cholesky_inplace(self, h: object) -> None:
            calls["factor"] += 1
            self.h = h

        def __call__(self, rhs: np.ndarray) -> np.ndarray:
            import scipy.sparse.linalg as sla

            return np.asarray(sla.spsolve(self.h.tocsc(), rhs))

    def analyze(h: object, **kwargs: str) -> FakeFactor:
        calls["analyze"] += 1
        assert kwargs == {"mode": "simplicial", "ordering_method": "natural"}  # h comes fill-reduced
        return FakeFactor()

    g, _ = random_graph(np.random.default_rng(10), n=30, loops=10)
    ref = optimize(g, NONE)
    if not sc.HAVE_CHOLMOD:
        with pytest.raises(ValueError, match="scikit-sparse"):
            sc.SparseCholesky("cholmod")
    monkeypatch.setattr(sc, "_cholmod_analyze", analyze)
    monkeypatch.setattr(sc, "HAVE_CHOLMOD", True)
    r = optimize(g, OptimizerConfig(kernel=Kernel.NONE, linear_solver="cholmod"))
    assert r.linear_solver == "cholmod" and calls["analyze"] == 1 and calls["factor"] == r.n_factorizations
    np.testing.assert_allclose(r.poses, ref.poses, atol=1e-9)


def test_bad_input_raises_value_error_naming_the_argument() -> None:
    """Bad shapes, indices, information, gauge or config are ValueErrors that name the culprit."""
    eye = np.eye(3)[None]
    with pytest.raises(ValueError, match="poses must have shape"):
        PoseGraph(np.zeros((2, 2)), [0], [1], [[1, 0, 0]], eye)
    with pytest.raises(ValueError, match="poses must be finite"):
        PoseGraph([[0, 0, 0], [np.nan, 0, 0]], [0], [1], [[1, 0, 0]], eye)
    with pytest.raises(ValueError, match="out of range"):
        PoseGraph(np.zeros((2, 3)), [0], [2], [[1, 0, 0]], eye)
    with pytest.raises(ValueError, match="self-loop"):
        PoseGraph(np.zeros((2, 3)), [1], [1], [[1, 0, 0]], eye)
    with pytest.raises(ValueError, match="measurements must have shape"):
        PoseGraph(np.zeros((2, 3)), [0], [1], [[1, 0]], eye)
    with pytest.raises(ValueError, match=r"information\[0\] is not symmetric positive definite"):
        PoseGraph(np.zeros((2, 3)), [0], [1], [[1, 0, 0]], -eye)
    with pytest.raises(ValueError, match="i and j must have the same shape"):
        PoseGraph(np.zeros((2, 3)), [0, 1], [1], [[1, 0, 0]], eye)
    g = PoseGraph(np.zeros((3, 3)), [0], [1], [[1, 0, 0]], eye)
    with pytest.raises(ValueError, match="2 connected components"):
        optimize(g)
    g = PoseGraph(np.zeros((2, 3)), [0], [1], [[1, 0, 0]], eye)
    with pytest.raises(ValueError, match="gauge must be vertex indices"):
        optimize(g, OptimizerConfig(gauge=5))
    with pytest.raises(ValueError, match="method must be"):
        OptimizerConfig(method="dogleg")
    with pytest.raises(ValueError, match="kernel_parameter must be > 0"):
        OptimizerConfig(kernel_parameter=-1.0)
    with pytest.raises(ValueError, match="max_iterations must be >= 0"):
        OptimizerConfig(max_iterations=-1)
    with pytest.raises(ValueError, match="graduated_factor must be in"):
        OptimizerConfig(graduated_factor=1.0)
    with pytest.raises(ValueError, match="inlier_gate must be in"):
        OptimizerConfig(inlier_gate=1.0)
    with pytest.raises(ValueError, match="linear_solver must be"):
        OptimizerConfig(linear_solver="umfpack")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="vertices must be in"):
        marginal_covariances(g, [4])
    with pytest.raises(ValueError, match="poses must have shape"):
        g.with_poses(np.zeros((3, 3)))


# ---- reference datasets (../shared/data) ------------------------------------------------------

REFERENCE = [  # file, reference optimum chi2 (g2o EDGE_SE2 convention), start
    ("posegraph-m3500/manhattanOlson3500.g2o", 146.077, "file"),
    ("posegraph-toro-csail-fr079/CSAIL_P_toro.graph", 38.956, "file"),
    ("posegraph-toro-csail-fr079/FR079_P_toro.graph", 37.599, "file"),
    ("pose_graphs/intel.g2o", 45.005, "odometry"),
    ("pose_graphs/manhattan.g2o", 3549.04, "odometry"),
    ("pose_graphs/CSAIL.g2o", 40.555, "odometry"),
    ("pose_graphs/city10000.g2o", 511.985, "odometry"),
]


@pytest.mark.parametrize(("name", "optimum", "start"), REFERENCE, ids=[r[0].split("/")[1] for r in REFERENCE])
def test_reference_optimum_reached(shared_data: Path, name: str, optimum: float, start: str) -> None:
    """Gauss-Newton without a kernel reaches the published/reference chi2 within 0.01 %."""
    g = read_graph(shared_data / name).graph
    if start == "odometry":
        g = g.with_poses(init_odometry(g))
    r = optimize(g, NONE)
    assert r.status is Status.CONVERGED
    assert r.chi2_final == pytest.approx(optimum, rel=1e-4)


@pytest.mark.parametrize(("name", "optimum", "start"), REFERENCE, ids=[r[0].split("/")[1] for r in REFERENCE])
def test_default_options_reach_reference_optimum(shared_data: Path, name: str, optimum: float, start: str) -> None:
    """Default options (graduated DCS, chi-square gate, plain re-solve): the reference chi2, 0 rejected."""
    g = read_graph(shared_data / name).graph
    if start == "odometry":
        g = g.with_poses(init_odometry(g))
    r = optimize(g)
    assert r.status is Status.CONVERGED and r.edges_rejected == 0
    assert r.chi2_final == pytest.approx(optimum, rel=1e-4)


@pytest.mark.parametrize("name", ["posegraph-m3500/manhattanOlson3500.g2o", "pose_graphs/intel.g2o"])
def test_reference_optimum_lm_and_chordal(shared_data: Path, name: str) -> None:
    """LM from the file and GN from the chordal start reach the same optimum as GN."""
    g = read_graph(shared_data / name).graph
    gn = optimize(g, NONE)
    lm = optimize(g, OptimizerConfig(method="lm", kernel=Kernel.NONE))
    ch = optimize(g.with_poses(init_chordal(g)), NONE)
    assert lm.chi2_final == pytest.approx(gn.chi2_final, rel=1e-4)
    assert ch.chi2_final == pytest.approx(gn.chi2_final, rel=1e-4)
    assert ch.iterations <= gn.iterations


def test_mit_odometry_and_chordal_minima(shared_data: Path) -> None:
    """MIT: odometry ends in a poor local minimum (~770.7); the chordal start reaches ~41.16."""
    g = read_graph(shared_data / "pose_graphs/MIT.g2o").graph
    odo = optimize(g.with_poses(init_odometry(g)), NONE)
    ch = optimize(g.with_poses(init_chordal(g)), NONE)
    ch_lm = optimize(g.with_poses(init_chordal(g)), OptimizerConfig(method="lm", kernel=Kernel.NONE))
    assert odo.status is ch.status is Status.CONVERGED
    assert np.isfinite(odo.chi2_final) and ch.chi2_final < odo.chi2_final
    assert ch.chi2_final == pytest.approx(41.163, rel=1e-4)
    assert ch_lm.chi2_final == pytest.approx(ch.chi2_final, rel=1e-4)
    odo_default = optimize(g.with_poses(init_odometry(g)))  # DCS leaves the odometry basin
    assert odo_default.edges_rejected == 0 and odo_default.chi2_final == pytest.approx(41.163, rel=1e-4)


def test_m3500_dcs_with_ten_percent_false_loop_closures(shared_data: Path) -> None:
    """10 % random false loop closures: with DCS the RMSE vs ground truth stays within 10 % of clean."""
    root = shared_data / "posegraph-m3500"
    g = read_graph(root / "manhattanOlson3500.g2o").graph
    truth = np.loadtxt(root / "manhattanOlson3500_nodes_groundTruth.dat")
    clean = aligned_position_rmse(optimize(g, NONE).poses, truth)
    assert clean == pytest.approx(0.794, abs=0.001)
    rng = np.random.default_rng(2013)
    k = round(0.1 * g.n_edges)
    a = rng.integers(0, g.n_vertices, k)
    b = (a + rng.integers(2, g.n_vertices - 1, k)) % g.n_vertices  # never |a - b| <= 1
    z = np.column_stack([rng.uniform(-10, 10, k), rng.uniform(-10, 10, k), rng.uniform(-np.pi, np.pi, k)])
    loop_info = g.information[np.flatnonzero(np.abs(g.i - g.j) != 1)[0]]
    bad = PoseGraph(g.poses, np.r_[g.i, a], np.r_[g.j, b], np.r_[g.measurements, z],
                    np.r_[g.information, np.broadcast_to(loop_info, (k, 3, 3))])
    r = optimize(bad)  # default options: graduated DCS, chi-square gate, plain re-solve
    rmse = aligned_position_rmse(r.poses, truth)
    assert r.status is Status.CONVERGED
    assert rmse <= 1.1 * clean
    assert r.edges_rejected == k and not r.inliers[g.n_edges :].any() and np.all(r.weights[g.n_edges :] == 0.0)
    assert r.chi2_final == pytest.approx(146.077, rel=1e-4)  # the clean optimum, over the kept edges


def test_default_options_reject_exactly_the_false_loop_closures() -> None:
    """Synthetic graph with 4 wrong closures: the default two-stage solve drops those and only those."""
    g, truth = random_graph(np.random.default_rng(21), n=60, loops=25, noise=0.01)
    wrong_i, wrong_j = np.array([3, 10, 20, 41]), np.array([30, 52, 47, 58])
    z = between(truth[wrong_i], truth[wrong_j]) + [[2.0, -1.5, 0.8], [-3.0, 1.0, -1.2], [1.5, 2.5, 2.0],
                                                   [0.0, -4.0, 0.5]]
    bad = PoseGraph(g.poses, np.r_[g.i, wrong_i], np.r_[g.j, wrong_j], np.r_[g.measurements, z],
                    np.r_[g.information, g.information[:4]])
    r = optimize(bad)
    clean = optimize(g, NONE)
    np.testing.assert_array_equal(np.flatnonzero(~r.inliers), g.n_edges + np.arange(4))
    assert r.edges_rejected == 4 and r.status is Status.CONVERGED
    assert r.chi2_final == pytest.approx(clean.chi2_final, rel=1e-6)
    assert r.chi2_final == pytest.approx(float(r.edge_chi2[r.inliers].sum()), rel=1e-12)
    np.testing.assert_allclose(r.poses, clean.poses, atol=1e-6)
    # the robust stage alone (old DCS behaviour) keeps every edge and reports chi2 over all of them
    one = optimize(bad, OptimizerConfig(graduated=False, inlier_gate=None))
    assert one.edges_rejected == 0 and one.inliers.all() and one.weights[-4:].max() < 0.01


def test_clean_graph_rejects_nothing_and_matches_plain_least_squares() -> None:
    """Without outliers the default (DCS, gate, re-solve) ends at the plain optimum, 0 rejected."""
    g, _ = random_graph(np.random.default_rng(22), n=60, loops=25, noise=0.01)
    r, plain = optimize(g), optimize(g, NONE)
    assert r.edges_rejected == 0 and r.inliers.all()
    assert r.chi2_final == pytest.approx(plain.chi2_final, rel=1e-6)
    assert r.chi2_history.size == r.cost_history.size == r.iterations + 1


@pytest.mark.skipif(not sc.HAVE_CVXOPT, reason="cvxopt is not installed")
def test_cvxopt_cholmod_reuses_the_analysis(monkeypatch: pytest.MonkeyPatch) -> None:
    """CVXOPT's CHOLMOD: one symbolic analysis per optimization, a numeric one per factorization, SuperLU's answer."""
    calls = {"symbolic": 0, "numeric": 0}
    symbolic, numeric = sc._cvx_cholmod.symbolic, sc._cvx_cholmod.numeric

    def count(name: str, fn: object) -> object:
        def wrapped(*args: object, **kwargs: object) -> object:
            calls[name] += 1
            return fn(*args, **kwargs)  # type: ignore[operator]
        return wrapped

    monkeypatch.setattr(sc, "_cholmod_analyze", None)  # CVXOPT even where scikit-sparse is installed
    monkeypatch.setattr(sc._cvx_cholmod, "symbolic", count("symbolic", symbolic))
    monkeypatch.setattr(sc._cvx_cholmod, "numeric", count("numeric", numeric))
    g, _ = random_graph(np.random.default_rng(11), n=40, loops=12)
    ref = optimize(g, OptimizerConfig(kernel=Kernel.NONE, linear_solver="superlu"))
    r = optimize(g, OptimizerConfig(kernel=Kernel.NONE, linear_solver="cholmod"))
    assert r.linear_solver == "cholmod" and r.n_factorizations >= 2
    assert calls == {"symbolic": 1, "numeric": r.n_factorizations}
    np.testing.assert_allclose(r.poses, ref.poses, atol=1e-9)
    h = sp.csc_matrix(np.diag([1.0, 2.0, 0.0, 1.0, 1.0, 1.0]))
    assert not sc.SparseCholesky("cholmod").factor(h)  # singular: False, not an exception
    big = sp.csc_matrix(-np.eye(sc.SUPERNODAL_MIN_SIZE))  # the supernodal LL' also catches indefinite
    assert not sc.SparseCholesky("cholmod").factor(big)


@pytest.mark.skipif(not sc.HAVE_QDLDL, reason="qdldl is not installed")
def test_qdldl_refactors_in_place_and_reports_singular_matrices(monkeypatch: pytest.MonkeyPatch) -> None:
    """QDLDL: one AMD + elimination tree per pattern, ``update`` for every later factorization, SuperLU's answer;
    a zero pivot is False on the first factorization and LinAlgError (a failed step) on a re-factorization."""
    calls = {"new": 0, "update": 0}
    real = sc._qdldl.Solver

    class Counting:
        def __init__(self, a: object, upper: bool = False) -> None:
            calls["new"] += 1
            assert upper
            self.s = real(a, upper=True)

        def update(self, a: object, upper: bool = False) -> None:
            calls["update"] += 1
            self.s.update(a, upper=upper)

        def solve(self, b: np.ndarray) -> np.ndarray:
            return self.s.solve(b)

    monkeypatch.setattr(sc._qdldl, "Solver", Counting)
    g, _ = random_graph(np.random.default_rng(12), n=40, loops=12)
    ref = optimize(g, OptimizerConfig(kernel=Kernel.NONE, linear_solver="superlu"))
    r = optimize(g, OptimizerConfig(kernel=Kernel.NONE, linear_solver="qdldl"))
    assert r.linear_solver == "qdldl" and r.n_factorizations >= 2
    assert calls == {"new": 1, "update": r.n_factorizations - 1}
    np.testing.assert_allclose(r.poses, ref.poses, atol=1e-9)
    lm = optimize(g, OptimizerConfig(method="lm", kernel=Kernel.NONE, linear_solver="qdldl"))
    np.testing.assert_allclose(lm.poses, ref.poses, atol=1e-6)
    # a full matrix (posegraph_init's systems) works as well: its upper triangle is taken
    a = np.array([[4.0, 1.0, 0.0], [1.0, 3.0, 1.0], [0.0, 1.0, 2.0]])
    chol = sc.SparseCholesky("qdldl")
    assert chol.factor(sp.csc_matrix(a))
    np.testing.assert_allclose(chol.solve(np.ones(3)), np.linalg.solve(a, np.ones(3)), rtol=1e-12)
    np.testing.assert_allclose(chol.solve(np.eye(3)), np.linalg.inv(a), rtol=1e-12)  # several right-hand sides
    assert chol.factor(sp.csc_matrix(a + 1.0 * (a != 0)))  # same pattern: re-factored in place
    np.testing.assert_allclose(chol.solve(np.ones(3)), np.linalg.solve(a + 1.0 * (a != 0), np.ones(3)), rtol=1e-12)
    singular = np.array([[1.0, 1.0, 0.0], [1.0, 2.0, 1.0], [0.0, 1.0, 1.0]])  # a's pattern; a zero pivot in any order
    assert not sc.SparseCholesky("qdldl").factor(sp.csc_matrix(singular))
    assert chol.factor(sp.csc_matrix(singular))  # QDLDL's update does not tell
    with pytest.raises(np.linalg.LinAlgError, match="zero pivot"):
        chol.solve(np.ones(3))
    with pytest.raises(ValueError, match="pip install qdldl"):
        monkeypatch.setattr(sc, "HAVE_QDLDL", False)
        sc.SparseCholesky("qdldl")


def test_robust_mask_chooses_the_edges_the_kernel_applies_to() -> None:
    """optimize(robust=...) overrides the |i - j| != 1 rule: a false sequential edge is rejected only when masked."""
    n = 6
    poses = np.array([[float(k), 0.0, 0.0] for k in range(n)])
    i = np.r_[np.arange(n - 1), 0, 4]
    j = np.r_[np.arange(1, n), 3, 5]
    z = np.vstack([np.tile([1.0, 0.0, 0.0], (n - 1, 1)), [3.0, 0.0, 0.0], [5.0, 0.0, 0.0]])  # 4 -> 5: false, 5 m
    info = np.tile(np.eye(3) * 100.0, (len(i), 1, 1))
    g = PoseGraph(poses, i, j, z, info)
    robust = np.zeros(len(i), bool)
    robust[[5, 6]] = True
    res = optimize(g, OptimizerConfig(kernel=Kernel.DCS), robust=robust)
    assert list(np.flatnonzero(~res.inliers)) == [6]
    np.testing.assert_allclose(res.poses[:5, 0], np.arange(5.0), atol=1e-6)
    assert optimize(g, OptimizerConfig(kernel=Kernel.DCS)).edges_rejected == 0  # default rule: 4 -> 5 is odometry
    with pytest.raises(ValueError, match=r"robust must have shape \(7,\), got \(3,\)"):
        optimize(g, OptimizerConfig(kernel=Kernel.DCS), robust=np.ones(3, bool))


def test_incremental_set_poses_replaces_the_estimate() -> None:
    """set_poses takes an estimate solved elsewhere; a wrong shape or a moved gauge is refused."""
    inc = IncrementalOptimizer(IncrementalConfig(OptimizerConfig(kernel=Kernel.NONE, max_iterations=3)))
    inc.step([0], [1], [[1.0, 0.0, 0.0]], [np.eye(3)])
    inc.set_poses([[0.0, 0.0, 0.0], [1.5, 0.0, 0.0]])
    np.testing.assert_allclose(inc.poses[1], [1.5, 0.0, 0.0])
    with pytest.raises(ValueError, match=r"poses must be finite with shape \(2, 3\)"):
        inc.set_poses(np.zeros((3, 3)))
    with pytest.raises(ValueError, match="vertex 0 is the gauge"):
        inc.set_poses([[0.1, 0.0, 0.0], [1.0, 0.0, 0.0]])
