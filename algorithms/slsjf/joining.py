"""The global map of the Sparse Local Submap Joining Filter: local maps fused into an exactly sparse
information form over local-map end poses and features.

The global state is ``X = (X_1, ..., X_K, F_1, ..., F_N)``: the end pose of each local map (which is
the start frame of the next one; the first local map's start frame is the global frame, fixed) and
every feature in the global frame. A local map ``k`` built from start frame ``X_s`` to end pose
``X_e`` is a measurement of its own state, the end pose and its features in the start frame::

    z_k = ( X_s^-1 (+) X_e ,  R(theta_s)^T (F_j - t_s) for its features j ) + v,   v ~ N(0, P_k)

(Huang, Wang, Dissanayake 2008 [1]_, eqs. 5-7), ``P_k`` the local map's covariance from the EKF that
built it. Each local map touches only its two poses and its features, so the information matrix
``sum_k J_k^T P_k^-1 J_k`` is exactly sparse (there is no marginalization of past robot poses).

Fusing (``join``) either linearizes the new local map once, at the estimate when it arrives, and adds
its information to the running sums (SLSJF [1]_ section III: an extended information filter, the old
local maps' linearization points are kept; only the sums are held, so a join adds O(size of the new
local map) to them), or re-linearizes every local map at the current estimate and iterates
Gauss-Newton to convergence (I-SLSJF [2]_: the estimate is the maximum-likelihood joining of all local
maps, at the cost of rebuilding the information matrix, which is O(size of the map); its sparsity
pattern changes only at a join, so it is worked out once per join and each iteration only sums values
into it).

State recovery (``recovery``):

- ``direct`` (the paper's): a sparse LU (SuperLU) of the information matrix, which is symmetric positive
  definite: the fill-reducing ordering is symmetric (minimum degree on ``A + A^T``) and the pivots stay on
  the diagonal, so the factor has the fill of the Cholesky factor [1]_ recovers the state with. It is
  redone at every join and kept until the next, for the covariance columns: its time and memory grow
  faster than the map (``benchmarks/slsjf_scaling.py``).
- ``pcg`` (D-SLAM's, a departure from [1]_): preconditioned CG from the previous estimate, covariance
  columns by PCG from the previous join's (:mod:`slamreplay.algorithms.slsjf.recovery`). No factor is
  held. A solve that does not converge within ``pcg_max_iterations`` is redone by a direct factorization,
  not kept, and counted in ``fallbacks``.

References
----------
.. [1] S. Huang, Z. Wang, G. Dissanayake, "Sparse local submap joining filter for building large-scale
   maps", IEEE Transactions on Robotics 24(5), 2008.
.. [2] S. Huang, Z. Wang, G. Dissanayake, U. Frese, "Iterated SLSJF: a sparse local submap joining
   algorithm with improved consistency", ACRA 2008.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as sla
from numpy.typing import NDArray

from slamreplay.algorithms.common import se2
from slamreplay.algorithms.dslam.recovery import pcg
from slamreplay.algorithms.slsjf.recovery import Matrix, TwoLevel

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]
Linearization = Literal["once", "iterated"]
StateRecovery = Literal["direct", "pcg"]
STATE_RECOVERIES: tuple[str, ...] = ("direct", "pcg")
PCG_TOLERANCE = 1e-7  # m, rad: the estimate's PCG stops when no entry of M^-1 r exceeds this (I-SLSJF's
# Gauss-Newton stops at steps below 1e-6, so the solve is ten times finer)
COVARIANCE_RTOL = 1e-4  # a covariance column's PCG: the same, relative to the entry's block-Jacobi variance
# (D-SLAM's covariance_rtol)
PCG_MAX_ITERATIONS = 400
WARM_COLUMNS = 256  # covariance columns kept from one join to the next as PCG's initial guesses, at most
# The smallest variance a local map's covariance is given before it is inverted (m^2, rad^2): a local map
# whose robot did not move has an exactly zero end-pose covariance, which no information form can hold.
MIN_VARIANCE = 1e-12


@dataclass(frozen=True, slots=True)
class LocalMap:
    """A finished local map: its estimate ``z`` (end pose, then features, in its start frame), information
    ``W = P^-1``, the global index of its start pose (-1: the global frame) and end pose, and the global
    index of each of its features (in the order of ``z``)."""

    start: int
    end: int
    features: I64
    z: F64
    W: F64


@dataclass
class _Linear:
    """A local map's linearization: its state indices, ``A = J^T W J`` and ``g = J^T W (r + J x0)``."""

    idx: I64
    A: F64
    g: F64


