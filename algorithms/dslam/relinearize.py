"""Relinearisation of D-SLAM's map at the end of a run (not in [1]_): the same measurements, one model.

D-SLAM's map filter (eq. 10) linearises each measurement once, at the estimate of the moment,
and keeps only the sum of the linearised terms in I and i. The map has no prediction step, so
``I^-1 i`` is one Gauss-Newton step per measurement, each from a different point: a measurement
taken while the map was rotated by a degree or two (exploration before a loop closure) keeps a
model linearised in that rotated map. z_map (eq. 7) is invariant to rotations, and the map's
rotation is fixed by phase I alone, so the second-order remainders of those models add up along
that weakly known direction: on the paper's scenario (``sim-landmarks``, seed 2) the EIF map is
rotated by 0.15 degrees about the start (8.7 cm RMSE) while its shape is as good as EKF-SLAM's
(1.3 cm after a rigid alignment). Gauss-Newton over the same measurements, relinearised at the
final estimate, gives 2.5 cm.

:class:`MeasurementLog` holds what the map filter was given, in a summary whose size depends on
the map, not on the run's length: every measurement model D-SLAM uses is a fixed function of the
feature positions, so measurements of the same function add up into one exact sufficient statistic.

- A phase I reading ``[r, theta]`` of feature f from the exactly known origin (eq. 1): per feature,
  ``Lambda = sum R_k^-1`` (2, 2) and ``eta = sum R_k^-1 z_k``.
- A recast ``z_map`` with anchors f_1, f_2 (eq. 7): its entries ``d_12``, ``alpha_i12`` and ``d_1i``
  are functions of f_1, f_2 and f_i alone, so every scan with the same anchor pair measures rows of
  one function ``h_12(X)`` over the union of the features seen with that pair: ``Lambda = sum S_k^T
  R_k^-1 S_k`` and ``eta = sum S_k^T R_k^-1 z_k`` (``S_k`` places the scan's rows; R_map's
  correlations are kept).
- A fixed information prior (the bootstrap, which depends on the robot pose of its scan): summed
  per feature set.

The log-likelihood of all the measurements is then ``-1/2 h^T Lambda h + eta^T h`` per entry, so
Gauss-Newton over the summary is Gauss-Newton over every measurement: the same I and i at any
linearisation point (angles are unwrapped against the first reading of their row, which every
later reading is within noise of). Its size is the number of anchor pairs times the features seen
with a pair, O(N) for a sensor of bounded range, whatever the duration.

:func:`relinearize` iterates ``x <- I(x)^-1 i(x)``, with I and i rebuilt by eq. (10) at x, until no
feature moves more than the tolerance. It uses exactly the information D-SLAM has, no odometry
and no ``z_rob``; it costs a pass over the summary plus a sparse factorisation per iteration, so
it runs once, when the run ends.

References
----------
.. [1] Z. Wang, S. Huang, G. Dissanayake, "Implementation issues and experimental evaluation
   of D-SLAM", FSR 2005, eqs. (7)-(10).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.linalg as sla
from numpy.typing import NDArray

from slamreplay.algorithms.common import rangebearing
from slamreplay.algorithms.common.se2 import wrap_angle
from slamreplay.algorithms.dslam.information import InformationMatrix
from slamreplay.algorithms.dslam.recast import angle_rows, map_invariants
from slamreplay.algorithms.dslam.recovery import direct

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]


@dataclass(frozen=True, slots=True)
class Relinearized:
    """The relinearised information (I, i at ``x``), the estimate ``x`` (2N,), iterations and the last step (m)."""

    info: InformationMatrix
    x: F64
    iterations: int
    step_m: float


class _Entry:
    """One summary entry (module docstring): features, ``Lambda``, ``eta`` and each angle row's first reading."""

    __slots__ = ("eta", "features", "lam", "position", "ref", "seen")

    def __init__(self, features: list[int], rows: int) -> None:
        self.features = list(features)
        self.position = {f: k for k, f in enumerate(features)}
        self.lam = np.zeros((rows, rows))
        self.eta = np.zeros(rows)
        self.ref = np.zeros(rows)
        self.seen = np.zeros(rows, dtype=bool)

    def grow(self, rows: int) -> None:
        old = len(self.eta)
        if rows <= old:
            return
        lam = np.zeros((rows, rows))
        lam[:old, :old] = self.lam
        self.lam = lam
        self.eta = np.concatenate([self.eta, np.zeros(rows - old)])
        self.ref = np.concatenate([self.ref, np.zeros(rows - old)])
        self.seen = np.concatenate([self.seen, np.zeros(rows - old, dtype=bool)])

    def add(self, rows: I64, z: F64, r_cov: F64, angles: I64) -> None:
        """Add a measurement ``z`` of the entry's ``rows`` with noise ``r_cov``; ``angles``: its angle rows (local)."""
        z = np.array(z, dtype=np.float64)
        first = ~self.seen[rows]
        self.ref[rows[first]] = z[first]
        self.seen[rows] = True
        z[angles] = self.ref[rows[angles]] + wrap_angle(z[angles] - self.ref[rows[angles]])
        chol = sla.cho_factor(0.5 * (r_cov + r_cov.T), check_finite=False)
        w = sla.cho_solve(chol, np.eye(len(z)), check_finite=False)
        self.lam[np.ix_(rows, rows)] += 0.5 * (w + w.T)
        self.eta[rows] += w @ z

    @property
    def nbytes(self) -> int:
        return int(self.lam.nbytes + self.eta.nbytes + self.ref.nbytes + self.seen.nbytes + 8 * len(self.features))


