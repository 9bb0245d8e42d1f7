"""A conservative joint covariance of the features near the robot (sections 3.2-3.3 of [1]_).

Localization needs the joint covariance of the observed mapped features (eq. 12), the anchor
rule and the map gate a block of it, data association the marginals of the candidates. All are
blocks of ``I^-1``. Recomputing them per scan by solving ``I c = e_j`` (2 columns per feature)
costs O(N) per column and iteration, so here the block of the vicinity set V (the features
observed recently and still near the robot) is carried from scan to scan in covariance form,
at O(|V|^2) per scan whatever N:

- eq. (10) adds ``dI = J^T R^-1 J`` on the scan's features. For features all in V, the
  marginal of V under ``(I + dI)^-1`` follows from the marginal of V alone (Woodbury):
  ``P_VV' = P_VV - P_VT J^T (R + J P_TT J^T)^-1 J P_TV``, the Kalman form of the same update.
  Exact.
- A feature joining V through a recast scan (a new feature, eq. 9, or a mapped feature not in
  V) has no prior in this computation: the scan's rows ``z_n = [alpha_i12, d_1i]`` of such
  features are conditioned on the rows ``z_o`` of the features in V (R_map is full), which
  update V alone; each joining feature is then the linear function of the anchors and its
  own rows that eq. (9) linearises, ``x_n = A x_o + J_nn^-1 (conditional noise)`` with
  ``A = -J_nn^-1 (J_no - R_no R_oo^-1 J_oo)``. For a new feature this is exactly what eq. (10)
  gives I; a mapped feature's earlier information is ignored, so its block is an upper bound.
- Phase I updates and initialises features directly (the robot is exactly at the origin), and
  the bootstrap (:func:`slamreplay.algorithms.dslam.mapping.bootstrap_increment`) adds features with their
  joint covariance; both are exact.
- A feature leaving V (farther than the vicinity radius) is marginalised out: its 2x2 marginal
  is kept, for gating and for the anchor rule when it is seen again.

Why the result is never overconfident: every matrix here bounds from above the error covariance
of some estimator of the same features built from the same data (the EIF estimate with some
information ignored, or updated with a gain computed from a bound); the EIF estimate x = I^-1 i
is the minimum-variance one, so its covariance is below every such bound. Marginalisation and
the Kalman form preserve the ordering, and ``I^-1`` only shrinks as eq. (10) adds information
(no prediction step), so a marginal kept from an earlier scan stays an upper bound.

:meth:`CovarianceCache.refresh` recomputes the block of a set of features exactly, by block
PCG on ``I c = e_j`` (O(N) per column and iteration); the filter calls it only when a scan
sees fewer than two features of V, or every ``covariance_refresh_scans`` scans when that is
positive.

References
----------
.. [1] Z. Wang, S. Huang, G. Dissanayake, "Implementation issues and experimental evaluation
   of D-SLAM", FSR 2005, sections 3.2-3.3, eqs. (9)-(10).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.linalg as sla
from numpy.typing import NDArray

from slamreplay.algorithms.dslam.information import InformationMatrix, _grown, dofs
from slamreplay.algorithms.dslam.recovery import TwoLevel, direct, invert_blocks, pcg

F64 = NDArray[np.float64]


@dataclass(frozen=True, slots=True)
class RefreshReport:
    """One exact recomputation: features solved for, PCG iterations, whether PCG fell back to a direct solve."""

    features: int
    iterations: int
    direct: bool


def _sym(a: F64) -> F64:
    return 0.5 * (a + a.T)


class CovarianceCache:
    """A conservative joint covariance of the vicinity features V (module docstring)."""

    def __init__(self) -> None:
        self.features: list[int] = []  # V, in the order of the rows of sigma
        self.position: dict[int, int] = {}
        self._sigma = np.zeros((32, 32))
        self._marginal = np.zeros((32, 2, 2))  # every feature's latest marginal bound
        self._known = np.zeros(32, dtype=bool)
        self.scan = -1  # scan of the last exact recomputation
        self.refreshes = 0

    @property
    def sigma(self) -> F64:
        """The joint covariance (2|V|, 2|V|) of V (a view)."""
        m = 2 * len(self.features)
        return self._sigma[:m, :m]

    @property
    def nbytes(self) -> int:
        """Bytes of the arrays: O(|V|^2 + N)."""
        return self._sigma.nbytes + self._marginal.nbytes + self._known.nbytes

    def has(self, features: list[int]) -> bool:
        """Whether every one of ``features`` is in V."""
        return all(f in self.position for f in features)

    def known(self, features: list[int]) -> bool:
        """Whether every one of ``features`` has a marginal bound (in V, or kept when it left V)."""
        return all(f < len(self._known) and self._known[f] for f in features)

    def block(self, features: list[int]) -> F64:
        """Joint covariance (2k, 2k) of ``features``, all of which must be in V."""
        idx = dofs([self.position[f] for f in features])
        return self.sigma[np.ix_(idx, idx)]

    def marginals(self, features: list[int]) -> F64:
        """Marginal covariances (k, 2, 2) of ``features`` (each in V or with a kept marginal)."""
        out = np.empty((len(features), 2, 2))
        for k, f in enumerate(features):
            p = self.position.get(f)
            if p is None:
                if not self.known([f]):
                    raise KeyError(f"feature {f} has no covariance")
                out[k] = self._marginal[f]
            else:
                out[k] = self._sigma[2 * p:2 * p + 2, 2 * p:2 * p + 2]
        return out

    # -- changes of V
    def _append(self, features: list[int], cross: F64, block: F64) -> None:
        """Append ``features`` to V with covariance ``block`` (2k, 2k) and ``cross`` (2k, 2|V|) with V."""
        m, k = 2 * len(self.features), 2 * len(features)
        if len(self._sigma) < m + k:
            grown = np.zeros((max(m + k, 2 * len(self._sigma)),) * 2)
            grown[:m, :m] = self._sigma[:m, :m]
            self._sigma = grown
        self._sigma[m:m + k, :m] = cross
        self._sigma[:m, m:m + k] = cross.T
        self._sigma[m:m + k, m:m + k] = _sym(block)
        for f in features:
            self.position[f] = len(self.features)
            self.features.append(f)
            if f >= len(self._known):
                self._known = _grown(self._known, f + 1)
                self._marginal = _grown(self._marginal, f + 1)
            self._known[f] = True

    def insert(self, features: list[int], block: F64) -> None:
        """Add features independent of V with joint covariance ``block`` (2k, 2k) (phase I, bootstrap)."""
        if features:
            self._append(features, np.zeros((2 * len(features), 2 * len(self.features))), block)

    def drop(self, features: list[int]) -> None:
        """Marginalise ``features`` out of V, keeping their 2x2 marginals. O(|V|^2)."""
        gone = set(features) & self.position.keys()
        if not gone:
            return
        for f in gone:
            p = self.position[f]
            self._marginal[f] = self._sigma[2 * p:2 * p + 2, 2 * p:2 * p + 2]
        keep = [f for f in self.features if f not in gone]
        idx = dofs([self.position[f] for f in keep])
        m = len(idx)
        self._sigma[:m, :m] = self._sigma[np.ix_(idx, idx)]
        self.features = keep
        self.position = {f: j for j, f in enumerate(keep)}

    def replace(self, features: list[int], sigma: F64) -> None:
        """Make V exactly ``features`` with joint covariance ``sigma`` (2k, 2k)."""
        for f in self.features:
            if f not in features:
                p = self.position[f]
                self._marginal[f] = self._sigma[2 * p:2 * p + 2, 2 * p:2 * p + 2]
        self.features, self.position = [], {}
        self._append(list(features), np.zeros((len(sigma), 0)), sigma)

    # -- eq. (10) in covariance form
    def update(self, features: list[int], jac: F64, r_cov: F64) -> None:
        """The Kalman form of eq. (10), ``dI = J^T R^-1 J`` on ``features`` (all in V): exact on V.

        ``jac`` (p, 2k) is the measurement Jacobian with respect to ``features`` (k), ``r_cov``
        (p, p) the measurement noise covariance.
        """
        sigma = self.sigma
        idx = dofs([self.position[f] for f in features])
        pht = sigma[:, idx] @ jac.T  # P_V,T J^T (2|V|, p)
        s = jac @ pht[idx] + r_cov
        gain = sla.cho_solve(sla.cho_factor(_sym(s), check_finite=False), pht.T, check_finite=False)  # S^-1 J P_T,V
        sigma -= pht @ gain
        sigma[...] = _sym(sigma)

    def recast_update(self, old: list[int], joining: list[int], jac: F64, r_map: F64) -> None:
        """Eq. (10) for one recast measurement (eqs. 7-8), and eq. (9) for the features joining V.

        ``jac`` (2m-3, 2m) is d z_map / d X over ``old + joining`` in that order (``old``: the
        k_o >= 2 features of the scan in V, anchors first; ``joining``: the others), ``r_map``
        (2m-3, 2m-3) the noise covariance of ``z_map``. Module docstring for the algebra.
        """
        ko, kn = 2 * len(old), 2 * len(joining)
        ro = ko - 3  # z_map rows of the features in V: d_12, then alpha_i12, d_1i per feature
        j_oo = jac[:ro, :ko]
        r_oo = r_map[:ro, :ro]
        if ro:
            self.update(old, j_oo, r_oo)
        if not joining:
            return
        j_no, j_nn = jac[ro:, :ko], jac[ro:, ko:]
        r_no, r_nn = r_map[ro:, :ro], r_map[ro:, ro:]
        if ro:
            chol = sla.cho_factor(_sym(r_oo), check_finite=False)
            g = sla.cho_solve(chol, r_no.T, check_finite=False).T  # R_no R_oo^-1
            coupling = j_no - g @ j_oo
            q = r_nn - g @ r_no.T
        else:
            coupling, q = j_no, r_nn
        k = len(joining)
        diag = j_nn.reshape(k, 2, k, 2)[np.arange(k), :, np.arange(k), :]  # (k, 2, 2) blocks of J_nn
        inv = np.zeros((kn, kn))
        for j, block in enumerate(invert_blocks(diag)):  # J_nn is block-diagonal: one feature per 2 rows
            inv[2 * j:2 * j + 2, 2 * j:2 * j + 2] = block
        a = -inv @ coupling  # (2kn, 2ko)
        idx = dofs([self.position[f] for f in old])
        sigma = self.sigma
        cross = a @ sigma[idx, :]
        block = cross[:, idx] @ a.T + inv @ q @ inv.T
        self._append(joining, cross, block)

    # -- exact recomputation
    def refresh(self, info: InformationMatrix, inv_blocks: F64, features: list[int], scan: int, rtol: float,
                maxiter: int, x: F64 | None = None) -> RefreshReport:
        """Replace V by ``features`` with their exact joint block of I^-1 (2 columns each, block PCG). O(N).

        With the estimates ``x`` (2N,), PCG uses the two-level preconditioner
        (:class:`slamreplay.algorithms.dslam.recovery.TwoLevel`), else block-Jacobi.
        """
        n2, k = 2 * info.n, len(features)
        idx = dofs(features)
        e = np.zeros((n2, 2 * k))
        e[idx, np.arange(2 * k)] = 1.0
        x0 = np.zeros((n2, 2 * k))
        p = np.repeat(np.asarray(features, dtype=np.int64), 2)
        scale = np.abs(inv_blocks[p, np.tile([0, 1], k), np.tile([0, 1], k)])
        precondition = TwoLevel(info, inv_blocks, x) if x is not None and info.n else None
        result = pcg(info, e, x0, inv_blocks, rtol * np.maximum(scale, 1e-300), maxiter, precondition)
        columns = result.x if result.converged else direct(info, e)
        self.replace(list(features), _sym(columns[idx, :]))
        self.scan = scan
        self.refreshes += 1
        return RefreshReport(k, result.iterations, not result.converged)
