"""D-SLAM [1]_: decoupled EIF mapping of absolute feature positions and CI localization.

Per odometry increment, :meth:`DSlam.predict` propagates the robot estimate (the process model
of :mod:`slamreplay.algorithms.common.motion`). Per scan, :meth:`DSlam.observe`

1. associates the observations with mapped features (known ids, or maximum likelihood with
   gating and the confirmed/tentative lists, section 3.1);
2. phase I (the robot has not moved, its pose is exactly the map origin): initialises and
   updates features from the original range-bearing measurements;
3. phase II: localizes (section 2.3) from the odometry prediction and the measurement estimate
   (eq. 12), fused by Covariance Intersection; then, with at least two mapped features f_1, f_2
   in the scan, recasts the scan (eqs. 3-4), initialises new features by eq. (9) and updates
   the information matrix and vector by eq. (10) with ``z_map`` only; a scan with fewer than
   two mapped features goes to localization only;
4. recovers the state (sections 3.2-3.3) without inverting I, and carries the joint covariance
   of the features near the robot in covariance form (:mod:`slamreplay.algorithms.dslam.covariance`).

Every measurement the map used is also summarised (:mod:`slamreplay.algorithms.dslam.relinearize`: an exact
sufficient statistic of O(N) size, whatever the run's length): at the end of a run,
:meth:`DSlam.finalize` relinearises them all at the final estimate (not in the paper;
``final_relinearization_iterations = 0`` keeps the EIF estimate ``I^-1 i`` and no summary).

Cost per scan: everything above works on the scan's features, the features near the robot and
their neighbours in I, so a scan costs the same whatever the map size N, except for the
fallbacks: a global PCG or direct solve when the local recovery is not enough, and an exact
recomputation of the vicinity covariance (O(N) each) when a scan sees fewer than two features
of the vicinity set.

Localization uses the map as it was before this scan's update, so ``z_loc`` and the map
estimate it is compared with are independent.

References
----------
.. [1] Z. Wang, S. Huang, G. Dissanayake, "Implementation issues and experimental evaluation
   of D-SLAM", FSR 2005.
"""

from __future__ import annotations

import enum
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from slamreplay.algorithms.common import motion, rangebearing
from slamreplay.algorithms.common.association import AssociationConfig
from slamreplay.algorithms.common.ci import Criterion, covariance_intersection
from slamreplay.algorithms.common.motion import OdometryNoise
from slamreplay.algorithms.common.se2 import wrap_angle
from slamreplay.algorithms.dslam import mapping
from slamreplay.algorithms.dslam.associate import Associator
from slamreplay.algorithms.dslam.composite import CompositeScan
from slamreplay.algorithms.dslam.covariance import CovarianceCache, RefreshReport
from slamreplay.algorithms.dslam.information import InformationMatrix, dofs
from slamreplay.algorithms.dslam.localization import MeasurementPose, PoseStatus, chi2_quantile, measurement_pose
from slamreplay.algorithms.dslam.recast import Recast, angle_rows, init_features, map_invariants, recast
from slamreplay.algorithms.dslam.recovery import Recovery, RecoveryReport, factor
from slamreplay.algorithms.dslam.relinearize import MeasurementLog, relinearize
from slamreplay.algorithms.dslam.spatial import Grid
from slamreplay.algorithms.observe import NULL_OBSERVER, Observer, Scalar, Text

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]