def _terms(jac: F64, lam: F64, nu: F64, x_lin: F64) -> tuple[F64, F64]:
    """Eq. (10) with the information ``lam`` in place of ``R^-1``: ``J^T lam J`` and ``J^T lam (nu + J x_lin)``."""
    w = lam @ jac
    return 0.5 * (jac.T @ w + (jac.T @ w).T), w.T @ (nu + jac @ x_lin)


class MeasurementLog:
    """The summary of every measurement the map filter used (module docstring)."""

    def __init__(self) -> None:
        self._phase_one: dict[int, _Entry] = {}
        self._recast: dict[tuple[int, int], _Entry] = {}
        self._priors: dict[tuple[int, ...], tuple[F64, F64]] = {}
        self.measurements = 0

    def __len__(self) -> int:
        """Measurements summarised so far."""
        return self.measurements

    @property
    def entries(self) -> int:
        """Summary entries (phase I features, anchor pairs, prior feature sets): what the memory grows with."""
        return len(self._phase_one) + len(self._recast) + len(self._priors)

    @property
    def nbytes(self) -> int:
        """Bytes of the summary's arrays."""
        priors = sum(a.nbytes + b.nbytes for a, b in self._priors.values())
        return sum(e.nbytes for e in (*self._phase_one.values(), *self._recast.values())) + priors

    def phase_one(self, feature: int, z: F64, r_cov: F64) -> None:
        """A phase I reading ``z = [r, theta]`` (2,) of ``feature`` from the origin, noise ``r_cov`` (2, 2)."""
        entry = self._phase_one.setdefault(int(feature), _Entry([int(feature)], 2))
        entry.add(np.arange(2), z, r_cov, np.array([1]))
        self.measurements += 1

    def recast(self, features: list[int], z_map: F64, r_map: F64) -> None:
        """A recast ``z_map`` (2k-3,) of ``features`` (k,), anchors first, noise ``r_map`` (eq. 7)."""
        fs = [int(f) for f in features]
        key = (fs[0], fs[1])
        entry = self._recast.get(key)
        if entry is None:
            entry = self._recast[key] = _Entry(fs[:2], 1)
        rows = [0]
        for f in fs[2:]:
            pos = entry.position.get(f)
            if pos is None:
                pos = entry.position[f] = len(entry.features)
                entry.features.append(f)
            rows += [2 * pos - 3, 2 * pos - 2]
        entry.grow(2 * len(entry.features) - 3)
        entry.add(np.asarray(rows, dtype=np.int64), z_map, r_map, angle_rows(len(fs)))
        self.measurements += 1

    def prior(self, features: list[int], d_matrix: F64, d_vector: F64) -> None:
        """A fixed information term (2k, 2k), (2k,) on ``features`` (the bootstrap)."""
        key = tuple(int(f) for f in features)
        old = self._priors.get(key)
        d_matrix, d_vector = np.array(d_matrix, dtype=np.float64), np.array(d_vector, dtype=np.float64)
        self._priors[key] = (d_matrix, d_vector) if old is None else (old[0] + d_matrix, old[1] + d_vector)
        self.measurements += 1

    def information(self, n: int, x: F64) -> InformationMatrix:
        """I and i of ``n`` features, every measurement linearised by eq. (10) at ``x`` (2n,)."""
        info = InformationMatrix()
        info.add_features(n)
        pts = x.reshape(-1, 2)
        for key, (d_matrix, d_vector) in self._priors.items():
            info.add(np.asarray(key, dtype=np.int64), d_matrix, d_vector)
        for f, entry in self._phase_one.items():
            zp, _, h_l = rangebearing.predict(np.zeros(3), pts[f][None, :])
            nu = entry_mean(entry) - zp[0]
            nu[1] = wrap_angle(nu[1])
            info.add(np.array([f]), *_terms(h_l[0], entry.lam, nu, pts[f]))
        for entry in self._recast.values():
            fs = np.asarray(entry.features, dtype=np.int64)
            h, jac = map_invariants(pts[fs])
            nu = entry_mean(entry) - h
            rows = angle_rows(len(fs))
            nu[rows] = wrap_angle(nu[rows])
            info.add(fs, *_terms(jac, entry.lam, nu, pts[fs].reshape(-1)))
        return info


def entry_mean(entry: _Entry) -> F64:
    """The merged measurement ``Lambda^-1 eta`` of one summary entry."""
    return np.asarray(sla.cho_solve(sla.cho_factor(entry.lam, check_finite=False), entry.eta, check_finite=False))

def relinearize(log: MeasurementLog, n: int, x0: F64, max_iterations: int, tol_m: float) -> Relinearized:
    """Gauss-Newton over ``log`` from ``x0`` (2n,): at most ``max_iterations`` steps, until none exceeds ``tol_m``.

    Returns the information rebuilt at the final estimate, so that ``I^-1`` is its covariance.
    """
    if x0.shape != (2 * n,):
        raise ValueError(f"x0 must have shape ({2 * n},), got {x0.shape}")
    if max_iterations < 1:
        raise ValueError(f"max_iterations must be >= 1, got {max_iterations}")
    x = np.array(x0, dtype=np.float64)
    step = np.inf
    it = 0
    info = log.information(n, x)
    while it < max_iterations and step > tol_m:
        it += 1
        new = direct(info, np.array(info.vector))
        step = float(np.max(np.abs(new - x))) if n else 0.0
        x = new
        info = log.information(n, x)
    return Relinearized(info, x, it, step)
