"""The covariance of the features near the robot, recovered by solving ``I c = e_j`` (section 3.3 of [1]_).

Localization needs the joint covariance of the observed mapped features, data association the
marginals of the features in the robot's vicinity. Both are blocks of ``I^-1``; they come from
2 columns per feature, solved by block PCG warm-started from the previous columns of the same
features, with a direct sparse solve when PCG does not converge.

The blocks are kept as a snapshot and reused for a few scans. This is safe because D-SLAM's
map has no prediction step: eq. (10) only ever adds a positive semi-definite term to I, so
``I^-1`` only shrinks, and any block of an older ``I^-1`` bounds the current one from above
(a conservative covariance, never an overconfident one). Features initialised after the
snapshot join it through eq. (9): their covariance, and their cross-covariance with the
snapshot's features, are those of the eq. (9) initial estimate, which the later EIF estimate
improves on, so the joint block stays conservative.

References
----------
.. [1] Z. Wang, S. Huang, G. Dissanayake, "Implementation issues and experimental evaluation
   of D-SLAM", FSR 2005, sections 3.2-3.3, eq. (9).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from algorithms.dslam.information import InformationMatrix, dofs
from algorithms.dslam.recovery import direct, pcg

F64 = NDArray[np.float64]


@dataclass(frozen=True, slots=True)
class RefreshReport:
    """One recomputation of the snapshot: features solved for, PCG iterations, whether PCG sufficed."""

    features: int
    iterations: int
    direct: bool


class CovarianceCache:
    """A conservative joint covariance of a set of features (module docstring)."""

    def __init__(self) -> None:
        self.features: list[int] = []
        self.position: dict[int, int] = {}
        self.sigma = np.zeros((0, 0))
        self.scan = -1
        self._columns = np.zeros((0, 0))  # (2N_then, 2k) solved columns, for warm starts
        self._solved: dict[int, int] = {}  # feature -> its column pair in _columns

    def has(self, features: list[int]) -> bool:
        """Whether every one of ``features`` is in the snapshot."""
        return all(f in self.position for f in features)

    def block(self, features: list[int]) -> F64:
        """Joint covariance (2k, 2k) of ``features``, all of which must be in the snapshot."""
        idx = dofs([self.position[f] for f in features])
        return self.sigma[np.ix_(idx, idx)]

    def marginals(self, features: list[int]) -> F64:
        """Marginal covariances (k, 2, 2) of ``features`` in the snapshot."""
        out = np.empty((len(features), 2, 2))
        for k, f in enumerate(features):
            p = 2 * self.position[f]
            out[k] = self.sigma[p:p + 2, p:p + 2]
        return out

    def refresh(self, info: InformationMatrix, inv_blocks: F64, features: list[int], scan: int, rtol: float,
                maxiter: int) -> RefreshReport:
        """Recompute the joint covariance of ``features`` from the current I (2 columns each)."""
        n2, k = 2 * info.n, len(features)
        idx = dofs(features)
        e = np.zeros((n2, 2 * k))
        e[idx, np.arange(2 * k)] = 1.0
        x0 = np.zeros((n2, 2 * k))
        old_n2 = self._columns.shape[0]
        for j, f in enumerate(features):
            p = self._solved.get(f)
            if p is not None:
                x0[:old_n2, 2 * j:2 * j + 2] = self._columns[:, 2 * p:2 * p + 2]
        scale = np.abs(inv_blocks[np.repeat(np.asarray(features, dtype=np.int64), 2), np.tile([0, 1], k),
                                  np.tile([0, 1], k)])
        result = pcg(info, e, x0, inv_blocks, rtol * np.maximum(scale, 1e-300), maxiter)
        columns = result.x if result.converged else direct(info, e)
        sigma = columns[idx, :]
        self.features = list(features)
        self.position = {f: j for j, f in enumerate(features)}
        self._solved = dict(self.position)
        self._columns = columns
        self.sigma = 0.5 * (sigma + sigma.T)
        self.scan = scan
        return RefreshReport(k, result.iterations, not result.converged)

    def augment(self, new: list[int], anchors: tuple[int, int], j_x: F64, j_z: F64, r_z: F64) -> bool:
        """Add features initialised by eq. (9) from ``anchors``; False when an anchor is not in the snapshot.

        ``j_x`` (k, 2, 4) and ``j_z`` (k, 2, 2) are eq. (9)'s Jacobians, ``r_z`` (2k, 2k) the noise
        covariance of the new features' ``[alpha_i12, d_1i]`` entries of ``z_map``.
        """
        if not self.has(list(anchors)) or not new:
            return self.has(list(anchors))
        k = len(new)
        a_idx = dofs([self.position[a] for a in anchors])
        gx = np.concatenate(list(j_x), axis=0)  # (2k, 4)
        gz = np.zeros((2 * k, 2 * k))
        for j in range(k):
            gz[2 * j:2 * j + 2, 2 * j:2 * j + 2] = j_z[j]
        cross = gx @ self.sigma[a_idx, :]  # (2k, 2n): cov(new, snapshot)
        new_block = gx @ self.sigma[np.ix_(a_idx, a_idx)] @ gx.T + gz @ r_z @ gz.T
        m = self.sigma.shape[0]
        sigma = np.zeros((m + 2 * k, m + 2 * k))
        sigma[:m, :m] = self.sigma
        sigma[m:, :m] = cross
        sigma[:m, m:] = cross.T
        sigma[m:, m:] = 0.5 * (new_block + new_block.T)
        self.sigma = sigma
        for f in new:
            self.position[f] = len(self.features)
            self.features.append(f)
        return True