@dataclass(frozen=True, slots=True)
class DSlamConfig:
    """Parameters of D-SLAM; the docstrings of the modules named say what each one does."""

    odometry_noise: OdometryNoise = field(default_factory=OdometryNoise)  # motion
    default_range_sigma_m: float = 0.1  # when a scan states no sigma
    default_bearing_sigma_rad: float = 0.02
    association: Literal["known", "unknown"] = "known"
    association_params: AssociationConfig = field(default_factory=AssociationConfig)
    ci_criterion: Criterion = "det"  # ci
    localization_gate_probability: float = 0.9999  # localization; also gates measurement vs prediction
    map_gate_probability: float = 0.9999  # a recast update whose z_map innovation fails this gate is skipped
    recovery: Literal["local", "pcg", "direct"] = "local"  # recovery.Recovery
    recovery_tol_m: float = 1e-5  # PCG stops when no feature's error estimate exceeds this
    local_tol_m: float = 1e-3  # a local recovery is accepted when no feature's error estimate exceeds this
    local_max_hops: int = 20  # growth rounds of the local region
    pcg_max_iterations: int = 1000
    global_every_scans: int = 100  # a global two-level PCG every this many updates (0: only when needed)
    covariance_rtol: float = 1e-4  # covariance
    covariance_refresh_scans: int = 0  # exact recomputation of the vicinity covariance (0: only when needed)
    vicinity_margin_m: float = 2.0  # V keeps features within the largest range seen so far plus this margin
    loop_closure_gap_scans: int = 300  # a mapped feature unseen for this long closes a loop
    final_relinearization_iterations: int = 10  # relinearize: Gauss-Newton steps at finalize (0: the EIF estimate)
    composite_max_scans: int = 0  # composite: scans a reading may wait in the window (0: off, the paper's rule)
    composite_max_distance_m: float = 3.0  # composite: readings taken more than this much travel ago are dropped
    composite_max_heading_sigma_rad: float = 0.4  # composite: ... or odometry heading sigma accrued since

    def __post_init__(self) -> None:
        positive = ("default_range_sigma_m", "default_bearing_sigma_rad", "recovery_tol_m", "local_tol_m",
                    "covariance_rtol")
        for name in positive:
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)}")
        for name in ("local_max_hops", "pcg_max_iterations", "loop_closure_gap_scans"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        for name in ("composite_max_distance_m", "composite_max_heading_sigma_rad"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)}")
        for name in ("global_every_scans", "covariance_refresh_scans", "final_relinearization_iterations",
                     "composite_max_scans"):
            if getattr(self, name) < 0:
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)}")
        if self.association not in ("known", "unknown"):
            raise ValueError(f"association must be 'known' or 'unknown', got {self.association!r}")
        if self.recovery not in ("local", "pcg", "direct"):
            raise ValueError(f"recovery must be 'local', 'pcg' or 'direct', got {self.recovery!r}")
        for name in ("localization_gate_probability", "map_gate_probability"):
            if not 0 < getattr(self, name) <= 1:
                raise ValueError(f"{name} must be in (0, 1], got {getattr(self, name)}")


class ScanStatus(enum.Enum):
    EMPTY = "empty"  # no observations
    PHASE_I = "phase_i"  # robot at its initial pose: direct feature updates
    BOOTSTRAP = "bootstrap"  # phase II with fewer than two mapped features (mapping.bootstrap_increment)
    MAPPED = "mapped"  # phase II: localized, recast, eqs. (9)-(10)
    LOCALIZATION_ONLY = "localization_only"  # fewer than two mapped features observed
    MAP_REJECTED = "map_rejected"  # the recast innovation of the mapped features failed the map gate


@dataclass(frozen=True, slots=True)
class ScanResult:
    """Everything one scan did, in the map frame (the initial robot frame)."""

    status: ScanStatus
    prediction: F64  # (3,) odometry prediction and its covariance (3, 3)
    prediction_cov: F64
    measurement: MeasurementPose | None  # eq. (12) estimate, None without two mapped features
    omega: float | None  # CI weight of the prediction; None when nothing was fused
    pose: F64  # (3,) the localization result and its covariance
    pose_cov: F64
    features: I64  # (m,) mapped feature of each observation after this scan, -1 for none
    tentative: I64  # (m,) tentative-list entry of each observation (unknown ids), -1 for none
    anchors: tuple[int, int] | None  # f_1, f_2 of the recast measurement
    new_features: tuple[int, ...]
    loop_closure: bool
    recovery: RecoveryReport | None
    covariance: RefreshReport | None  # when the vicinity covariance was recomputed exactly
    note: str = ""