@dataclass
class _Pattern:
    """The sparsity pattern of ``sum_k A_k`` (CSC) and where each entry of each ``A_k``, in order, is summed."""

    indices: I64
    indptr: I64
    slot: I64  # (sum_k |A_k|,) position in the CSC data of each entry of A_1, A_2, ... (row-major)

    @classmethod
    def of(cls, parts: list[_Linear], dim: int) -> _Pattern:
        rows = np.concatenate([np.repeat(p.idx, len(p.idx)) for p in parts])
        cols = np.concatenate([np.tile(p.idx, len(p.idx)) for p in parts])
        keys, slot = np.unique(cols * dim + rows, return_inverse=True)  # sorted by column, then row: CSC order
        indptr = np.searchsorted(keys // dim, np.arange(dim + 1)).astype(np.int64)
        return cls(np.asarray(keys % dim, np.int64), indptr, np.asarray(slot, np.int64))

    def matrix(self, parts: list[_Linear], dim: int) -> sp.csc_matrix:
        vals = np.concatenate([p.A.reshape(-1) for p in parts])
        data = np.bincount(self.slot, weights=vals, minlength=len(self.indices))
        return sp.csc_matrix((data, self.indices, self.indptr), shape=(dim, dim))


def _h_and_jacobian(x: F64, pose_at: dict[int, int], feat_at: dict[int, int], m: LocalMap) -> tuple[F64, F64, I64]:
    """(h(X), dh/dX over the map's state indices, those indices) of local map ``m`` at ``x``."""
    has_start = m.start >= 0
    s = x[pose_at[m.start]:pose_at[m.start] + 3] if has_start else np.zeros(3)
    e = x[pose_at[m.end]:pose_at[m.end] + 3]
    c, sn = math.cos(s[2]), math.sin(s[2])
    rt = np.array([[c, sn], [-sn, c]])  # R(theta_s)^T
    drt = np.array([[-sn, c], [-c, -sn]])  # its derivative by theta_s
    nf = len(m.features)
    idx = []
    if has_start:
        idx += list(range(pose_at[m.start], pose_at[m.start] + 3))
    idx += list(range(pose_at[m.end], pose_at[m.end] + 3))
    for g in m.features.tolist():
        idx += [feat_at[g], feat_at[g] + 1]
    off = 3 if has_start else 0  # columns: [start (3)] end (3) features (2 each)
    J = np.zeros((3 + 2 * nf, len(idx)))
    h = np.zeros(3 + 2 * nf)
    d = e[:2] - s[:2]
    h[:2], h[2] = rt @ d, e[2] - s[2]
    J[:2, off:off + 2], J[2, off + 2] = rt, 1.0
    if has_start:
        J[:2, 0:2], J[:2, 2], J[2, 2] = -rt, drt @ d, -1.0
    if nf:
        f = np.array([x[feat_at[g]:feat_at[g] + 2] for g in m.features.tolist()])  # (nf, 2)
        df = f - s[:2]
        h[3:] = (df @ rt.T).reshape(-1)
        for j in range(nf):
            rows = slice(3 + 2 * j, 5 + 2 * j)
            J[rows, off + 3 + 2 * j:off + 5 + 2 * j] = rt
            if has_start:
                J[rows, 0:2], J[rows, 2] = -rt, drt @ df[j]
    return h, J, np.asarray(idx, np.int64)


@dataclass
class GlobalMap:
    """Local maps joined into one sparse information map (module docstring)."""

    linearization: Linearization = "iterated"
    max_iterations: int = 10
    tolerance: float = 1e-6  # Gauss-Newton stops when the largest state change is below this (m, rad)
    recovery: StateRecovery = "direct"
    pcg_max_iterations: int = PCG_MAX_ITERATIONS
    x: F64 = field(default_factory=lambda: np.zeros(0))
    pose_at: dict[int, int] = field(default_factory=dict)  # global pose index -> offset in x
    feat_at: dict[int, int] = field(default_factory=dict)  # global feature index -> offset in x
    maps: list[LocalMap] = field(default_factory=list)
    iterations: list[int] = field(default_factory=list)  # Gauss-Newton iterations of each join
    _info: sp.csc_matrix | None = None  # SLSJF: the running sum of every local map's A
    _vector: F64 = field(default_factory=lambda: np.zeros(0))  # SLSJF: the running sum of their g
    _pattern: _Pattern | None = None  # I-SLSJF: the pattern of the current local maps' A
    _factor: sla.SuperLU | None = None  # recovery="direct": the factor of the last solve
    _matrix: sp.csc_matrix | None = None  # the information matrix of the last solve
    _operator: Matrix | None = None  # recovery="pcg": the information matrix of the last solve, as PCG multiplies by it
    _precondition: TwoLevel | None = None  # recovery="pcg": the preconditioner of the last solve
    _warm: dict[int, F64] = field(default_factory=dict)  # recovery="pcg": covariance columns of the last join
    _fresh: dict[int, F64] = field(default_factory=dict)  # ... and of this one
    pcg_iterations: list[int] = field(default_factory=list)  # recovery="pcg": CG iterations of each state solve
    column_iterations: list[int] = field(default_factory=list)  # ... of each covariance solve
    fallbacks: int = 0  # recovery="pcg": solves that did not converge and were redone directly

    def __post_init__(self) -> None:
        if self.linearization not in ("once", "iterated"):
            raise ValueError(f"linearization must be 'once' or 'iterated', got {self.linearization!r}")
        if self.recovery not in STATE_RECOVERIES:
            raise ValueError(f"recovery must be one of {', '.join(STATE_RECOVERIES)}, got {self.recovery!r}")
        if self.max_iterations < 1 or not self.tolerance > 0 or self.pcg_max_iterations < 1:
            raise ValueError("max_iterations and pcg_max_iterations must be >= 1 and tolerance > 0")

    @property
    def n_poses(self) -> int:
        return len(self.pose_at)

    @property
    def n_features(self) -> int:
        return len(self.feat_at)

    @property
    def dim(self) -> int:
        return len(self.x)

    def pose(self, k: int) -> F64:
        """Global pose ``k`` (-1: the origin)."""
        return np.zeros(3) if k < 0 else self.x[self.pose_at[k]:self.pose_at[k] + 3].copy()

    def feature(self, g: int) -> F64:
        return self.x[self.feat_at[g]:self.feat_at[g] + 2].copy()

    def has_feature(self, g: int) -> bool:
        return g in self.feat_at

    def join(self, start: int, end_pose_local: F64, features: I64, z: F64, P: F64) -> int:
        """Fuse a local map built from global pose ``start`` (-1: the origin); returns its end pose's index.

        ``z`` (3 + 2m,) is the local map's end pose and its m features in its start frame, ``P`` their
        covariance, ``features`` (m,) their global indices (new ones are added, initialised from ``z``).
        """
        features = np.asarray(features, np.int64).reshape(-1)
        z = np.asarray(z, np.float64).reshape(-1)
        P = np.asarray(P, np.float64)
        if z.shape != (3 + 2 * len(features),) or P.shape != (len(z), len(z)):
            raise ValueError(f"z must be (3 + 2m,) and P (3 + 2m, 3 + 2m) for m = {len(features)} features, got "
                             f"{z.shape} and {P.shape}")
        if start >= 0 and start not in self.pose_at:
            raise ValueError(f"start pose {start} is not in the map")
        s = self.pose(start)
        end = self.n_poses
        self.pose_at[end] = self.dim
        self.x = np.concatenate([self.x, se2.compose(s, end_pose_local)])
        for j, g in enumerate(features.tolist()):
            if g not in self.feat_at:
                self.feat_at[g] = self.dim
                self.x = np.concatenate([self.x, se2.transform_points(s, z[3 + 2 * j:5 + 2 * j][None])[0]])
        p = 0.5 * (P + P.T) + MIN_VARIANCE * np.eye(len(P))
        m = LocalMap(start, end, features, z, np.linalg.inv(p))
        self.maps.append(m)
        self._warm = {i: np.concatenate([c, np.zeros(self.dim - len(c))]) for i, c in self._fresh.items()}
        self._fresh = {}
        if self.linearization == "once":
            self._add(self._linearize(m))
            self.x = self._solve(self._info, self._vector)
            self.iterations.append(1)
        else:
            self._pattern = None  # a new local map: new pattern
            self.iterations.append(self._gauss_newton())
        return end

    def _linearize(self, m: LocalMap) -> _Linear:
        h, J, idx = _h_and_jacobian(self.x, self.pose_at, self.feat_at, m)
        r = m.z - h
        r[2] = se2.wrap_angle(r[2])
        JW = J.T @ m.W
        return _Linear(idx, JW @ J, JW @ (r + J @ self.x[idx]))

    def _add(self, part: _Linear) -> None:
        """SLSJF: add one local map's information to the running sums, grown to the current state."""
        n = len(part.idx)
        new = sp.csc_matrix((part.A.reshape(-1), (np.repeat(part.idx, n), np.tile(part.idx, n))),
                            shape=(self.dim, self.dim))
        if self._info is None:
            self._info = new
        else:
            self._info.resize((self.dim, self.dim))
            self._info = (self._info + new).tocsc()
        self._vector = np.concatenate([self._vector, np.zeros(self.dim - len(self._vector))])
        np.add.at(self._vector, part.idx, part.g)

    def _assemble(self, parts: list[_Linear]) -> tuple[sp.csc_matrix, F64]:
        """I-SLSJF: the information matrix and vector of the local maps linearized as ``parts`` (one per map)."""
        if self._pattern is None:
            self._pattern = _Pattern.of(parts, self.dim)
        g = np.zeros(self.dim)
        for p in parts:
            np.add.at(g, p.idx, p.g)
        return self._pattern.matrix(parts, self.dim), g

    @staticmethod
    def _factorize(a: sp.csc_matrix) -> sla.SuperLU:
        # Symmetric positive definite: a symmetric ordering and diagonal pivots, the Cholesky factor's fill.
        return sla.splu(a.tocsc(), permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0, options={"SymmetricMode": True})

    def _offsets(self) -> tuple[I64, I64]:
        return (np.fromiter(self.pose_at.values(), np.int64, len(self.pose_at)),
                np.fromiter(self.feat_at.values(), np.int64, len(self.feat_at)))

    def _solve(self, a: sp.csc_matrix, g: F64) -> F64:
        """The estimate ``a^-1 g``: by a factor (kept for the covariance columns) or by PCG from ``self.x``."""
        self._matrix = a
        if self.recovery == "direct":
            self._factor = self._factorize(a)
            return np.asarray(self._factor.solve(g), np.float64)
        self._factor = None
        self._operator = Matrix(a)
        self._precondition = TwoLevel(self._operator.a, self.x, *self._offsets())
        result = pcg(self._operator, g, self.x, None, PCG_TOLERANCE, self.pcg_max_iterations, self._precondition)
        self.pcg_iterations.append(result.iterations)
        if result.converged:
            return np.asarray(result.x, np.float64)
        self.fallbacks += 1
        return np.asarray(self._factorize(a).solve(g), np.float64)

    def _gauss_newton(self) -> int:
        """I-SLSJF: every local map re-linearized at the current estimate until the update is below tolerance."""
        for it in range(1, self.max_iterations + 1):
            parts = [self._linearize(m) for m in self.maps]
            a, g = self._assemble(parts)
            new = self._solve(a, g)
            step = float(np.max(np.abs(new - self.x), initial=0.0))
            self.x = new
            if step < self.tolerance:
                return it
        return self.max_iterations

    def information(self) -> sp.csc_matrix:
        """The information matrix at the current estimate (I-SLSJF) or as accumulated (SLSJF)."""
        if not self.maps:
            return sp.csc_matrix((0, 0))
        if self.linearization == "once" and self._info is not None:
            return self._info.copy()
        return self._assemble([self._linearize(m) for m in self.maps])[0]

    def covariance_block(self, offsets: list[int], size: int, exact: bool = False) -> F64:
        """The joint covariance of the blocks of ``size`` starting at each of ``offsets`` (columns of I^-1)."""
        if not offsets:
            return np.zeros((0, 0))
        idx = (np.asarray(offsets)[:, None] + np.arange(size)).reshape(-1)
        out = self.covariance_columns(idx.tolist(), exact)[idx]
        return np.asarray(0.5 * (out + out.T), np.float64)

    def covariance_columns(self, idx: list[int], exact: bool = False) -> F64:
        """The columns (dim, len(idx)) of the covariance I^-1 at state indices ``idx``.

        ``recovery="direct"``: one solve with the factor of the last join, O(fill of the factor) per column.
        ``recovery="pcg"``: PCG from the same columns at the last join where they were asked for (module
        docstring); ``exact`` (for scoring every feature, as D-SLAM's exact marginals) factorizes instead,
        without keeping the factor.
        """
        if self._matrix is None:
            raise ValueError("no local map has been joined yet")
        e = np.zeros((self.dim, len(idx)))
        e[idx, np.arange(len(idx))] = 1.0
        if self._factor is not None:
            return np.asarray(self._factor.solve(e), np.float64)
        if exact:
            return np.asarray(self._factorize(self._matrix).solve(e), np.float64)
        assert self._operator is not None and self._precondition is not None
        x0 = np.stack([self._fresh.get(i, self._warm.get(i, np.zeros(self.dim))) for i in idx], -1)
        scale = self._precondition.variances()[idx]
        result = pcg(self._operator, e, x0, None, COVARIANCE_RTOL * np.maximum(scale, 1e-300),
                     self.pcg_max_iterations, self._precondition)
        self.column_iterations.append(result.iterations)
        cols = np.asarray(result.x, np.float64)
        if not result.converged:
            self.fallbacks += 1
            cols = np.asarray(self._factorize(self._matrix).solve(e), np.float64)
        for k, i in enumerate(idx):
            if i in self._fresh or len(self._fresh) < WARM_COLUMNS:
                self._fresh[i] = cols[:, k]
        return cols

    def pose_covariance(self, k: int) -> F64:
        """The marginal covariance (3, 3) of global pose ``k`` (zeros for -1, the fixed origin)."""
        return np.zeros((3, 3)) if k < 0 else self.covariance_block([self.pose_at[k]], 3)

    def feature_covariances(self, features: list[int], exact: bool = False) -> F64:
        """Marginal covariances (k, 2, 2) of global features (one solve with all their columns; ``exact``: as
        :meth:`covariance_columns`)."""
        if not features:
            return np.zeros((0, 2, 2))
        joint = self.covariance_block([self.feat_at[g] for g in features], 2, exact)
        k = len(features)
        return np.asarray(joint.reshape(k, 2, k, 2)[np.arange(k), :, np.arange(k), :], np.float64)

    def joint_feature_covariance(self, features: list[int]) -> F64:
        """The joint covariance (2k, 2k) of global features."""
        return self.covariance_block([self.feat_at[g] for g in features], 2)


def sparsity_image(a: sp.spmatrix, max_pixels: int = 512) -> NDArray[np.uint8]:
    """The nonzero pattern of a sparse matrix as a uint8 image (255 = nonzero); a larger matrix is reduced to
    ``max_pixels`` a side, a pixel lit when any entry it covers is nonzero."""
    n = a.shape[0]
    scale = max(1, -(-n // max_pixels))
    size = max(1, -(-n // scale))
    img = np.zeros((size, size), dtype=np.uint8)
    coo = a.tocoo()
    keep = coo.data != 0
    img[coo.row[keep] // scale, coo.col[keep] // scale] = 255
    return img
