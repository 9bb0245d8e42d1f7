"""Data association for landmark SLAM with unknown ids: maximum likelihood with Mahalanobis gating.

Section 3.1 of [1]_ follows the standard maximum-likelihood approach of [2]_ and keeps two
lists: confirmed features (in the map) and tentative ones, not yet validated. Here:

- every observation ``z_j`` is compared with every candidate feature ``c`` through the
  innovation ``nu = z_j - z_c`` and its covariance ``S_c``; the pair is admissible when the
  squared Mahalanobis distance ``d2 = nu^T S_c^-1 nu`` is inside the ``gate_probability``
  chi-square gate (2 degrees of freedom);
- among admissible pairs, the assignment maximises the joint likelihood: it minimises the sum
  of ``d2 + ln det S_c`` (the negative log-likelihood up to a constant) with each feature used at
  most once (a linear assignment, not a greedy nearest neighbour);
- with known ids, an observation of a mapped landmark whose innovation falls outside the
  ``outlier_probability`` gate is rejected as an outlier (1 keeps every observation);
- an observation matched to no confirmed feature starts or extends a tentative feature only
  when it lies outside the ``new_feature_probability`` gate of every confirmed feature (else it
  is ambiguous and dropped); a tentative feature seen ``confirm_hits`` times is confirmed, one
  not seen again within ``tentative_window_scans`` scans is forgotten.

References
----------
.. [1] Z. Wang, S. Huang, G. Dissanayake, "Implementation issues and experimental evaluation
   of D-SLAM", FSR 2005, section 3.1.
.. [2] G. Dissanayake et al., "A solution to the simultaneous localization and map building
   (SLAM) problem", IEEE TRA 17:229-241, 2001.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import cast

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import linear_sum_assignment
from scipy.stats import chi2

from slamreplay.algorithms.common.se2 import wrap_angle

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]
_INADMISSIBLE = 1e12


@dataclass(frozen=True, slots=True)
class AssociationConfig:
    """Gates and the tentative-list rules (module docstring)."""

    gate_probability: float = 0.99
    new_feature_probability: float = 0.9999
    confirm_hits: int = 3
    tentative_window_scans: int = 25
    outlier_probability: float = 1.0  # off: a filter that is wrong about its pose would reject good data

    def __post_init__(self) -> None:
        if not 0 < self.outlier_probability <= 1:
            raise ValueError(f"outlier_probability must be in (0, 1], got {self.outlier_probability}")
        if not 0 < self.gate_probability <= self.new_feature_probability < 1:
            raise ValueError("gate_probability and new_feature_probability must satisfy "
                             f"0 < gate <= new < 1, got {self.gate_probability}, {self.new_feature_probability}")
        if self.confirm_hits < 1 or self.tentative_window_scans < 1:
            raise ValueError(f"confirm_hits and tentative_window_scans must be >= 1, got {self.confirm_hits}, "
                             f"{self.tentative_window_scans}")

    @property
    def gate(self) -> float:
        return float(chi2.ppf(self.gate_probability, 2))

    @property
    def new_gate(self) -> float:
        return float(chi2.ppf(self.new_feature_probability, 2))

    @property
    def outlier_gate(self) -> float:
        return float(chi2.ppf(self.outlier_probability, 2)) if self.outlier_probability < 1 else np.inf


def innovation_covariance(h_r: F64, p_r: F64, h_l: F64, p_l: F64, r_cov: F64, p_rl: F64 | None = None) -> F64:
    """S (k, 2, 2) = H_r P_r H_r^T + H_l P_l H_l^T + R (+ the cross terms when P_rl (k, 3, 2) is given)."""
    s = h_r @ p_r @ h_r.transpose(0, 2, 1) + h_l @ p_l @ h_l.transpose(0, 2, 1) + r_cov
    if p_rl is not None:
        cross = h_r @ p_rl @ h_l.transpose(0, 2, 1)
        s = s + cross + cross.transpose(0, 2, 1)
    return s


def outliers(z: F64, z_pred: F64, s: F64, gate: float) -> NDArray[np.bool_]:
    """Observations z (k, 2) whose own innovation fails the gate (known ids), given z_pred and S (k, 2, 2)."""
    nu = z - z_pred
    nu[:, 1] = wrap_angle(nu[:, 1])
    return cast(NDArray[np.bool_], np.einsum("ki,kij,kj->k", nu, np.linalg.inv(s), nu) > gate)


def mahalanobis(z: F64, z_pred: F64, s: F64, angular: bool = True) -> F64:
    """Squared Mahalanobis distances (m, n) of observations z (m, 2) to predictions (n, 2) with S (n, 2, 2).

    With ``angular`` the second component is a bearing and its difference is wrapped.
    """
    nu = z[:, None, :] - z_pred[None, :, :]
    if angular:
        nu[..., 1] = wrap_angle(nu[..., 1])
    s_inv = np.linalg.inv(s)
    return cast(F64, np.einsum("mni,nij,mnj->mn", nu, s_inv, nu))


def match(d2: F64, log_det: F64, gate: float, new_gate: float) -> tuple[I64, NDArray[np.bool_]]:
    """Maximum-likelihood assignment of m observations to n candidates (module docstring).

    Parameters
    ----------
    d2 : (m, n) squared Mahalanobis distances; log_det : (n,) ln det S of each candidate.

    Returns
    -------
    assigned : (m,) the candidate of each observation, -1 for none.
    new : (m,) True where an unassigned observation is outside ``new_gate`` of every candidate.
    """
    m, n = d2.shape
    assigned = np.full(m, -1, dtype=np.int64)
    far = np.all(d2 > new_gate, axis=1) if n else np.ones(m, dtype=bool)
    if n and m:
        cost = np.where(d2 <= gate, d2 + log_det[None, :], _INADMISSIBLE)
        rows, cols = linear_sum_assignment(cost)
        ok = cost[rows, cols] < _INADMISSIBLE
        assigned[rows[ok]] = cols[ok]
    return assigned, far & (assigned < 0)


class TentativeList:
    """Features seen but not yet confirmed: positions in the map frame with a covariance and a hit count."""

    def __init__(self) -> None:
        self.means = np.zeros((0, 2))
        self.covs = np.zeros((0, 2, 2))
        self.hits = np.zeros(0, dtype=np.int64)
        self.last_seen = np.zeros(0, dtype=np.int64)

    def __len__(self) -> int:
        return len(self.hits)

    def observe(self, points: F64, covs: F64, scan: int, cfg: AssociationConfig) -> tuple[I64, NDArray[np.bool_]]:
        """Match map-frame observations (k, 2) with covariances (k, 2, 2) to the list, adding new entries.

        Returns the tentative index of each observation (-1 for an ambiguous one, dropped) and
        whether that entry now has at least ``confirm_hits`` hits.
        """
        k = len(points)
        index = np.full(k, -1, dtype=np.int64)
        if k == 0:
            return index, np.zeros(0, dtype=bool)
        n = len(self)
        if n:
            s = covs[:, None] + self.covs[None, :]
            nu = points[:, None, :] - self.means[None, :, :]
            d2 = np.einsum("kni,knij,knj->kn", nu, np.linalg.inv(s), nu)
            assigned, new = match(d2, np.zeros(n), cfg.gate, cfg.new_gate)
        else:
            assigned, new = np.full(k, -1, dtype=np.int64), np.ones(k, dtype=bool)
        for j in np.flatnonzero(assigned >= 0).tolist():
            t = int(assigned[j])
            info_t, info_j = np.linalg.inv(self.covs[t]), np.linalg.inv(covs[j])
            mean = np.linalg.solve(info_t + info_j, info_t @ self.means[t] + info_j @ points[j])
            # Robot-pose errors are shared between sightings: keep the smaller covariance, do not fuse them.
            self.means[t] = mean
            if np.trace(covs[j]) < np.trace(self.covs[t]):
                self.covs[t] = covs[j]
            self.hits[t] += 1
            self.last_seen[t] = scan
            index[j] = t
        fresh = np.flatnonzero(new)
        if len(fresh):
            index[fresh] = np.arange(n, n + len(fresh))
            self.means = np.concatenate([self.means, points[fresh]])
            self.covs = np.concatenate([self.covs, covs[fresh]])
            self.hits = np.concatenate([self.hits, np.ones(len(fresh), dtype=np.int64)])
            self.last_seen = np.concatenate([self.last_seen, np.full(len(fresh), scan, dtype=np.int64)])
        confirmed = np.zeros(k, dtype=bool)
        ok = index >= 0
        confirmed[ok] = self.hits[index[ok]] >= cfg.confirm_hits
        return index, confirmed

    def remove(self, entries: list[int]) -> None:
        """Forget these entries (confirmed ones that joined the map)."""
        keep = np.ones(len(self), dtype=bool)
        keep[entries] = False
        self._keep(keep)

    def prune(self, scan: int, cfg: AssociationConfig) -> int:
        """Forget unconfirmed entries not seen for more than the window; returns how many."""
        stale = (self.hits < cfg.confirm_hits) & (scan - self.last_seen > cfg.tentative_window_scans)
        self._keep(~stale)
        return int(stale.sum())

    def _keep(self, keep: NDArray[np.bool_]) -> None:
        self.means, self.covs = self.means[keep], self.covs[keep]
        self.hits, self.last_seen = self.hits[keep], self.last_seen[keep]