class DSlam:
    """D-SLAM with absolute map (module docstring); the map frame is the initial robot frame.

    ``clock`` (e.g. ``time.perf_counter``), when given, times the stages into ``profile``
    (seconds per call, by stage); results never depend on it.
    """

    def __init__(self, config: DSlamConfig = DSlamConfig(), observer: Observer = NULL_OBSERVER,
                 clock: Callable[[], float] | None = None) -> None:
        self.config = config
        self.observer = observer
        self.info = InformationMatrix()
        self.recovery = self._new_recovery()
        self.map_log = MeasurementLog()  # every measurement of eq. (10), summarised, for the final relinearisation
        self._log = config.final_relinearization_iterations > 0
        self.covariance = CovarianceCache()
        self.pose = np.zeros(3)
        self.pose_cov = np.zeros((3, 3))
        self.moved = False
        self.scans = 0
        self.feature_ids: list[int] = []  # the scan's landmark id of each feature (known ids), else -1
        self.last_seen: list[int] = []
        self.max_range = 0.0
        self.associator = Associator(config.association, config.association_params)
        self.window: CompositeScan | None = None  # known ids only: composite scans (composite.py)
        if config.composite_max_scans and config.association == "known":
            self.window = CompositeScan(config.composite_max_scans, config.composite_max_distance_m,
                                        config.composite_max_heading_sigma_rad)
        self._recast: tuple[list[int], int, Recast] | None = None  # set by _map_outlier for _map
        self._refresh: RefreshReport | None = None
        self._grid: Grid | None = None  # built at the first spatial query
        self._clock = clock
        self.profile: dict[str, list[float]] = {}

    def _new_recovery(self) -> Recovery:
        c = self.config
        return Recovery(self.info, c.recovery, c.recovery_tol_m, c.local_tol_m, c.local_max_hops,
                        c.pcg_max_iterations, c.global_every_scans)

    @property
    def n(self) -> int:
        """Mapped features."""
        return self.info.n

    @property
    def rejected(self) -> int:
        """Known-id observations rejected by the outlier gate so far."""
        return self.associator.rejected

    def estimates(self) -> F64:
        """Current feature estimates (N, 2) in the map frame."""
        return self.recovery.x.reshape(-1, 2).copy()

    def _tic(self) -> float:
        return self._clock() if self._clock is not None else 0.0

    def _toc(self, stage: str, tic: float) -> None:
        if self._clock is not None:
            self.profile.setdefault(stage, []).append(self._clock() - tic)

    def predict(self, increment: ArrayLike) -> None:
        """Propagate the robot estimate by one odometry increment ``[dx, dy, dtheta]`` (robot frame)."""
        u = motion.check_increment(increment)
        if np.any(u != 0.0):
            self.moved = True
        q = self.config.odometry_noise.covariance(u)
        self.pose, self.pose_cov, _ = motion.predict(self.pose, self.pose_cov, u, q)
        if self.window is not None:
            self.window.move(u, q)

    def _sigmas(self, range_sigma: float, bearing_sigma: float) -> tuple[float, float]:
        return rangebearing.scan_sigmas(range_sigma, bearing_sigma, self.config.default_range_sigma_m,
                                        self.config.default_bearing_sigma_rad)

    def within(self, position: F64, radius: float) -> list[int]:
        """Mapped features whose estimate is within ``radius`` of ``position`` (2,) (a grid: O(1) in N)."""
        if self.n == 0:
            return []
        x = self.recovery.x.reshape(-1, 2)
        if self._grid is None:
            self._grid = Grid(max(1.0, self.max_range))
            self._grid.rebuild(x)
        return self._grid.near(position, radius, x)

    def _refile(self) -> None:
        """Keep the grid in step with the estimates the last recovery moved."""
        if self._grid is None:
            return
        changed = self.recovery.changed
        x = self.recovery.x.reshape(-1, 2)
        if changed is None:
            self._grid.rebuild(x)
        elif changed:
            self._grid.file(changed, x[changed])

    def vicinity(self, position: F64) -> list[int]:
        """Mapped features within the largest range seen so far plus the margin of ``position`` (2,)."""
        return self.within(position, self.vicinity_radius)

    @property
    def vicinity_radius(self) -> float:
        """The largest range seen so far plus the margin (m)."""
        return self.max_range + self.config.vicinity_margin_m

    def ensure_covariance(self, needed: list[int]) -> RefreshReport | None:
        """Recompute the vicinity covariance exactly when V holds fewer than two of ``needed``, or periodically.

        The period is ``covariance_refresh_scans`` (0: never). The new V is the old one plus ``needed``.
        """
        cov = self.covariance
        period = self.config.covariance_refresh_scans
        inside = sum(f in cov.position for f in needed)
        if inside >= min(2, len(needed)) and not (period and self.scans - cov.scan >= period):
            return None
        tic = self._tic()
        features = sorted(set(needed) | set(cov.features))
        report = cov.refresh(self.info, self.recovery.inv_blocks, features, self.scans,
                             self.config.covariance_rtol, self.config.pcg_max_iterations, self.recovery.x)
        self._toc("covariance", tic)
        self._refresh = report
        self.observer.log("dslam/covariance/pcg_iterations", Scalar(report.iterations))
        return report

    def _leave(self) -> None:
        """Marginalise out of V the features farther than the vicinity radius from the robot. O(|V|)."""
        cov = self.covariance
        if not cov.features:
            return
        feats = np.asarray(cov.features, dtype=np.int64)
        d = np.hypot(*(self.recovery.x.reshape(-1, 2)[feats] - self.pose[:2]).T)
        far = feats[d > self.vicinity_radius]
        if len(far):
            cov.drop(far.tolist())

    def observe(self, ranges: ArrayLike, bearings: ArrayLike, ids: ArrayLike | None = None,
                range_sigma: float = 0.0, bearing_sigma: float = 0.0) -> ScanResult:
        """Process one scan: ranges (m,) metres, bearings (m,) radians, ids (m,) landmark ids (known mode).

        Sigmas of 0 mean "not stated": the config's defaults apply. Raises ValueError for NaN or
        negative ranges, mismatched lengths, or missing ids in known-id mode.
        """
        r, b = rangebearing.check_scan(ranges, bearings)
        sr, sb = self._sigmas(range_sigma, bearing_sigma)
        ids_arr = self.associator.check_ids(ids, len(r))
        r_old = rangebearing.noise(len(r), sr, sb)  # eq. (2)
        self.scans += 1
        m = len(r)
        if m:
            self.max_range = max(self.max_range, float(r.max()))
        pred, pred_cov = self.pose.copy(), self.pose_cov.copy()
        self._refresh = None
        if m == 0:
            return self._result(ScanStatus.EMPTY, pred, pred_cov, np.full(0, -1), np.full(0, -1), note="empty scan")
        tic = self._tic()
        assoc = self.associator.associate(self, r, b, ids_arr, r_old)
        self._toc("associate", tic)
        old = [j for j in range(m) if assoc.features[j] >= 0]
        old_f = [int(assoc.features[j]) for j in old]
        measurement, omega = None, None
        if self.moved and len(old) >= 2:
            tic = self._tic()
            self.ensure_covariance(old_f)
            loc = [j for j in old if int(assoc.features[j]) in self.covariance.position]  # z_loc: features in V
            loc_f = [int(assoc.features[j]) for j in loc]
            measurement = measurement_pose(r[loc], b[loc], r_old[np.ix_(dofs(loc), dofs(loc))],
                                           self.recovery.x.reshape(-1, 2)[loc_f],
                                           self.covariance.block(loc_f), self.config.localization_gate_probability)
            if measurement.status is PoseStatus.OK and not self._agrees(pred, pred_cov, measurement):
                measurement = MeasurementPose(PoseStatus.INCONSISTENT, measurement.pose, measurement.cov,
                                              measurement.chi2, measurement.iterations)
            if measurement.status is PoseStatus.OK:
                jitter = 1e-12 * np.eye(3)
                ci = covariance_intersection(pred, pred_cov + jitter, measurement.pose, measurement.cov,
                                             self.config.ci_criterion, angular=(2,))
                self.pose, self.pose_cov, omega = ci.mean, ci.cov, ci.omega
            self._toc("localize", tic)
        new, tentative = self.associator.confirm(self, r, b, assoc, r_old)
        if self.moved:
            new = self.associator.check_unmapped(self, r, b, new, r_old)
        if self.window is not None and self.moved and self.n >= 2:
            assert ids_arr is not None
            return self._map_composite(r, b, r_old, ids_arr, assoc.features, old + new, pred, pred_cov,
                                       measurement, omega)
        if self.window is not None:
            self.window.clear()
        result = self._map(r, b, r_old, assoc.features, tentative, old, new, pred, pred_cov, measurement, omega)
        self.associator.commit(result.features, tentative)
        return result

    def _map_composite(self, r: F64, b: F64, r_old: F64, ids: I64, features: I64, usable: list[int], pred: F64,
                       pred_cov: F64, measurement: MeasurementPose | None, omega: float | None) -> ScanResult:
        """Phase II with composite scans (composite.py): the scan joins the window, and the window's
        oldest scans are mapped whenever the split rule allows. A window whose oldest scan is beyond
        the limits (composite.py) is mapped whole, or dropped scan by scan when it cannot be, before
        this scan joins.

        ``usable``: the scan's readings of mapped features that passed the outlier gate and of
        unmapped ids. The result's ``features`` refer to this scan's readings.
        """
        window = self.window
        assert window is not None
        by_id = self.associator.by_id
        result: ScanResult | None = None
        while window.expired(self.scans):  # the odometry since the oldest scan is too long to bridge with
            if len(window.keys() & set(by_id)) >= 2:
                result = self._map_window(len(window)) or result  # the window was within its limits until now
            else:
                window.drop_oldest()
        window.add(ids[usable].tolist(), r[usable], b[usable], rangebearing.blocks(r_old)[usable], self.scans)
        while count := window.split(set(by_id)):
            result = self._map_window(count) or result
        scan_features = features.copy()
        for j in usable:
            scan_features[j] = by_id.get(int(ids[j]), -1)
        for j in np.flatnonzero(features >= 0).tolist():  # seen now, whenever its reading is mapped
            self.last_seen[int(features[j])] = self.scans
        if result is None:
            note = (f"scan {self.scans}: fewer than two mapped features in the composite window "
                    f"({len(window)} scan(s)): localization only")
            self.observer.log("dslam/log", Text(note))
            self._leave()
            return self._result(ScanStatus.LOCALIZATION_ONLY, pred, pred_cov, scan_features, np.full(len(r), -1),
                                measurement, omega, note=note)
        return replace(result, pose=self.pose.copy(), pose_cov=self.pose_cov.copy(), prediction=pred,
                       prediction_cov=pred_cov, measurement=measurement, omega=omega, features=scan_features,
                       tentative=np.full(len(r), -1))

    def _map_window(self, count: int) -> ScanResult | None:
        """Map the window's ``count`` oldest scans as one composite scan (eqs. 3-4, 9-10 via :meth:`_map`)."""
        window = self.window
        assert window is not None
        comp = window.take(count, chi2_quantile(self.config.map_gate_probability, 2))
        w_features = np.array([self.associator.by_id.get(int(k), -1) for k in comp.keys], dtype=np.int64)
        w_old = np.flatnonzero(w_features >= 0).tolist()
        if len(w_old) < 2:  # the fusion gate dropped an anchor's readings
            return None
        w_new = np.flatnonzero(w_features < 0).tolist()
        self.ensure_covariance(w_features[w_old].tolist())
        none = np.full(len(comp.keys), -1)
        self.observer.log("dslam/composite/scans", Scalar(comp.scans))
        result = self._map(comp.ranges, comp.bearings, comp.cov, w_features, none, w_old, w_new, self.pose,
                           self.pose_cov, None, None, ids=comp.keys)
        self.associator.commit(result.features, none, ids=comp.keys)
        return result

    def _map(self, r: F64, b: F64, r_old: F64, features: I64, tentative: I64, old: list[int],
             new: list[int], pred: F64, pred_cov: F64, measurement: MeasurementPose | None,
             omega: float | None, ids: I64 | None = None) -> ScanResult:
        """The mapping half of :meth:`observe` (phase I, bootstrap or eqs. 9-10), the recovery, the covariance."""
        r_blocks = rangebearing.blocks(r_old)
        features = features.copy()
        cov = self.covariance
        tic = self._tic()
        anchors: tuple[int, int] | None = None
        created: list[int] = []
        loop = False
        if not self.moved:
            status = ScanStatus.PHASE_I
            created = self._add_features(rangebearing.landmarks_from(np.zeros(3), r[new], b[new])[0], new, features)
            touched = [int(features[j]) for j in old + new]
            jacs = []
            for j in old + new:
                f = int(features[j])
                d_matrix, d_vector, h = mapping.phase_one_terms(self.recovery.x[2 * f:2 * f + 2],
                                                                np.array([r[j], b[j]]), r_blocks[j])
                self._apply([f], d_matrix, d_vector)
                if self._log:
                    self.map_log.phase_one(f, np.array([r[j], b[j]]), r_blocks[j])
                jacs.append(h)
            self._phase_one_covariance(touched, jacs, r_blocks[old + new])
        elif new and self._may_bootstrap(len(old)):
            status = ScanStatus.BOOTSTRAP
            lm, d_matrix, d_vector = mapping.bootstrap_increment(self.pose, self.pose_cov, r[new], b[new],
                                                                 r_old[np.ix_(dofs(new), dofs(new))])
            created = self._add_features(lm, new, features)
            touched = created
            self._apply(created, d_matrix, d_vector)
            if self._log:
                self.map_log.prior(created, d_matrix, d_vector)
            cov.insert(created, np.asarray(np.linalg.inv(d_matrix), dtype=np.float64))
        elif len(old) >= 2 and not self._map_outlier(r, b, r_old, features, old, new):
            status = ScanStatus.MAPPED
            assert self._recast is not None
            order, k_v, rc = self._recast  # anchors first, the scan's features in V, the others, the new ones
            f1, f2 = int(features[order[0]]), int(features[order[1]])
            anchors = (f1, f2)
            x = self.recovery.x.reshape(-1, 2)
            k0 = len(order) - len(new)
            alpha, dist = rc.z_map[2 * k0 - 3::2], rc.z_map[2 * k0 - 2::2]
            pos, _, _ = init_features(x[f1], x[f2], alpha, dist)  # eq. (9)
            created = self._add_features(pos, new, features, ids)
            ordered = [int(features[j]) for j in order]
            d_matrix, d_vector, jac = mapping.recast_terms(self.recovery.x.reshape(-1, 2)[ordered], rc)
            self._apply(ordered, d_matrix, d_vector)
            if self._log:
                self.map_log.recast(ordered, rc.z_map, rc.r_map)
            cov.recast_update(ordered[:k_v], ordered[k_v:], jac, rc.r_map)
            loop = any(self.scans - self.last_seen[int(features[j])] >= self.config.loop_closure_gap_scans
                       for j in old)
            touched = ordered
        else:
            status = ScanStatus.LOCALIZATION_ONLY if len(old) < 2 else ScanStatus.MAP_REJECTED
            touched = []
            for j in new:
                features[j] = -1
        self._toc("update", tic)
        for j in old:
            self.last_seen[int(features[j])] = self.scans
        report = None
        if touched:
            tic = self._tic()
            report = self.recovery.solve(sorted(set(touched)), loop)
            self._refile()
            self._toc("recover", tic)
            self.observer.log("dslam/recovery/cg_iterations", Scalar(report.iterations))
        self._leave()
        note = {ScanStatus.LOCALIZATION_ONLY: f"scan {self.scans}: {len(old)} mapped feature(s) observed, fewer "
                                              f"than two: localization only",
                ScanStatus.MAP_REJECTED: f"scan {self.scans}: the recast measurement disagrees with the map "
                                         f"(map gate): localization only"}.get(status, "")
        if note:
            self.observer.log("dslam/log", Text(note))
        return self._result(status, pred, pred_cov, features, tentative, measurement, omega, anchors,
                            tuple(created), loop, report, note=note)

    def _may_bootstrap(self, seen_mapped: int) -> bool:
        """Whether a moving robot's new features may start from its odometry pose (its scan sees ``seen_mapped``
        mapped features): while fewer than two are mapped (multi.py widens it to each robot's first features)."""
        return self.n < 2

    def _phase_one_covariance(self, features: list[int], jacs: list[F64], r_blocks: F64) -> None:
        """Phase I in covariance form: Kalman update of the features in V, the others join with ``H^-1 R H^-T``.

        The robot is exactly at the origin, so each reading is independent of everything else:
        a feature not in V (new, or one that left V) joins with the covariance of this reading
        alone, uncorrelated with V (exact for a new feature, an upper bound otherwise).
        """
        cov = self.covariance
        inside = [k for k, f in enumerate(features) if f in cov.position]
        if inside:
            k = len(inside)
            jac, r_cov = np.zeros((2 * k, 2 * k)), np.zeros((2 * k, 2 * k))
            for p, q in enumerate(inside):
                jac[2 * p:2 * p + 2, 2 * p:2 * p + 2] = jacs[q]
                r_cov[2 * p:2 * p + 2, 2 * p:2 * p + 2] = r_blocks[q]
            cov.update([features[q] for q in inside], jac, r_cov)
        joining = [k for k, f in enumerate(features) if f not in cov.position]
        if joining:
            k = len(joining)
            block = np.zeros((2 * k, 2 * k))
            for p, q in enumerate(joining):
                h_inv = np.linalg.inv(jacs[q])
                block[2 * p:2 * p + 2, 2 * p:2 * p + 2] = h_inv @ r_blocks[q] @ h_inv.T
            cov.insert([features[q] for q in joining], block)

    def _agrees(self, pred: F64, pred_cov: F64, m: MeasurementPose) -> bool:
        """Whether the measurement pose is within the localization gate of the prediction (3 dof)."""
        d = m.pose - pred
        d[2] = float(wrap_angle(d[2]))
        d2 = float(d @ np.linalg.solve(pred_cov + m.cov, d))
        return d2 <= chi2_quantile(self.config.localization_gate_probability, 3)

    def _map_outlier(self, r: F64, b: F64, r_old: F64, features: I64, old: list[int], new: list[int]) -> bool:
        """Choose the anchors, recast the scan (eqs. 3-4); True when the part in V fails the map gate.

        Only the scan's features in V (at least two, :meth:`ensure_covariance`) have a joint
        covariance; the innovation of their ``z_map`` rows (the first ``2 k_v - 3``) against the
        map estimate has covariance ``H P H^T + R_map`` with P their joint (conservative)
        covariance. The recast, ordered anchors first, then the other features in V, the other
        mapped features, the new ones, is kept in ``self._recast`` for the update.
        """
        cov = self.covariance
        in_v = [j for j in old if int(features[j]) in cov.position]
        in_f = [int(features[j]) for j in in_v]
        points, _ = rangebearing.to_points(r[in_v], b[in_v])
        traces = np.trace(cov.marginals(in_f), axis1=1, axis2=2)
        a1, a2 = mapping.choose_anchors(points, traces)
        ordered_v = [in_v[a1], in_v[a2]] + [j for k, j in enumerate(in_v) if k not in (a1, a2)]
        order = ordered_v + [j for j in old if j not in in_v] + new
        rc = recast(r[order], b[order], r_old[np.ix_(dofs(order), dofs(order))])
        k_v = len(ordered_v)
        self._recast = (order, k_v, rc)
        ordered = [int(features[j]) for j in ordered_v]
        h, jac = map_invariants(self.recovery.x.reshape(-1, 2)[ordered])
        rows_v = 2 * k_v - 3
        nu = rc.z_map[:rows_v] - h
        rows = angle_rows(k_v)
        nu[rows] = wrap_angle(nu[rows])
        s = jac @ cov.block(ordered) @ jac.T + rc.r_map[:rows_v, :rows_v]
        stat = float(nu @ np.linalg.solve(s, nu))
        return stat > chi2_quantile(self.config.map_gate_probability, len(nu))

    def _add_features(self, positions: F64, obs: list[int], features: I64, ids: I64 | None = None) -> list[int]:
        """Append features at ``positions`` for the observations ``obs``; returns their indices.

        ``ids``: the landmark id of each observation when they are not the current scan's (composite).
        """
        if not obs:
            return []
        created: list[int] = self.info.add_features(len(obs)).tolist()
        self.recovery.grow(positions)
        for j, f in zip(obs, created, strict=True):
            features[j] = f
            self.feature_ids.append(int(ids[j]) if ids is not None else self.associator.pending_id(j))
            self.last_seen.append(self.scans)
        return created

    def _apply(self, features: list[int], d_matrix: F64, d_vector: F64) -> None:
        idx = np.asarray(features, dtype=np.int64)
        self.info.add(idx, d_matrix, d_vector)
        self.recovery.record(idx, d_matrix, d_vector)

    def _result(self, status: ScanStatus, pred: F64, pred_cov: F64, features: I64, tentative: I64,
                measurement: MeasurementPose | None = None, omega: float | None = None,
                anchors: tuple[int, int] | None = None, new: tuple[int, ...] = (), loop: bool = False,
                report: RecoveryReport | None = None, note: str = "") -> ScanResult:
        return ScanResult(status, pred, pred_cov, measurement, omega, self.pose.copy(), self.pose_cov.copy(),
                          features, tentative, anchors, new, loop, report, self._refresh, note)

    def finalize(self) -> RecoveryReport:
        """End of the run: the exact EIF estimate ``I^-1 i``, then the relinearised one (module docstring).

        With ``final_relinearization_iterations > 0``, I and i are replaced by every logged
        measurement linearised at the final estimate (:func:`~slamreplay.algorithms.dslam.relinearize.relinearize`),
        so :meth:`estimates` and :meth:`marginal_covariances` describe the relinearised map; the
        report's ``iterations`` are the Gauss-Newton steps and ``error_m`` the last step (m).
        The vicinity covariance is not recomputed.
        """
        if not self.n:
            return RecoveryReport("none", 0, 0, 0.0)
        report = self.recovery.solve_direct()
        iterations = self.config.final_relinearization_iterations
        if not iterations:
            return report
        result = relinearize(self.map_log, self.n, np.array(self.recovery.x), iterations, self.config.recovery_tol_m)
        self.info = result.info
        self.recovery = self._new_recovery()
        self.recovery.grow(result.x.reshape(-1, 2))
        self.recovery.set_state(result.x)
        self._grid = None
        self.observer.log("dslam/relinearization/iterations", Scalar(result.iterations))
        return RecoveryReport("relinearized", result.iterations, 0, result.step_m)

    def marginal_covariances(self) -> F64:
        """Exact marginal covariances (N, 2, 2) of all features, by direct solves I c = e_j (costly: for scoring)."""
        n = self.n
        out = np.empty((n, 2, 2))
        if n == 0:
            return out
        lu = factor(self.info)
        chunk = 256
        for start in range(0, n, chunk):
            f = np.arange(start, min(n, start + chunk))
            e = np.zeros((2 * n, 2 * len(f)))
            e[2 * f, 2 * np.arange(len(f))] = 1.0
            e[2 * f + 1, 2 * np.arange(len(f)) + 1] = 1.0
            cols = lu.solve(e)
            for k, g in enumerate(f.tolist()):
                out[g] = cols[2 * g:2 * g + 2, 2 * k:2 * k + 2]
        return 0.5 * (out + out.transpose(0, 2, 1))
