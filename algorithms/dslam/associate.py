"""D-SLAM data association (section 3.1 of [1]_): known landmark ids, or unknown ids by maximum likelihood.

Unknown ids: the candidates are the mapped features in the robot's vicinity; the innovation
covariance of candidate c is ``S_c = H_r P_r H_r^T + H_c P_c H_c^T + R`` with P_r the predicted
robot covariance and P_c the feature's marginal bound (:mod:`slamreplay.algorithms.dslam.covariance`: from
the vicinity covariance, or the bound kept when the feature left the vicinity). D-SLAM does not
keep the robot-map cross-covariance, so it is taken as zero here. The candidates come from a
grid over the estimates (:mod:`slamreplay.algorithms.dslam.spatial`), not a scan of all N features.
Matching, gating and the tentative list are :mod:`slamreplay.algorithms.common.association`; tentative
features are placed with the localized pose, after Covariance Intersection.

References
----------
.. [1] Z. Wang, S. Huang, G. Dissanayake, "Implementation issues and experimental evaluation
   of D-SLAM", FSR 2005, section 3.1.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np
from numpy.typing import ArrayLike, NDArray

from slamreplay.algorithms.common import rangebearing
from slamreplay.algorithms.common.association import (
    AssociationConfig,
    TentativeList,
    innovation_covariance,
    mahalanobis,
    match,
    outliers,
)
from slamreplay.algorithms.dslam.covariance import CovarianceCache
from slamreplay.algorithms.dslam.recovery import Recovery

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]


class _Margins(Protocol):
    @property
    def vicinity_margin_m(self) -> float: ...


class FilterState(Protocol):
    """What association reads of the filter (:class:`~slamreplay.algorithms.dslam.filter.DSlam` is one): the
    robot's pose and covariance, the map's estimates and marginals, and the features near a point. A protocol,
    so that this module does not import the filter that owns an ``Associator``."""

    pose: F64
    pose_cov: F64
    max_range: float
    recovery: Recovery
    covariance: CovarianceCache

    @property
    def config(self) -> _Margins: ...

    def within(self, position: F64, radius: float) -> list[int]: ...


@dataclass(frozen=True, slots=True)
class Association:
    """Mapped feature per observation (-1: none) and the observations that may start a feature."""

    features: I64
    candidates_new: tuple[int, ...]


class Associator:
    """Known-id or unknown-id association for one :class:`~slamreplay.algorithms.dslam.filter.DSlam`."""

    def __init__(self, mode: str, params: AssociationConfig) -> None:
        self.mode, self.params = mode, params
        self.by_id: dict[int, int] = {}
        self.tentative = TentativeList()
        self._ids: I64 | None = None
        self.rejected = 0  # known-id observations rejected as outliers
        self.unmapped: dict[int, tuple[F64, F64, int]] = {}  # known ids not mapped yet: sum C^-1 p, sum C^-1, readings

    def check_ids(self, ids: ArrayLike | None, m: int) -> I64 | None:
        """Validated ids (m,) in known-id mode (ValueError when absent or negative); None otherwise."""
        if self.mode != "known":
            return None
        if ids is None:
            raise ValueError("ids are required in known-id association mode (use association='unknown')")
        arr = np.asarray(ids, dtype=np.int64).reshape(-1)
        if arr.shape != (m,):
            raise ValueError(f"ids must have shape ({m},), got {arr.shape}")
        if np.any(arr < 0):
            raise ValueError("ids must all be >= 0 in known-id association mode (-1 means unknown)")
        return arr

    def pending_id(self, j: int) -> int:
        """The landmark id of observation ``j`` of the current scan (known ids), else -1."""
        return int(self._ids[j]) if self._ids is not None else -1

    def associate(self, slam: FilterState, r: F64, b: F64, ids: I64 | None, r_old: F64) -> Association:
        """Match the scan's observations with mapped features (predicted robot pose)."""
        m = len(r)
        self._ids = ids
        features = np.full(m, -1, dtype=np.int64)
        if ids is not None:
            seen: set[int] = set()
            new = []
            for j, i in enumerate(ids.tolist()):
                if i in seen:
                    continue  # a landmark twice in one scan: keep its first reading
                seen.add(i)
                f = self.by_id.get(i)
                if f is None:
                    new.append(j)
                else:
                    features[j] = f
            self._reject_outliers(slam, r, b, features, r_old)
            return Association(features, tuple(new))
        pose, cov = slam.pose, slam.pose_cov
        spread = 3.0 * float(np.sqrt(max(np.linalg.eigvalsh(cov[:2, :2]).max(), 0.0)))
        cand = slam.within(pose[:2], slam.max_range + slam.config.vicinity_margin_m + spread)
        if cand:
            z_pred, h_r, h_l = rangebearing.predict(pose, slam.recovery.x.reshape(-1, 2)[cand])
            s = innovation_covariance(h_r, cov, h_l, slam.covariance.marginals(cand), r_old[:2, :2])
            d2 = mahalanobis(np.stack([r, b], -1), z_pred, s)
            assigned, far = match(d2, np.linalg.slogdet(s)[1], self.params.gate, self.params.new_gate)
            ok = assigned >= 0
            features[ok] = np.asarray(cand, dtype=np.int64)[assigned[ok]]
        else:
            far = np.ones(m, dtype=bool)
        return Association(features, tuple(np.flatnonzero(far).tolist()))

    def _reject_outliers(self, slam: FilterState, r: F64, b: F64, features: I64, r_old: F64) -> None:
        """Known ids: drop observations of mapped features that fail the outlier gate (``features`` in place)."""
        obs = np.flatnonzero(features >= 0)
        if not len(obs) or not np.isfinite(self.params.outlier_gate):
            return
        f = features[obs].tolist()
        z_pred, h_r, h_l = rangebearing.predict(slam.pose, slam.recovery.x.reshape(-1, 2)[f])
        s = innovation_covariance(h_r, slam.pose_cov, h_l, slam.covariance.marginals(f),
                                  rangebearing.blocks(r_old)[obs])
        bad = outliers(np.stack([r[obs], b[obs]], -1), z_pred, s, self.params.outlier_gate)
        features[obs[bad]] = -1
        self.rejected += int(bad.sum())

    def check_unmapped(self, slam: FilterState, r: F64, b: F64, new: list[int], r_old: F64) -> list[int]:
        """Known ids with the outlier gate on: the readings of unmapped ids that agree with their earlier readings.

        The tentative list of section 3.1, for known ids: every reading of an id that is not
        mapped yet is placed with the localized pose (covariance ``G_X P G_X^T + G_z R G_z^T``);
        a reading whose position is outside the outlier gate of the earlier readings' mean is not
        used (a misread barcode), the others join the mean. The mean's covariance is kept at the
        readings' average, not their fused one, since they share the robot's pose error.
        """
        if self.mode != "known" or self._ids is None or not np.isfinite(self.params.outlier_gate) or not new:
            return new
        lm, g_pose, g_z = rangebearing.landmarks_from(slam.pose, r[new], b[new])
        r_cov = rangebearing.blocks(r_old)[new]
        covs = g_pose @ slam.pose_cov @ g_pose.transpose(0, 2, 1) + g_z @ r_cov @ g_z.transpose(0, 2, 1)
        kept = []
        for j, p, c in zip(new, lm, covs, strict=True):
            key = int(self._ids[j])
            info = np.linalg.inv(c)
            if key in self.unmapped:
                vec, mat, count = self.unmapped[key]
                mean = np.linalg.solve(mat, vec)
                d = p - mean
                if float(d @ np.linalg.solve(c + count * np.linalg.inv(mat), d)) > self.params.outlier_gate:
                    self.rejected += 1
                    continue
                self.unmapped[key] = (vec + info @ p, mat + info, count + 1)
            else:
                self.unmapped[key] = (info @ p, info, 1)
            kept.append(j)
        return kept

    def confirm(self, slam: FilterState, r: F64, b: F64, assoc: Association, r_old: F64
                ) -> tuple[list[int], I64]:
        """The observations to map as new features now, and the tentative entry of each observation.

        Known ids: every observation of an unmapped id. Unknown ids: observations far from every
        mapped feature go to the tentative list (placed with the localized pose); those whose
        entry reaches the confirmation count are returned.
        """
        m = len(r)
        tentative = np.full(m, -1, dtype=np.int64)
        obs = list(assoc.candidates_new)
        if self.mode == "known" or not obs:
            return (obs if self.mode == "known" else []), tentative
        lm, g_pose, g_z = rangebearing.landmarks_from(slam.pose, r[obs], b[obs])
        r_cov = rangebearing.blocks(r_old)[obs]
        covs = g_pose @ slam.pose_cov @ g_pose.transpose(0, 2, 1) + g_z @ r_cov @ g_z.transpose(0, 2, 1)
        self.tentative.prune(slam.scans, self.params)
        index, confirmed = self.tentative.observe(lm, covs, slam.scans, self.params)
        tentative[obs] = index
        return [j for j, ok in zip(obs, confirmed.tolist(), strict=True) if ok], tentative

    def commit(self, features: I64, tentative: I64, ids: I64 | None = None) -> None:
        """Record the scan's outcome: ids of new features; tentative entries that joined the map.

        ``ids``: the landmark id of each entry of ``features`` when not the current scan's (composite scans).
        """
        if self.mode == "known":
            ids = ids if ids is not None else self._ids
            if ids is not None:
                for j in np.flatnonzero(features >= 0).tolist():
                    self.by_id.setdefault(int(ids[j]), int(features[j]))
                    self.unmapped.pop(int(ids[j]), None)
            return
        mapped = [int(tentative[j]) for j in range(len(features)) if features[j] >= 0 and tentative[j] >= 0]
        if mapped:
            self.tentative.remove(mapped)
