"""EKF-SLAM, the "traditional SLAM" D-SLAM is compared with ([1]_ section 4, after [2]_).

One Extended Kalman Filter over the robot pose and every landmark position,
``x = [x_r, y_r, phi_r, x_1, y_1, ..., x_N, y_N]`` with a dense covariance P, in the initial robot
frame (the robot starts exactly at the origin, P = 0). It uses the same inputs, noise models and
association modes as :class:`slamreplay.algorithms.dslam.DSlam`:

- prediction per odometry increment (:mod:`slamreplay.algorithms.common.motion`): O(N) (robot rows of P);
- update per scan with all associated range-bearing observations at once
  (:mod:`slamreplay.algorithms.common.rangebearing`), ``K = P H^T S^-1``, ``P -= K S K^T``: O(N^2);
- new landmarks by augmentation from the updated pose, with their full cross-covariances;
- known ids, or unknown ids by maximum likelihood with gating on the exact innovation
  covariance (robot-landmark correlation included) and the confirmed/tentative lists of
  :mod:`slamreplay.algorithms.common.association`.

``jacobians = "first_estimates"`` is the first-estimates-Jacobian EKF (FEJ-EKF) of [3]_, the
consistent baseline: the standard EKF linearises each step at the latest estimates, so the
linearised system gains information along the global rotation, which no measurement carries
(the map's orientation is held by the known start alone), and becomes overconfident. FEJ keeps
the unobservable directions of the nonlinear system: the propagation Jacobian's position-heading
block is ``J (p_{k+1|k} - p_{k|k-1})`` (the propagated, not the updated, previous position) and
the measurement Jacobians are evaluated at the propagated robot pose and at each landmark's
first estimate (its position when it was added). Innovations still use the latest estimates.

References
----------
.. [1] Z. Wang, S. Huang, G. Dissanayake, "Implementation issues and experimental evaluation
   of D-SLAM", FSR 2005.
.. [2] G. Dissanayake et al., "A solution to the simultaneous localization and map building
   (SLAM) problem", IEEE TRA 17:229-241, 2001.
.. [3] G. P. Huang, A. I. Mourikis, S. I. Roumeliotis, "Observability-based rules for designing
   consistent EKF SLAM estimators", IJRR 29(5):502-528, 2010 (FEJ-EKF, section 5).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
import scipy.linalg as sla
from numpy.typing import ArrayLike, NDArray

from slamreplay.algorithms.common import motion, rangebearing
from slamreplay.algorithms.common.association import (
    AssociationConfig,
    TentativeList,
    innovation_covariance,
    mahalanobis,
    match,
    outliers,
)
from slamreplay.algorithms.common.motion import OdometryNoise
from slamreplay.algorithms.common.se2 import wrap_angle
from slamreplay.algorithms.observe import NULL_OBSERVER, Observer

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]
ROW_CHUNK = 1024  # rows of P updated per matrix product: bounds the temporary memory


def symmetrise(p: F64, tile: int = 512) -> None:
    """``p[:] = (p + p^T) / 2`` in place, tile by tile (no full-size temporary, cache-friendly transposes)."""
    n = len(p)
    for i0 in range(0, n, tile):
        i1 = min(n, i0 + tile)
        d = p[i0:i1, i0:i1]
        d[...] = 0.5 * (d + d.T)
        for j0 in range(i1, n, tile):
            j1 = min(n, j0 + tile)
            upper = 0.5 * (p[i0:i1, j0:j1] + p[j0:j1, i0:i1].T)
            p[i0:i1, j0:j1] = upper
            p[j0:j1, i0:i1] = upper.T


@dataclass(frozen=True, slots=True)
class EkfSlamConfig:
    """Parameters shared with D-SLAM (same meaning, same defaults)."""

    odometry_noise: OdometryNoise = field(default_factory=OdometryNoise)
    default_range_sigma_m: float = 0.1
    default_bearing_sigma_rad: float = 0.02
    association: Literal["known", "unknown"] = "known"
    association_params: AssociationConfig = field(default_factory=AssociationConfig)
    vicinity_margin_m: float = 1.0
    jacobians: Literal["standard", "first_estimates"] = "standard"  # module docstring: FEJ-EKF [3]

    def __post_init__(self) -> None:
        if not (self.default_range_sigma_m > 0 and self.default_bearing_sigma_rad > 0):
            raise ValueError("default_range_sigma_m and default_bearing_sigma_rad must be > 0")
        if self.jacobians not in ("standard", "first_estimates"):
            raise ValueError(f"jacobians must be 'standard' or 'first_estimates', got {self.jacobians!r}")
        if self.association not in ("known", "unknown"):
            raise ValueError(f"association must be 'known' or 'unknown', got {self.association!r}")


@dataclass(frozen=True, slots=True)
class EkfScanResult:
    """One scan: the prediction, the updated pose, the landmark (or tentative entry) of each observation."""

    prediction: F64
    prediction_cov: F64
    pose: F64
    pose_cov: F64
    features: I64  # (m,) landmark index per observation after the scan, -1 for none
    tentative: I64  # (m,) tentative entry (unknown ids), -1 for none
    new_features: tuple[int, ...]
    nis: float  # normalised innovation squared of the update (nan without one)


class EkfSlam:
    """Full EKF-SLAM (module docstring). ``capacity`` preallocates P for that many landmarks."""

    def __init__(self, config: EkfSlamConfig = EkfSlamConfig(), observer: Observer = NULL_OBSERVER,
                 clock: Callable[[], float] | None = None, capacity: int = 64) -> None:
        self.config = config
        self.observer = observer
        self.dim = 3
        self._x = np.zeros(3 + 2 * capacity)
        self._p = np.zeros((3 + 2 * capacity, 3 + 2 * capacity))
        self._fej = config.jacobians == "first_estimates"
        self._first = np.zeros(2 * capacity)  # FEJ: each landmark's position when it was added
        self._propagated = np.zeros(3)  # FEJ: the last propagated pose p_{k|k-1} (the start before any)
        self.feature_ids: list[int] = []
        self.by_id: dict[int, int] = {}
        self.tentative = TentativeList()
        self.scans = 0
        self.max_range = 0.0
        self.rejected = 0  # known-id observations rejected as outliers
        self._clock = clock
        self.profile: dict[str, list[float]] = {}

    @property
    def n(self) -> int:
        return (self.dim - 3) // 2

    @property
    def x(self) -> F64:
        """The state (3 + 2N,), a view."""
        return self._x[: self.dim]

    @property
    def P(self) -> F64:
        """The covariance (3 + 2N, 3 + 2N), a view."""
        return self._p[: self.dim, : self.dim]

    @property
    def pose(self) -> F64:
        return self._x[:3].copy()

    @property
    def pose_cov(self) -> F64:
        return self._p[:3, :3].copy()

    def estimates(self) -> F64:
        """Landmark estimates (N, 2) in the map frame."""
        return self.x[3:].reshape(-1, 2).copy()

    def marginal_covariances(self) -> F64:
        """Landmark marginal covariances (N, 2, 2)."""
        idx = 3 + 2 * np.arange(self.n)
        p = self.P
        return np.stack([np.stack([p[idx, idx], p[idx, idx + 1]], -1), np.stack([p[idx + 1, idx], p[idx + 1, idx + 1]],
                                                                                 -1)], -2)

    def _timed(self, stage: str, tic: float) -> None:
        if self._clock is not None:
            self.profile.setdefault(stage, []).append(self._clock() - tic)

    def predict(self, increment: ArrayLike) -> None:
        """Propagate the robot by one odometry increment; the robot rows of P by F (O(N))."""
        tic = self._clock() if self._clock else 0.0
        u = motion.check_increment(increment)
        q = self.config.odometry_noise.covariance(u)
        pose, p_rr, f = motion.predict(self._x[:3], self._p[:3, :3], u, q)
        if self._fej:  # [3] section 5: J (p_{k+1|k} - p_{k|k-1}), not J (p_{k+1|k} - p_{k|k})
            f = np.array(f)
            f[0, 2], f[1, 2] = -(pose[1] - self._propagated[1]), pose[0] - self._propagated[0]
            c, s = math.cos(self._x[2]), math.sin(self._x[2])
            g = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
            p_rr = f @ self._p[:3, :3] @ f.T + g @ q @ g.T
            p_rr = 0.5 * (p_rr + p_rr.T)
            self._propagated = pose.copy()
        self._x[:3] = pose
        p = self.P
        cross = f @ p[:3, 3:]
        p[:3, 3:] = cross
        p[3:, :3] = cross.T
        p[:3, :3] = p_rr
        self._timed("predict", tic)

    def _grow(self, k: int) -> None:
        need = self.dim + 2 * k
        if need > len(self._x):
            cap = max(need, int(1.5 * len(self._x)))
            x, p, first = np.zeros(cap), np.zeros((cap, cap)), np.zeros(cap)
            x[: self.dim] = self.x
            p[: self.dim, : self.dim] = self.P
            first[: self.dim - 3] = self._first[: self.dim - 3]
            self._x, self._p, self._first = x, p, first

    def observe(self, ranges: ArrayLike, bearings: ArrayLike, ids: ArrayLike | None = None,
                range_sigma: float = 0.0, bearing_sigma: float = 0.0) -> EkfScanResult:
        """Associate, update and augment with one scan (same arguments and errors as ``DSlam.observe``)."""
        r, b = rangebearing.check_scan(ranges, bearings)
        sr, sb = rangebearing.scan_sigmas(range_sigma, bearing_sigma, self.config.default_range_sigma_m,
                                          self.config.default_bearing_sigma_rad)
        ids_arr = self._check_ids(ids, len(r))
        self.scans += 1
        m = len(r)
        if m:
            self.max_range = max(self.max_range, float(r.max()))
        pred, pred_cov = self.pose, self.pose_cov
        r_cov = np.diag([sr**2, sb**2])
        tic = self._clock() if self._clock else 0.0
        features, new = self._associate(r, b, ids_arr, r_cov)
        self._timed("associate", tic)
        tic = self._clock() if self._clock else 0.0
        nis = self._update(r, b, features, r_cov) if np.any(features >= 0) else math.nan
        tentative = np.full(m, -1, dtype=np.int64)
        if self.config.association == "unknown" and new:
            new, tentative = self._tentative(r, b, new, r_cov)
        created = self._augment(r[new], b[new], r_cov) if new else []
        for j, f in zip(new, created, strict=True):
            features[j] = f
            self.feature_ids.append(int(ids_arr[j]) if ids_arr is not None else -1)
            if ids_arr is not None:
                self.by_id[int(ids_arr[j])] = f
        if self.config.association == "unknown":
            mapped = [int(tentative[j]) for j in new if tentative[j] >= 0]
            if mapped:
                self.tentative.remove(mapped)
        self._timed("update", tic)
        return EkfScanResult(pred, pred_cov, self.pose, self.pose_cov, features, tentative, tuple(created), nis)

    def _check_ids(self, ids: ArrayLike | None, m: int) -> I64 | None:
        if self.config.association != "known":
            return None
        if ids is None:
            raise ValueError("ids are required in known-id association mode (use association='unknown')")
        arr = np.asarray(ids, dtype=np.int64).reshape(-1)
        if arr.shape != (m,) or np.any(arr < 0):
            raise ValueError(f"ids must be ({m},) and all >= 0 in known-id association mode")
        return arr

    def _associate(self, r: F64, b: F64, ids: I64 | None, r_cov: F64) -> tuple[I64, list[int]]:
        m = len(r)
        features = np.full(m, -1, dtype=np.int64)
        if ids is not None:
            seen: set[int] = set()
            new = []
            for j, i in enumerate(ids.tolist()):
                if i not in seen:
                    seen.add(i)
                    f = self.by_id.get(i)
                    if f is None:
                        new.append(j)
                    else:
                        features[j] = f
            obs = np.flatnonzero(features >= 0)
            if len(obs) and np.isfinite(self.config.association_params.outlier_gate):
                z_pred, s = self._predicted(features[obs], r_cov)
                bad = outliers(np.stack([r[obs], b[obs]], -1), z_pred, s, self.config.association_params.outlier_gate)
                features[obs[bad]] = -1
                self.rejected += int(bad.sum())
            return features, new
        if self.n == 0:
            return features, list(range(m))
        pose, p = self._x[:3], self.P
        spread = 3.0 * float(np.sqrt(max(np.linalg.eigvalsh(p[:2, :2]).max(), 0.0)))
        lms = self.x[3:].reshape(-1, 2)
        cand = np.flatnonzero(np.hypot(*(lms - pose[:2]).T) <= self.max_range + self.config.vicinity_margin_m + spread)
        if not len(cand):
            return features, list(range(m))
        z_pred, s = self._predicted(cand, r_cov)
        d2 = mahalanobis(np.stack([r, b], -1), z_pred, s)
        assigned, far = match(d2, np.linalg.slogdet(s)[1], self.config.association_params.gate,
                              self.config.association_params.new_gate)
        ok = assigned >= 0
        features[ok] = cand[assigned[ok]]
        return features, np.flatnonzero(far).tolist()

    def _measurement_model(self, landmarks: I64) -> tuple[F64, F64, F64]:
        """Predicted measurements (k, 2) of landmarks from the latest estimates, and the Jacobians
        (k, 2, 3), (k, 2, 2): at the latest estimates, or (FEJ) at the propagated pose and the first estimates."""
        z_pred, h_r, h_l = rangebearing.predict(self._x[:3], self.x[3:].reshape(-1, 2)[landmarks])
        if self._fej:
            first = self._first[: self.dim - 3].reshape(-1, 2)[landmarks]
            _, h_r, h_l = rangebearing.predict(self._propagated, first)
        return z_pred, h_r, h_l

    def _predicted(self, landmarks: I64, r_cov: F64) -> tuple[F64, F64]:
        """Predicted measurements (k, 2) of landmarks and their exact innovation covariances (k, 2, 2)."""
        p = self.P
        z_pred, h_r, h_l = self._measurement_model(landmarks)
        rows = 3 + 2 * landmarks
        p_rl = np.stack([p[:3, rows], p[:3, rows + 1]], -1).transpose(1, 0, 2)  # (k, 3, 2)
        p_ll = np.stack([np.stack([p[rows, rows], p[rows, rows + 1]], -1),
                         np.stack([p[rows + 1, rows], p[rows + 1, rows + 1]], -1)], -2)
        return z_pred, innovation_covariance(h_r, p[:3, :3], h_l, p_ll, r_cov, p_rl)

    def _update(self, r: F64, b: F64, features: I64, r_cov: F64) -> float:
        """One EKF update with every associated observation; returns the NIS."""
        obs = np.flatnonzero(features >= 0)
        f = features[obs]
        k = len(obs)
        z_pred, h_r, h_l = self._measurement_model(f)
        cols = np.concatenate([[0, 1, 2], np.stack([3 + 2 * f, 4 + 2 * f], -1).reshape(-1)])
        h = np.zeros((2 * k, len(cols)))
        h[:, :3] = h_r.reshape(2 * k, 3)
        for j in range(k):
            h[2 * j:2 * j + 2, 3 + 2 * j:5 + 2 * j] = h_l[j]
        nu = np.stack([r[obs], b[obs]], -1).reshape(-1) - z_pred.reshape(-1)
        nu[1::2] = wrap_angle(nu[1::2])
        p = self.P
        pht = p[:, cols] @ h.T  # (dim, 2k)
        s = h @ pht[cols] + sla.block_diag(*([r_cov] * k))
        chol = sla.cho_factor(0.5 * (s + s.T))
        gain = sla.cho_solve(chol, pht.T).T  # K = P H^T S^-1
        self._x[: self.dim] += gain @ nu
        self._x[2] = wrap_angle(self._x[2])
        for i0 in range(0, self.dim, ROW_CHUNK):
            p[i0:i0 + ROW_CHUNK] -= gain[i0:i0 + ROW_CHUNK] @ pht.T  # P -= K S K^T = K (P H^T)^T
        symmetrise(p)
        return float(nu @ sla.cho_solve(chol, nu))

    def _tentative(self, r: F64, b: F64, obs: list[int], r_cov: F64) -> tuple[list[int], I64]:
        lm, g_pose, g_z = rangebearing.landmarks_from(self._x[:3], r[obs], b[obs])
        covs = g_pose @ self._p[:3, :3] @ g_pose.transpose(0, 2, 1) + g_z @ r_cov @ g_z.transpose(0, 2, 1)
        params = self.config.association_params
        self.tentative.prune(self.scans, params)
        index, confirmed = self.tentative.observe(lm, covs, self.scans, params)
        tentative = np.full(len(r), -1, dtype=np.int64)
        tentative[obs] = index
        return [j for j, ok in zip(obs, confirmed.tolist(), strict=True) if ok], tentative

    def _augment(self, r: F64, b: F64, r_cov: F64) -> list[int]:
        """Add landmarks from the current pose with their cross-covariances (standard augmentation)."""
        k = len(r)
        lm, g_pose, g_z = rangebearing.landmarks_from(self._x[:3], r, b)
        self._grow(k)
        old = self.dim
        self.dim += 2 * k
        gr = g_pose.reshape(2 * k, 3)
        p = self.P
        cross = gr @ p[:3, :old]
        p[old:, :old] = cross
        p[:old, old:] = cross.T
        p[old:, old:] = gr @ p[:3, :3] @ gr.T + sla.block_diag(*(g @ r_cov @ g.T for g in g_z))
        self._x[old:self.dim] = lm.reshape(-1)
        self._first[old - 3:self.dim - 3] = lm.reshape(-1)
        return list(range((old - 3) // 2, self.n))
