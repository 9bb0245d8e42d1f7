"""Batch least squares over planar poses and point landmarks: the full-SLAM optimum of a data set.

The pose graph of :mod:`slamreplay.algorithms.common.posegraph` extended with landmark vertices (x, y) and
range-bearing edges. Odometry edges ``(i, j, z, Ω)`` have the residual
``e = (⊖x_i ⊕ x_j) - z`` (angle wrapped) as in g2o's SE(2) edge [1]_; an observation of landmark
``l`` from pose ``i`` has ``e = h(x_i, l) - z`` with ``h = (|d|, atan2(d_y, d_x))``,
``d = R_iᵀ (l - t_i)`` (bearing wrapped). The cost is ``χ² = Σ eᵀ Ω e``; pose 0 is held fixed
(the gauge). Minimized by Levenberg-Marquardt [2]_ on the sparse normal equations
``(H + λ diag H) δ = -g``, ``H = Jᵀ Ω J``, solved by SuperLU with a fill-reducing (COLAMD) order.

Started from dead reckoning, a long trajectory's batch problem may fall into a poor minimum
(the Victoria Park file's README reports exactly that for GTSAM's LM). :func:`solve_incremental`
therefore grows the problem through time in chunks of ``chunk_poses`` poses, each new pose
started from its odometry and each new landmark from its first observation, and optimizes after
each chunk, in the spirit of iSAM's periodic batch steps [3]_; a final full optimization follows.

References
----------
.. [1] R. Kümmerle et al., "g2o: A general framework for graph optimization", ICRA 2011.
.. [2] K. Madsen, H. B. Nielsen, O. Tingleff, "Methods for non-linear least squares problems", 2004, sec. 3.2.
.. [3] M. Kaess, A. Ranganathan, F. Dellaert, "iSAM: Incremental smoothing and mapping", IEEE T-RO 24(6), 2008.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as sla
from numpy.typing import NDArray

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]


def _wrap(a: F64) -> F64:
    return (a + np.pi) % (2 * np.pi) - np.pi


@dataclass(frozen=True, slots=True)
class LandmarkGraph:
    """Poses 0..n_poses-1, landmarks 0..n_landmarks-1, odometry and range-bearing edges.

    Attributes
    ----------
    odo_i, odo_j : (m,) pose indices; odo_z : (m, 3) ``[dx, dy, dθ]`` of j in i's frame;
    odo_info : (m, 3, 3) information matrices.
    obs_pose, obs_landmark : (k,) indices; obs_z : (k, 2) ``[range_m, bearing_rad]``;
    obs_info : (k, 2, 2) information matrices.
    """

    n_poses: int
    n_landmarks: int
    odo_i: I64
    odo_j: I64
    odo_z: F64
    odo_info: F64
    obs_pose: I64
    obs_landmark: I64
    obs_z: F64
    obs_info: F64

    def __post_init__(self) -> None:
        m, k = len(self.odo_i), len(self.obs_pose)
        shapes = {"odo_j": (self.odo_j, (m,)), "odo_z": (self.odo_z, (m, 3)), "odo_info": (self.odo_info, (m, 3, 3)),
                  "obs_landmark": (self.obs_landmark, (k,)), "obs_z": (self.obs_z, (k, 2)),
                  "obs_info": (self.obs_info, (k, 2, 2))}
        for name, (arr, shape) in shapes.items():
            if np.shape(arr) != shape:
                raise ValueError(f"{name} must have shape {shape}, got {np.shape(arr)}")
        for name, arr, hi in (("odo_i", self.odo_i, self.n_poses), ("odo_j", self.odo_j, self.n_poses),
                              ("obs_pose", self.obs_pose, self.n_poses),
                              ("obs_landmark", self.obs_landmark, self.n_landmarks)):
            if len(arr) and (np.min(arr) < 0 or np.max(arr) >= hi):
                raise ValueError(f"{name} must index 0..{hi - 1}")
        if not (np.all(np.isfinite(self.odo_z)) and np.all(np.isfinite(self.obs_z))):
            raise ValueError("odo_z and obs_z must be finite")


@dataclass(frozen=True, slots=True)
class LsqConfig:
    """Levenberg-Marquardt and incremental-growth settings."""

    max_iterations: int = 50
    relative_tolerance: float = 1e-9  # stop when χ² falls by less than this fraction
    lambda_init: float = 1e-5
    chunk_poses: int = 50  # solve_incremental: poses added between optimizations
    chunk_iterations: int = 20  # solve_incremental: at most this many LM iterations after each chunk
    chunk_tolerance: float = 1e-4  # solve_incremental: relative_tolerance after each chunk

    def __post_init__(self) -> None:
        if self.max_iterations < 1 or self.chunk_poses < 1 or self.chunk_iterations < 1:
            raise ValueError("max_iterations, chunk_poses and chunk_iterations must be >= 1")
        if not self.lambda_init > 0 or not self.relative_tolerance >= 0:
            raise ValueError("lambda_init must be > 0 and relative_tolerance >= 0")


@dataclass(frozen=True, slots=True)
class LsqResult:
    """The optimum found: poses (n, 3), landmarks (L, 2), χ², iterations and whether it converged."""

    poses: F64
    landmarks: F64
    chi2: float
    iterations: int
    converged: bool


def _whiten(info: F64) -> F64:
    """Lᵀ per edge with Ω = L Lᵀ, so that ‖Lᵀ e‖² = eᵀ Ω e."""
    return np.transpose(np.linalg.cholesky(info), (0, 2, 1))


def residuals(graph: LandmarkGraph, poses: F64, landmarks: F64) -> tuple[F64, F64]:
    """Unwhitened residuals: odometry (m, 3) and observations (k, 2)."""
    xi, xj = poses[graph.odo_i], poses[graph.odo_j]
    c, s = np.cos(xi[:, 2]), np.sin(xi[:, 2])
    dx, dy = xj[:, 0] - xi[:, 0], xj[:, 1] - xi[:, 1]
    e_odo = np.column_stack([c * dx + s * dy - graph.odo_z[:, 0], -s * dx + c * dy - graph.odo_z[:, 1],
                             _wrap(xj[:, 2] - xi[:, 2] - graph.odo_z[:, 2])])
    x, lm = poses[graph.obs_pose], landmarks[graph.obs_landmark]
    c, s = np.cos(x[:, 2]), np.sin(x[:, 2])
    px, py = lm[:, 0] - x[:, 0], lm[:, 1] - x[:, 1]
    d0, d1 = c * px + s * py, -s * px + c * py
    e_obs = np.column_stack([np.hypot(d0, d1) - graph.obs_z[:, 0], _wrap(np.arctan2(d1, d0) - graph.obs_z[:, 1])])
    return e_odo, e_obs


def chi2(graph: LandmarkGraph, poses: F64, landmarks: F64) -> float:
    """χ² = Σ eᵀ Ω e over all edges."""
    e_odo, e_obs = residuals(graph, poses, landmarks)
    return float(np.einsum("ni,nij,nj->", e_odo, graph.odo_info, e_odo)
                 + np.einsum("ni,nij,nj->", e_obs, graph.obs_info, e_obs))


def _system(graph: LandmarkGraph, poses: F64, landmarks: F64, wo: F64, wl: F64) -> tuple[sp.csr_matrix, F64]:
    """Whitened Jacobian (rows, 3 n + 2 L) and whitened residual vector."""
    n = graph.n_poses
    m, k = len(graph.odo_i), len(graph.obs_pose)
    e_odo, e_obs = residuals(graph, poses, landmarks)
    xi, xj = poses[graph.odo_i], poses[graph.odo_j]
    c, s = np.cos(xi[:, 2]), np.sin(xi[:, 2])
    dx, dy = xj[:, 0] - xi[:, 0], xj[:, 1] - xi[:, 1]
    Ji = np.zeros((m, 3, 3))
    Ji[:, 0, 0], Ji[:, 0, 1], Ji[:, 0, 2] = -c, -s, -s * dx + c * dy
    Ji[:, 1, 0], Ji[:, 1, 1], Ji[:, 1, 2] = s, -c, -c * dx - s * dy
    Ji[:, 2, 2] = -1.0
    Jj = np.zeros((m, 3, 3))
    Jj[:, 0, 0], Jj[:, 0, 1] = c, s
    Jj[:, 1, 0], Jj[:, 1, 1] = -s, c
    Jj[:, 2, 2] = 1.0
    Ji, Jj, r_odo = wo @ Ji, wo @ Jj, np.einsum("nij,nj->ni", wo, e_odo)

    x, lm = poses[graph.obs_pose], landmarks[graph.obs_landmark]
    c, s = np.cos(x[:, 2]), np.sin(x[:, 2])
    px, py = lm[:, 0] - x[:, 0], lm[:, 1] - x[:, 1]
    d0, d1 = c * px + s * py, -s * px + c * py
    r2 = np.maximum(d0 * d0 + d1 * d1, 1e-12)
    r = np.sqrt(r2)
    H = np.stack([np.stack([d0 / r, d1 / r], -1), np.stack([-d1 / r2, d0 / r2], -1)], 1)  # ∂h/∂d (k, 2, 2)
    Dt = np.zeros((k, 2, 2))  # ∂d/∂t
    Dt[:, 0, 0], Dt[:, 0, 1], Dt[:, 1, 0], Dt[:, 1, 1] = -c, -s, s, -c
    Dth = np.stack([-s * px + c * py, -c * px - s * py], -1)[:, :, None]  # ∂d/∂θ
    Jx = np.concatenate([H @ Dt, H @ Dth], axis=2)  # (k, 2, 3)
    Jl = H @ -Dt  # ∂d/∂l = R_iᵀ = -∂d/∂t
    Jx, Jl, r_obs = wl @ Jx, wl @ Jl, np.einsum("nij,nj->ni", wl, e_obs)

    rows_o = (np.arange(m)[:, None] * 3 + np.arange(3))[:, :, None]
    rows_l = (3 * m + np.arange(k)[:, None] * 2 + np.arange(2))[:, :, None]

    def col(base: I64, width: int) -> I64:
        return (base[:, None] + np.arange(width))[:, None, :]

    blocks = [
        (rows_o, col(3 * graph.odo_i, 3), Ji), (rows_o, col(3 * graph.odo_j, 3), Jj),
        (rows_l, col(3 * graph.obs_pose, 3), Jx), (rows_l, col(3 * n + 2 * graph.obs_landmark, 2), Jl),
    ]
    rr = np.concatenate([np.broadcast_to(ro, b.shape).ravel() for ro, _, b in blocks])
    cc = np.concatenate([np.broadcast_to(co, b.shape).ravel() for _, co, b in blocks])
    vv = np.concatenate([b.ravel() for _, _, b in blocks])
    J = sp.csr_matrix((vv, (rr, cc)), shape=(3 * m + 2 * k, 3 * n + 2 * graph.n_landmarks))
    return J, np.concatenate([r_odo.ravel(), r_obs.ravel()])


def optimize(graph: LandmarkGraph, poses: F64, landmarks: F64, cfg: LsqConfig = LsqConfig(),
             max_iterations: int | None = None) -> LsqResult:
    """Levenberg-Marquardt from ``poses`` (n, 3) and ``landmarks`` (L, 2); pose 0 fixed.

    Every landmark must be observed at least once and every pose but 0 linked by an edge
    (otherwise the normal equations are singular: ValueError).
    """
    poses = np.array(poses, dtype=np.float64, copy=True)
    landmarks = np.array(landmarks, dtype=np.float64, copy=True).reshape(-1, 2)
    if poses.shape != (graph.n_poses, 3) or landmarks.shape != (graph.n_landmarks, 2):
        raise ValueError(f"poses must be ({graph.n_poses}, 3) and landmarks ({graph.n_landmarks}, 2), "
                         f"got {poses.shape} and {landmarks.shape}")
    if len(np.unique(graph.obs_landmark)) != graph.n_landmarks:
        raise ValueError("every landmark must be observed at least once")
    wo, wl = _whiten(graph.odo_info), _whiten(graph.obs_info)
    free = np.arange(3, 3 * graph.n_poses + 2 * graph.n_landmarks)
    current = chi2(graph, poses, landmarks)
    lam = cfg.lambda_init
    iters = max_iterations or cfg.max_iterations
    converged = False
    it = 0
    while it < iters:
        it += 1
        J, r = _system(graph, poses, landmarks, wo, wl)
        J = J[:, free].tocsc()
        H = (J.T @ J).tocsc()
        g = J.T @ r
        diag = H.diagonal()
        improved = False
        while lam < 1e12:
            A = (H + sp.diags(lam * np.maximum(diag, 1e-9))).tocsc()
            try:
                step = sla.splu(A, permc_spec="COLAMD").solve(-g)
            except RuntimeError:
                lam *= 10.0
                continue
            delta = np.zeros(3 * graph.n_poses + 2 * graph.n_landmarks)
            delta[free] = step
            new_poses = poses + delta[:3 * graph.n_poses].reshape(-1, 3)
            new_poses[:, 2] = _wrap(new_poses[:, 2])
            new_lms = landmarks + delta[3 * graph.n_poses:].reshape(-1, 2)
            new = chi2(graph, new_poses, new_lms)
            if math.isfinite(new) and new < current:
                decrease = (current - new) / max(current, 1e-300)
                poses, landmarks, current = new_poses, new_lms, new
                lam = max(lam / 10.0, 1e-12)
                improved = True
                converged = decrease < cfg.relative_tolerance
                break
            lam *= 10.0
        if not improved:  # no step lowers χ²: a minimum to numerical precision
            converged = True
        if converged:
            break
    return LsqResult(poses, landmarks, current, it, converged)


def _compose(a: F64, b: F64) -> F64:
    c, s = math.cos(a[2]), math.sin(a[2])
    return np.array([a[0] + c * b[0] - s * b[1], a[1] + s * b[0] + c * b[1], math.remainder(a[2] + b[2], math.tau)])


def solve_incremental(graph: LandmarkGraph, cfg: LsqConfig = LsqConfig()) -> LsqResult:
    """Grow the problem through the poses in order (odometry edges from a pose to a later one), optimizing
    after every ``chunk_poses`` poses, then optimize the whole to convergence (module docstring)."""
    if len(np.unique(graph.obs_landmark)) != graph.n_landmarks:
        raise ValueError("every landmark must be observed at least once")
    order = np.argsort(graph.odo_j, kind="stable")
    poses = np.zeros((graph.n_poses, 3))
    landmarks = np.zeros((graph.n_landmarks, 2))
    seen_lm = np.zeros(graph.n_landmarks, dtype=bool)
    placed = np.zeros(graph.n_poses, dtype=bool)
    placed[0] = True
    obs_order = np.argsort(graph.obs_pose, kind="stable")
    next_obs = 0
    total_iters = 0
    for end in [*range(cfg.chunk_poses, graph.n_poses, cfg.chunk_poses), graph.n_poses]:
        for e in order:
            j = int(graph.odo_j[e])
            if j < end and not placed[j] and placed[graph.odo_i[e]]:
                poses[j] = _compose(poses[graph.odo_i[e]], graph.odo_z[e])
                placed[j] = True
        while next_obs < len(obs_order) and graph.obs_pose[obs_order[next_obs]] < end:
            o = obs_order[next_obs]
            lm = int(graph.obs_landmark[o])
            if not seen_lm[lm]:
                x = poses[graph.obs_pose[o]]
                rng, brg = graph.obs_z[o]
                landmarks[lm] = [x[0] + rng * math.cos(x[2] + brg), x[1] + rng * math.sin(x[2] + brg)]
                seen_lm[lm] = True
            next_obs += 1
        if not placed[:end].all():
            raise ValueError(f"pose {int(np.argmin(placed[:end]))} is not linked to pose 0 by odometry")
        sub = _subgraph(graph, end, seen_lm)
        last = end == graph.n_poses
        res = optimize(sub.graph, poses[:end], landmarks[sub.landmarks],
                       cfg if last else replace(cfg, relative_tolerance=cfg.chunk_tolerance),
                       max_iterations=cfg.max_iterations if last else cfg.chunk_iterations)
        poses[:end] = res.poses
        landmarks[sub.landmarks] = res.landmarks
        total_iters += res.iterations
    return LsqResult(poses, landmarks, res.chi2, total_iters, res.converged)


@dataclass(frozen=True, slots=True)
class _Sub:
    graph: LandmarkGraph
    landmarks: I64  # the full graph's index of each sub-graph landmark


def _subgraph(graph: LandmarkGraph, end: int, seen: NDArray[np.bool_]) -> _Sub:
    """Poses 0..end-1, the landmarks seen so far, and the edges among them."""
    lms = np.flatnonzero(seen)
    remap = np.full(graph.n_landmarks, -1, dtype=np.int64)
    remap[lms] = np.arange(len(lms))
    ko = (graph.odo_i < end) & (graph.odo_j < end)
    kl = graph.obs_pose < end
    sub = LandmarkGraph(end, len(lms), graph.odo_i[ko], graph.odo_j[ko], graph.odo_z[ko], graph.odo_info[ko],
                        graph.obs_pose[kl], remap[graph.obs_landmark[kl]], graph.obs_z[kl], graph.obs_info[kl])
    return _Sub(sub, lms)


def noise_scales(graph: LandmarkGraph, poses: F64, landmarks: F64, rng: np.random.Generator,
                 samples: int = 64) -> F64:
    """How far each residual kind's noise is from its model, at an optimum: (5,) factors for odometry x, y, θ,
    range and bearing.

    For whitened residuals ``w`` of one kind, ``E[Σ w²] = c² (n - p)`` where ``c`` is the ratio of the true
    to the modelled sigma and ``p = tr(H⁻¹ J_kᵀ J_k)`` the unknowns that kind absorbs (its leverage; the
    ``p`` of all kinds add up to the number of unknowns). ``p`` is estimated with Hutchinson's
    estimator [4]_ over ``samples`` Rademacher vectors, one solve each with one factorization.
    Returns ``c = sqrt(Σ w² / (n - p))`` per kind, NaN where ``n - p < 0.05 n`` (nothing left to
    measure). Exact when the modelled sigmas are proportional to
    the true ones across kinds; otherwise an approximation.

    .. [4] M. F. Hutchinson, "A stochastic estimator of the trace of the influence matrix for Laplacian
       smoothing splines", Comm. Statistics - Simulation and Computation 19(2), 1990.
    """
    if samples < 1:
        raise ValueError(f"samples must be >= 1, got {samples}")
    J, r = _system(graph, poses, landmarks, _whiten(graph.odo_info), _whiten(graph.obs_info))
    free = np.arange(3, J.shape[1])
    J = J[:, free].tocsr()
    lu = sla.splu((J.T @ J).tocsc(), permc_spec="COLAMD")
    m3 = 3 * len(graph.odo_i)
    kinds = np.concatenate([np.arange(m3) % 3, 3 + np.arange(J.shape[0] - m3) % 2])
    rows = [np.flatnonzero(kinds == k) for k in range(5)]
    parts = [J[idx] for idx in rows]
    lev = np.zeros(5)
    for _ in range(samples):
        z = rng.choice([-1.0, 1.0], size=J.shape[1])
        hz = lu.solve(z)
        for k, Jk in enumerate(parts):
            lev[k] += float(hz @ (Jk.T @ (Jk @ z)))
    lev /= samples
    out = np.zeros(5)
    for k, idx in enumerate(rows):
        dof = len(idx) - lev[k]
        # a kind whose residuals the optimum absorbs almost whole says nothing about its noise
        out[k] = math.sqrt(float(r[idx] @ r[idx]) / dof) if dof > 0.05 * len(idx) else math.nan
    return out


def landmark_covariance(graph: LandmarkGraph, poses: F64, landmarks: F64, scales: F64 | None = None) -> F64:
    """The joint covariance (2 L, 2 L) of the landmarks at an optimum, the first pose fixed: the landmark block of
    ``(J^T J)^-1`` for the whitened Jacobian ``J`` (Gauss-Newton's, first order).

    ``scales`` (5,): each residual kind's noise relative to its model (odometry x, y, θ, range, bearing; as
    :func:`noise_scales` measures them): a kind's whitened rows are divided by its factor. Landmarks in
    ``graph`` order, x then y of each.
    """
    J, _ = _system(graph, poses, landmarks, _whiten(graph.odo_info), _whiten(graph.obs_info))
    if scales is not None:
        scales = np.asarray(scales, np.float64)
        if scales.shape != (5,) or not np.all(np.isfinite(scales)) or not np.all(scales > 0):
            raise ValueError(f"scales must be 5 finite factors > 0, got {scales}")
        m3 = 3 * len(graph.odo_i)
        kinds = np.concatenate([np.arange(m3) % 3, 3 + np.arange(J.shape[0] - m3) % 2])
        J = sp.diags(1.0 / scales[kinds]) @ J
    return _covariance_block(J, 3 * graph.n_poses + np.arange(2 * graph.n_landmarks))


def pose_landmark_covariance(graph: LandmarkGraph, poses: F64, landmarks: F64, pose: int) -> F64:
    """The joint covariance (3 + 2 L, 3 + 2 L) of pose ``pose`` (not 0, which is fixed) and the landmarks at an
    optimum, in that order: an EKF-SLAM state's layout, as a local map's end pose and features are (first order,
    as :func:`landmark_covariance`)."""
    if not 0 < pose < graph.n_poses:
        raise ValueError(f"pose must be 1..{graph.n_poses - 1} (pose 0 is fixed), got {pose}")
    J, _ = _system(graph, poses, landmarks, _whiten(graph.odo_info), _whiten(graph.obs_info))
    return _covariance_block(J, np.r_[3 * pose + np.arange(3), 3 * graph.n_poses + np.arange(2 * graph.n_landmarks)])


def _covariance_block(J: sp.csr_matrix, cols: I64) -> F64:
    """The block of ``(J^T J)^-1`` at the state columns ``cols`` of the whitened Jacobian, pose 0 fixed."""
    free = np.arange(3, J.shape[1])
    J = J[:, free].tocsc()
    lu = sla.splu((J.T @ J).tocsc(), permc_spec="COLAMD")
    at = np.asarray(cols) - 3
    e = np.zeros((len(free), len(at)))
    e[at, np.arange(len(at))] = 1.0
    cov = np.asarray(lu.solve(e), np.float64)[at]
    return np.asarray(0.5 * (cov + cov.T), np.float64)
