"""SLSJF as a landmark-SLAM filter: small EKF-SLAM local maps, joined into the sparse global map.

A local map is EKF-SLAM started at the robot's current pose with zero uncertainty in its own frame
([1]_ section III): at that size the EKF's linearization errors stay small and its covariance honest.
It ends after ``local_map_scans`` scans or ``local_map_distance_m`` of driving, whichever comes first;
then its end pose and features, with their covariance, are joined into the global map
(:class:`~slamreplay.algorithms.slsjf.joining.GlobalMap`) and the next local map starts at that end
pose.

Departure, ``local_map_estimate="smoothed"`` (not the default): at its join a local map is re-solved
by least squares over everything its EKF was given (:class:`LocalRecord`: a pose at each scan, the
odometry between them composed with its covariance, each sighting the EKF associated, with its sigmas;
Levenberg-Marquardt from the EKF's estimate, :func:`~slamreplay.algorithms.common.landmark_graph.optimize`)
and joined with the covariance at that optimum. The paper (``"ekf"``, the default) joins the EKF's
estimate and covariance: the EKF linearizes each sighting at the estimate of its moment, so a feature
first seen far off (20 m at 0.05 rad: a metre sideways) is updated about a wrong point, and that error
is frozen into the local map, which I-SLSJF then joins as an exact measurement. Smoothed, a local map
is the maximum-likelihood estimate of its own data, and I-SLSJF's joining of such maps is the batch
optimum of all the measurements to first order. On ``tests/replay/test_landmark_reference.py``'s worlds
(seeds 1, 3, 4) it lands 3, 2 and 98 mm from that optimum, against 31, 120 and 360 mm with the EKF's
local maps (seed 4's measurements have more than one minimum). On MRCLAM, whose sightings are biased and
misread, it helps two robots a lot and hurts two (docs/dslam.md), so it is not the default. The robot
and local map between joins, and the associations, stay the EKF's.

Features are matched across local maps by their ids when the recording has them. Without ids
(``association="unknown"``) the local EKF associates within its local map with its gates, and each
feature it confirms is matched to the global map's features near it (:meth:`Slsjf._associate_new`:
the same maximum-likelihood assignment and gates, the innovation's covariance adding the global
map's covariance of the start frame and of the candidate). Either way a matched feature whose local
estimate is outside the outlier gate of its global estimate is left out of the join
(:meth:`Slsjf._common`); with three or more matched features the gate is taken against the start
frame fitted to all of them, so a start frame that is itself off does not disconnect its local map.

Between joins the robot's estimate in the paper is the global pose of the current local map's start
frame composed with the local map's robot estimate; its covariance adds the start frame's marginal
covariance (from the global information matrix) and the local one, independent of it because the
local map starts with zero uncertainty ([1]_ eq. 13): ``robot_estimate="composed"``. A feature not
yet joined is drawn the same way; one already in the global map keeps its global estimate until the
local map that saw it again is joined. That robot sees the global map only at joins: between them it
drifts on its local map alone, and where sightings are sparse (MRCLAM: one landmark every few
seconds) a local map holds little to hold it.

Departure, ``robot_estimate="joined"`` (the default): the robot as joining the current local map now
would place it. The local map (its robot and the features the global map also holds, the rest
marginalized out) and the global map's marginal over its start frame and those features are
independent, so their maximum-likelihood fusion (:func:`fuse_local_map`, the join's measurement model
of [1]_ eqs. 5-7 on that marginal) is exact to first order; with no common feature it is the
composition. The global map's covariance columns it needs are solved once per local map.

Alternative, ``robot_estimate="tracked"``: a pose filter in the global frame, predicted by odometry,
updated at every scan by the sightings of features already in the global map (their joint covariance
from the global information matrix added to the sensor noise) and fused with the composed estimate;
both fusions are Covariance Intersection
(:func:`~slamreplay.algorithms.common.ci.covariance_intersection_update`), as D-SLAM fuses its robot
with the map ([2]_ section 2.3). Nothing flows back from either: the local maps and the global map are
the paper's, whichever estimate the robot reports.

References
----------
.. [1] S. Huang, Z. Wang, G. Dissanayake, "Sparse local submap joining filter for building large-scale
   maps", IEEE Transactions on Robotics 24(5), 2008.
.. [2] Z. Wang, S. Huang, G. Dissanayake, "Implementation issues and experimental evaluation of D-SLAM",
   FSR 2005.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from slamreplay.algorithms.common import motion, rangebearing, se2
from slamreplay.algorithms.common.association import match
from slamreplay.algorithms.common.ci import covariance_intersection, covariance_intersection_update
from slamreplay.algorithms.common.landmark_graph import LandmarkGraph, LsqConfig, optimize, pose_landmark_covariance
from slamreplay.algorithms.ekfslam import EkfSlam, EkfSlamConfig
from slamreplay.algorithms.observe import NULL_OBSERVER, Observer, Scalar
from slamreplay.algorithms.slsjf.joining import STATE_RECOVERIES, GlobalMap, Linearization, StateRecovery

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]
RobotEstimate = Literal["joined", "tracked", "composed"]
ROBOT_ESTIMATES: tuple[str, ...] = ("joined", "tracked", "composed")
LocalEstimate = Literal["ekf", "smoothed"]
LOCAL_ESTIMATES: tuple[str, ...] = ("ekf", "smoothed")
JOINED_ITERATIONS = 10  # Gauss-Newton iterations at most for the joined robot (it converges in 2-3)
MIN_FIT = 3  # common features from which the gate is taken against a fitted start frame (Slsjf._common)
FLOOR = 1e-12  # m^2, rad^2: added to a covariance that is exactly zero (the start) before a fusion


@dataclass(frozen=True, slots=True)
class SlsjfConfig:
    """The local maps' EKF, when a local map ends, and how the global map is linearized."""

    local: EkfSlamConfig = field(default_factory=EkfSlamConfig)
    local_map_scans: int = 30  # measured: 100 left two MRCLAM robots 5x and 1.7x worse (docs/dslam.md)
    local_map_distance_m: float = 30.0
    linearization: Linearization = "iterated"
    max_iterations: int = 10
    robot_estimate: RobotEstimate = "joined"  # "composed": the paper's (eq. 13); module docstring
    local_map_estimate: LocalEstimate = "ekf"  # "smoothed": the local map re-solved at its join; module docstring
    state_recovery: StateRecovery = "direct"  # "pcg": D-SLAM's preconditioned CG (algorithms/slsjf/recovery.py)

    def __post_init__(self) -> None:
        if self.robot_estimate not in ROBOT_ESTIMATES:
            raise ValueError(f"robot_estimate must be one of {', '.join(ROBOT_ESTIMATES)}, got {self.robot_estimate!r}")
        if self.local_map_estimate not in LOCAL_ESTIMATES:
            raise ValueError(f"local_map_estimate must be one of {', '.join(LOCAL_ESTIMATES)}, "
                             f"got {self.local_map_estimate!r}")
        if self.state_recovery not in STATE_RECOVERIES:
            raise ValueError(f"state_recovery must be one of {', '.join(STATE_RECOVERIES)}, "
                             f"got {self.state_recovery!r}")
        if self.local_map_scans < 1 or not self.local_map_distance_m > 0:
            raise ValueError(f"local_map_scans must be >= 1 and local_map_distance_m > 0, got "
                             f"{self.local_map_scans} and {self.local_map_distance_m}")


@dataclass(frozen=True, slots=True)
class SlsjfScanResult:
    """One scan in the global frame: the prediction, the updated pose, the global feature of each observation."""

    prediction: F64
    prediction_cov: F64
    pose: F64
    pose_cov: F64
    features: I64  # (m,) global feature index per observation, -1 for none
    new_features: tuple[int, ...]
    joined: bool  # whether this scan ended its local map


def compose_jacobians(a: F64, b: F64) -> tuple[F64, F64]:
    """The Jacobians (3, 3) of ``a (+) b`` with respect to ``a`` and to ``b``."""
    c, s = math.cos(a[2]), math.sin(a[2])
    ja = np.array([[1.0, 0.0, -s * b[0] - c * b[1]], [0.0, 1.0, c * b[0] - s * b[1]], [0.0, 0.0, 1.0]])
    jb = np.eye(3)
    jb[:2, :2] = [[c, -s], [s, c]]
    return ja, jb


def compose_cov(a: F64, cov_a: F64, b: F64, cov_b: F64) -> F64:
    """Covariance of ``a (+) b`` for independent ``a`` and ``b`` (first order)."""
    ja, jb = compose_jacobians(a, b)
    return np.asarray(ja @ cov_a @ ja.T + jb @ cov_b @ jb.T, np.float64)


def rotation_t(theta: float) -> tuple[F64, F64]:
    """``R(theta)^T`` and its derivative in theta: the start frame's view of a global point, ``R^T (p - t)``."""
    c, s = math.cos(theta), math.sin(theta)
    return np.array([[c, s], [-s, c]]), np.array([[-s, c], [-c, -s]])


def point_cov(a: F64, cov_a: F64, p: F64, cov_p: F64) -> F64:
    """Covariance (2, 2) of the point ``a (+) p`` for independent pose ``a`` and point ``p``."""
    c, s = math.cos(a[2]), math.sin(a[2])
    ja = np.array([[1.0, 0.0, -s * p[0] - c * p[1]], [0.0, 1.0, c * p[0] - s * p[1]]])
    r = np.array([[c, -s], [s, c]])
    return np.asarray(ja @ cov_a @ ja.T + r @ cov_p @ r.T, np.float64)


def local_feature(x: F64, P: F64, j: int) -> tuple[F64, F64]:
    """Feature ``j``'s estimate (2,) and covariance (2, 2) in an EKF-SLAM state (the pose first, then features)."""
    i = 3 + 2 * j
    return x[i:i + 2], P[i:i + 2, i:i + 2]


def fuse_local_map(glob: F64, glob_cov: F64, local: F64, local_cov: F64,
                   iterations: int = JOINED_ITERATIONS, tolerance: float = 1e-10) -> tuple[F64, F64]:
    """The robot's global pose and covariance from a local map fused with the global map's marginal.

    ``glob`` (3 + 2k,) is the local map's start frame ``s`` and k features ``g`` in the global frame, with their
    joint covariance ``glob_cov`` (from the global information matrix); ``local`` (3 + 2k,) is the local map's
    robot ``t`` and the same k features in its start frame, with their covariance ``local_cov`` (the local EKF's,
    the other local features marginalized out). The two are independent (the local map's sightings are not in
    the global map), so the maximum-likelihood ``(s, g, t)`` minimises

        |(s, g) - glob|^2_{glob_cov^-1} + |(t, R(s)^T (g - s_xy)) - local|^2_{local_cov^-1}

    (the local map's measurement model of [1]_ eqs. 5-7, for its features, and its robot); Gauss-Newton from
    ``(glob, t)``. The robot is ``s (+) t``, its covariance from the joint covariance of ``(s, t)``. With k = 0
    this is the composition of eq. 13.
    """
    y, a = fuse(glob, glob_cov, local, local_cov, iterations, tolerance)
    n = len(glob)
    cov = np.linalg.inv(a)
    s, t = y[:3], y[n:]
    st = np.r_[0, 1, 2, n, n + 1, n + 2]
    jac = np.hstack(compose_jacobians(s, t))  # (s, t) are correlated: their joint covariance, not compose_cov
    pose_cov = jac @ cov[np.ix_(st, st)] @ jac.T
    return se2.compose(s, t), np.asarray(0.5 * (pose_cov + pose_cov.T), np.float64)


def fuse(glob: F64, glob_cov: F64, local: F64, local_cov: F64, iterations: int = JOINED_ITERATIONS,
         tolerance: float = 1e-10) -> tuple[F64, F64]:
    """The maximum-likelihood ``(s, g, t)`` of :func:`fuse_local_map` and its information matrix."""
    k = (len(glob) - 3) // 2
    n = 3 + 2 * k
    w_g = np.linalg.inv(glob_cov + FLOOR * np.eye(len(glob)))  # the floor: a local map starts with its robot exact
    w_l = np.linalg.inv(local_cov + FLOOR * np.eye(len(local)))
    y = np.concatenate([glob, local[:3]])
    a = np.zeros((n + 3, n + 3))
    for _ in range(iterations):
        s, g, t = y[:3], y[3:n].reshape(k, 2), y[n:]
        rt, drt = rotation_t(s[2])
        d = g - s[:2]
        h = np.concatenate([t, (d @ rt.T).reshape(-1)])
        r_l = h - local
        r_l[2] = se2.wrap_angle(r_l[2])
        r_g = y[:n] - glob
        r_g[2] = se2.wrap_angle(r_g[2])
        j_l = np.zeros((n, n + 3))
        j_l[:3, n:] = np.eye(3)
        for i in range(k):
            j_l[3 + 2 * i:5 + 2 * i, :2] = -rt
            j_l[3 + 2 * i:5 + 2 * i, 2] = drt @ d[i]
            j_l[3 + 2 * i:5 + 2 * i, 3 + 2 * i:5 + 2 * i] = rt
        a = j_l.T @ w_l @ j_l
        a[:n, :n] += w_g
        grad = j_l.T @ w_l @ r_l
        grad[:n] += w_g @ r_g
        step = np.linalg.solve(a, -grad)
        y = y + step
        y[2], y[-1] = se2.wrap_angle(y[2]), se2.wrap_angle(y[-1])
        if float(np.max(np.abs(step))) < tolerance:
            break
    return y, a


class LocalRecord:
    """What one local map's EKF was given, for ``local_map_estimate="smoothed"``: the odometry between its scans
    (composed, with its first-order covariance), each scan's sightings of the local map's features, and the EKF's
    pose after each scan (where the solve starts)."""

    def __init__(self) -> None:
        self.poses: list[F64] = [np.zeros(3)]  # pose 0: the start frame (fixed)
        self.edges: list[tuple[int, F64, F64]] = []  # (pose index it ends at, increment, covariance)
        self.sightings: list[tuple[int, int, float, float, float, float]] = []  # (pose, feature, r, b, sr, sb)
        self._acc, self._cov, self._moved = np.zeros(3), np.zeros((3, 3)), False

    def predict(self, u: F64, q: F64) -> None:
        self._cov = compose_cov(self._acc, self._cov, u, q)
        self._acc = se2.compose(self._acc, u)
        self._moved = True

    @property
    def moved(self) -> bool:
        """Whether the robot was moved since the local map started."""
        return bool(self.edges) or self._moved

    def _pose(self, guess: F64) -> int:
        """The index of the pose now: a new one if the robot was moved since the last."""
        if self._moved:
            self.poses.append(np.array(guess, np.float64))
            self.edges.append((len(self.poses) - 1, self._acc, self._cov))
            self._acc, self._cov, self._moved = np.zeros(3), np.zeros((3, 3)), False
        return len(self.poses) - 1

    def observe(self, pose: F64, features: I64, r: F64, b: F64, sr: float, sb: float) -> None:
        k = self._pose(pose)
        self.sightings += [(k, f, float(r[j]), float(b[j]), sr, sb) for j, f in enumerate(features.tolist()) if f >= 0]

    def smoothed(self, pose: F64, features: F64) -> tuple[F64, F64]:
        """The local map's maximum-likelihood end pose and features and their covariance, in an EKF-SLAM state's
        layout: Levenberg-Marquardt over all its poses and features from the EKF's estimate (``pose``, the end
        pose, and ``features`` (n, 2)), the covariance from the information at the optimum."""
        end = self._pose(pose)
        if end == 0:  # never moved: the start frame is exact and so is the EKF
            raise ValueError("a local map that never moved has no pose to smooth")
        n = len(features)
        sight = np.array([s[:2] for s in self.sightings], np.int64).reshape(-1, 2)
        graph = LandmarkGraph(
            len(self.poses), n, np.array([j - 1 for j, _, _ in self.edges], np.int64),
            np.array([j for j, _, _ in self.edges], np.int64), np.array([u for _, u, _ in self.edges]),
            np.array([np.linalg.inv(c + FLOOR * np.eye(3)) for _, _, c in self.edges]), sight[:, 0], sight[:, 1],
            np.array([s[2:4] for s in self.sightings]).reshape(-1, 2),
            np.array([np.diag([1 / s[4]**2, 1 / s[5]**2]) for s in self.sightings]).reshape(-1, 2, 2))
        res = optimize(graph, np.array(self.poses), np.asarray(features, np.float64), LsqConfig())
        cov = pose_landmark_covariance(graph, res.poses, res.landmarks, end)
        return np.concatenate([res.poses[end], res.landmarks.reshape(-1)]), cov


class Slsjf:
    """Sparse Local Submap Joining Filter (module docstring), with EkfSlam's interface for the pipelines."""

    def __init__(self, config: SlsjfConfig = SlsjfConfig(), observer: Observer = NULL_OBSERVER,
                 clock: Callable[[], float] | None = None) -> None:
        self.config = config
        self.observer = observer
        self.map = GlobalMap(config.linearization, config.max_iterations, recovery=config.state_recovery)
        self.start = -1  # global pose index of the current local map's start frame (-1: the origin)
        self._start_pose = np.zeros(3)
        self._start_cov = np.zeros((3, 3))
        self.local = EkfSlam(config.local)
        self.local_scans = 0
        self.local_distance_m = 0.0
        self.feature_ids: list[int] = []  # known id of each global feature (-1: unknown ids)
        self.by_id: dict[int, int] = {}  # known id -> global feature
        self.local_global: list[int] = []  # global feature of each feature of the current local map (-1: none)
        self.local_of: dict[int, int] = {}  # global feature -> its feature in the current local map
        self.associated = 0  # unknown ids: local features found to be global features already mapped
        self.ambiguous = 0  # unknown ids: local features near a global one but not in its gate (not joined)
        self.rejected_joined = 0
        self.gated = 0  # local feature estimates left out at a join (outside the outlier gate)
        self._clock = clock
        self.profile: dict[str, list[float]] = {}
        self._columns: dict[int, F64] = {}  # columns of the global covariance I^-1 asked for since the last join
        self._joined: tuple[int, F64, F64] | None = None  # (version, pose, covariance) of the joined robot
        self._version = 0  # counts predictions and scans: the joined robot is recomputed when it changes
        self._track = np.zeros(3)  # the tracked robot (robot_estimate="tracked") in the global frame
        self._track_cov = np.zeros((3, 3))
        self.tracked_sightings = 0  # sightings of global features used by the tracked robot
        self._record = LocalRecord()  # local_map_estimate="smoothed": what the current local map was given

    # -- the EkfSlam-like interface the landmark pipelines use
    @property
    def rejected(self) -> int:
        return self.rejected_joined + self.local.rejected

    @property
    def pose(self) -> F64:
        if self.config.robot_estimate == "joined":
            return self.joined()[0]
        return self._track.copy() if self.config.robot_estimate == "tracked" else self.composed_pose

    @property
    def pose_cov(self) -> F64:
        if self.config.robot_estimate == "joined":
            return self.joined()[1]
        return self._track_cov.copy() if self.config.robot_estimate == "tracked" else self.composed_cov

    @property
    def composed_pose(self) -> F64:
        """The current local map's start frame composed with its robot estimate ([1]_ eq. 13)."""
        return se2.compose(self._start_pose, self.local.pose)

    @property
    def composed_cov(self) -> F64:
        return compose_cov(self._start_pose, self._start_cov, self.local.pose, self.local.pose_cov)

    @property
    def n(self) -> int:
        return len(self.feature_ids)

    @property
    def start_pose(self) -> F64:
        """The current local map's start frame in the global frame."""
        return self._start_pose.copy()

    def estimates(self) -> F64:
        """Every feature (N, 2) in the global frame: joined ones from the global map, the others from the
        current local map."""
        out = np.zeros((self.n, 2))
        local = self.local.estimates()
        for g in range(self.n):
            if self.map.has_feature(g):
                out[g] = self.map.feature(g)
            else:
                out[g] = se2.transform_points(self._start_pose, local[self.local_of[g]][None])[0]
        return out

    def marginal_covariances(self, features: list[int] | None = None) -> F64:
        """Marginal covariances (k, 2, 2) of ``features`` (default all, for scoring: exact by a direct solve
        whatever the state recovery, as D-SLAM's) in the global frame."""
        exact = features is None
        features = list(range(self.n)) if features is None else features
        joined = [g for g in features if self.map.has_feature(g)]
        glob = dict(zip(joined, self.map.feature_covariances(joined, exact), strict=True))
        out = np.zeros((len(features), 2, 2))
        if len(joined) < len(features):
            local_covs = self.local.marginal_covariances()
            local_xy = self.local.estimates()
        for k, g in enumerate(features):
            if g in glob:
                out[k] = glob[g]
            else:
                f = self.local_of[g]
                out[k] = point_cov(self._start_pose, self._start_cov, local_xy[f], local_covs[f])
        return out

    def joint_covariance(self, features: list[int]) -> F64 | None:
        """The joint covariance (2k, 2k) of joined features; None when one of them is not joined yet."""
        if not all(self.map.has_feature(g) for g in features):
            return None
        return self.map.joint_feature_covariance(features)

    # -- filtering
    def predict(self, increment: ArrayLike) -> None:
        u = np.asarray(increment, np.float64)
        self.local.predict(u)
        if self.config.local_map_estimate == "smoothed":
            self._record.predict(u, self.config.local.odometry_noise.covariance(u))
        self._version += 1
        if self.config.robot_estimate == "tracked":
            q = self.config.local.odometry_noise.covariance(u)
            self._track, self._track_cov, _ = motion.predict(self._track, self._track_cov, u, q)
        self.local_distance_m += float(math.hypot(u[0], u[1]))
        if self.local_distance_m >= self.config.local_map_distance_m:
            self.join()

    def observe(self, ranges: ArrayLike, bearings: ArrayLike, ids: ArrayLike | None = None,
                range_sigma: float = 0.0, bearing_sigma: float = 0.0) -> SlsjfScanResult:
        """Update the local map with one scan (EkfSlam.observe's arguments); join it when it is full.

        ``ids`` with ``association="known"``; with ``"unknown"`` the local EKF associates within its local map
        and each feature it creates is matched to the global map (:meth:`_associate_new`)."""
        known = self.config.local.association == "known"
        if known and ids is None:
            raise ValueError("association='known' needs landmark ids")
        pred, pred_cov = self.pose, self.pose_cov
        res = self.local.observe(ranges, bearings, ids if known else None, range_sigma, bearing_sigma)
        if self.config.local_map_estimate == "smoothed":
            r, b = rangebearing.check_scan(ranges, bearings)
            sr, sb = self._sigmas(range_sigma, bearing_sigma)
            self._record.observe(self.local.pose, res.features, r, b, sr, sb)
        self.local_scans += 1
        self._version += 1
        new: list[int] = []
        for f in res.new_features:
            g = self._new_global(f) if known else self._associate_new(f)
            if g == len(self.feature_ids):
                self.feature_ids.append(self.local.feature_ids[f])
                if known:
                    self.by_id[self.local.feature_ids[f]] = g
                new.append(g)
            self.local_global.append(g)
            if g >= 0:
                self.local_of[g] = f
        features = np.array([self.local_global[f] if f >= 0 else -1 for f in res.features.tolist()], np.int64)
        joined = self.local_scans >= self.config.local_map_scans
        if self.config.robot_estimate == "tracked":
            sightings = ([(j, self.by_id[int(i)]) for j, i in enumerate(np.asarray(ids, np.int64).reshape(-1).tolist())
                          if int(i) in self.by_id] if known else
                         [(j, int(g)) for j, g in enumerate(features.tolist()) if g >= 0])
            self._track_update(ranges, bearings, sightings, range_sigma, bearing_sigma)
        pose, pose_cov = self.pose, self.pose_cov
        if joined:
            self.join()
        return SlsjfScanResult(pred, pred_cov, pose, pose_cov, features, tuple(new), joined)

    def _new_global(self, f: int) -> int:
        """Known ids: the global feature of the local map's new feature ``f`` (a new index for a new id)."""
        return self.by_id.get(self.local.feature_ids[f], len(self.feature_ids))

    def _associate_new(self, f: int) -> int:
        """Unknown ids: the global feature the local map's new feature ``f`` is, a new index, or -1.

        The candidates are the global map's features not yet in this local map, near the feature's global
        position; each is compared with the local estimate seen from the start frame (:meth:`_distance`: the
        local covariance plus the global map's of the start frame and the candidate), and the assignment is
        :func:`~slamreplay.algorithms.common.association.match`'s maximum likelihood with the local EKF's gates:
        inside ``gate_probability`` it is that feature; outside ``new_feature_probability`` of every candidate
        it is new; between the two it is ambiguous and kept out of the global map (-1: marginalized at the
        join), as the local EKF drops an ambiguous sighting. The local EKF confirmed it over
        ``confirm_hits`` sightings before creating it, so its estimate is already several sightings deep."""
        new = len(self.feature_ids)
        if self.start < 0 or not self.map.feat_at:
            return new
        xy, cov = local_feature(np.asarray(self.local.x), np.asarray(self.local.P), f)
        where = se2.transform_points(self._start_pose, xy[None])[0]
        # 3 sigma of the local estimate and of the start frame (its heading error swings the feature about it)
        spread = 3.0 * math.sqrt(max(float(np.linalg.eigvalsh(cov).max()), 0.0)
                                 + max(float(np.linalg.eigvalsh(self._start_cov[:2, :2]).max()), 0.0)
                                 + float(xy @ xy) * max(self._start_cov[2, 2], 0.0))
        radius = spread + self.config.local.vicinity_margin_m
        gs = np.fromiter(self.map.feat_at.keys(), np.int64, len(self.map.feat_at))
        at = np.fromiter(self.map.feat_at.values(), np.int64, len(gs))
        near = np.hypot(self.map.x[at] - where[0], self.map.x[at + 1] - where[1]) <= radius
        cand = [g for g in gs[near].tolist() if g not in self.local_of]
        if not cand:
            return new
        innov = [self._innovation(g, xy, cov) for g in cand]
        d2 = np.array([[float(nu @ np.linalg.solve(sc, nu)) for nu, sc in innov]])
        log_det = np.array([np.linalg.slogdet(sc)[1] for _, sc in innov])
        params = self.config.local.association_params
        assigned, far = match(d2, log_det, params.gate, params.new_gate)
        if assigned[0] >= 0:
            self.associated += 1
            return cand[int(assigned[0])]
        if far[0]:
            return new
        self.ambiguous += 1
        return -1

    def _track_update(self, ranges: ArrayLike, bearings: ArrayLike, sightings: list[tuple[int, int]],
                      range_sigma: float, bearing_sigma: float) -> None:
        """The tracked robot: CI-updated by this scan's sightings of global features, then CI-fused with the
        composed estimate (module docstring)."""
        r, b = rangebearing.check_scan(ranges, bearings)
        sr, sb = self._sigmas(range_sigma, bearing_sigma)
        r_cov = np.diag([sr**2, sb**2])
        gate = self.config.local.association_params.outlier_gate
        x, p = self._track, self._track_cov + FLOOR * np.eye(3)
        seen = [(j, g) for j, g in sightings if self.map.has_feature(g)]
        if seen:
            gs = [g for _, g in seen]
            xy = np.array([self.map.feature(g) for g in gs])
            joint = self.map.joint_feature_covariance(gs)
            z_pred, h_r, h_l = rangebearing.predict(x, xy)
            js = [j for j, _ in seen]
            nu = np.stack([r[js], b[js]], -1) - z_pred
            nu[:, 1] = se2.wrap_angle(nu[:, 1])
            keep = []
            for k in range(len(gs)):  # the known-id outlier gate on each sighting alone
                s_k = h_r[k] @ p @ h_r[k].T + h_l[k] @ joint[2 * k:2 * k + 2, 2 * k:2 * k + 2] @ h_l[k].T + r_cov
                if not np.isfinite(gate) or float(nu[k] @ np.linalg.solve(s_k, nu[k])) <= gate:
                    keep.append(k)
            if keep:
                rows = (2 * np.array(keep)[:, None] + np.arange(2)).reshape(-1)
                hl = np.zeros((2 * len(keep), 2 * len(keep)))
                for n, k in enumerate(keep):
                    hl[2 * n:2 * n + 2, 2 * n:2 * n + 2] = h_l[k]
                s = hl @ joint[np.ix_(rows, rows)] @ hl.T + np.kron(np.eye(len(keep)), r_cov)
                fused = covariance_intersection_update(x, p, nu[keep].reshape(-1), h_r[keep].reshape(-1, 3), s,
                                                       angular=(2,))
                x, p = fused.mean, fused.cov
                self.tracked_sightings += len(keep)
        fused = covariance_intersection(x, p, self.composed_pose, self.composed_cov + FLOOR * np.eye(3),
                                        angular=(2,))
        self._track, self._track_cov = fused.mean, fused.cov

    def _sigmas(self, range_sigma: float, bearing_sigma: float) -> tuple[float, float]:
        local = self.config.local
        return rangebearing.scan_sigmas(range_sigma, bearing_sigma, local.default_range_sigma_m,
                                        local.default_bearing_sigma_rad)

    def _gate(self, features: I64, z: F64, P: F64) -> NDArray[np.bool_]:
        """Which local features to join: those :meth:`_common` leaves out are, and counted in ``gated``.

        Each local map initialises its features from their first sighting in it, where no gate can apply, so a
        wrong sighting would otherwise enter the global map as a confident local estimate (MRCLAM's outliers
        did). Leaving a feature out of a local map is marginalizing it: its rows and columns of P go."""
        kept = {j for j, _ in self._common(z, P)}
        keep = np.array([j in kept or not self.map.has_feature(int(g)) for j, g in enumerate(features.tolist())], bool)
        self.gated += int(np.count_nonzero(~keep))
        return keep

    def _common(self, x: F64, P: F64) -> list[tuple[int, int]]:
        """The current local map's features (``x``, ``P``: its state) already in the global map and consistent
        with it: (local index, global index) pairs.

        A feature is consistent when its local estimate is inside the known-id outlier gate
        (``outlier_probability``, chi2 with 2 dof) of its global estimate seen from the start frame. With
        ``MIN_FIT`` or more common features the test is made against the start frame and features fitted to
        all of them (:func:`fuse`), dropping the worst one and refitting while one is outside: a start frame
        that is itself off (a local map whose robot slipped, and every one after it) then moves to where
        its features place it instead of disconnecting them all from the map. With fewer, against the
        global estimates as they are."""
        pairs = [(j, g) for j, g in enumerate(self.local_global) if g >= 0 and self.map.has_feature(g)]
        gate = self.config.local.association_params.outlier_gate
        if self.start < 0 or not np.isfinite(gate):
            return pairs
        while len(pairs) >= MIN_FIT:
            y, _ = fuse(*self._fusion_inputs(pairs, x, P))
            d = [self._distance(g, *local_feature(x, P, j), y[:3], y[3 + 2 * i:5 + 2 * i])
                 for i, (j, g) in enumerate(pairs)]
            worst = int(np.argmax(d))
            if d[worst] <= gate:
                return pairs
            pairs = pairs[:worst] + pairs[worst + 1:]
        return [(j, g) for j, g in pairs if self._distance(g, *local_feature(x, P, j)) <= gate]

    def _fusion_inputs(self, pairs: list[tuple[int, int]], x: F64, P: F64) -> tuple[F64, F64, F64, F64]:
        """:func:`fuse`'s arguments for the common features ``pairs``: the global start frame and features with
        their joint covariance, the local robot and features with theirs."""
        a = self.map.pose_at[self.start]
        glob = [a, a + 1, a + 2] + [i for _, g in pairs for i in (self.map.feat_at[g], self.map.feat_at[g] + 1)]
        rows = [0, 1, 2] + [i for j, _ in pairs for i in (3 + 2 * j, 4 + 2 * j)]
        return self.map.x[glob], self._covariance(glob), x[rows], P[np.ix_(rows, rows)]

    def _distance(self, g: int, local_xy: F64, local_cov: F64, s: F64 | None = None, f: F64 | None = None) -> float:
        """The squared Mahalanobis distance of a local estimate (start frame) of global feature ``g`` from the
        global estimate seen from the start frame (``s`` and ``f``: the start frame's and the feature's global
        estimates, or others fitted to them), with the global map's covariance of the two."""
        nu, innov = self._innovation(g, local_xy, local_cov, s, f)
        return float(nu @ np.linalg.solve(innov, nu))

    def _innovation(self, g: int, local_xy: F64, local_cov: F64, s: F64 | None = None, f: F64 | None = None
                    ) -> tuple[F64, F64]:
        """:meth:`_distance`'s innovation (2,) and its covariance (2, 2)."""
        s = self._start_pose if s is None else s
        f = self.map.feature(g) if f is None else f
        rt, drt = rotation_t(s[2])
        fa = self.map.feat_at[g]
        a = self.map.pose_at[self.start]
        joint = self._covariance([a, a + 1, a + 2, fa, fa + 1])
        jac = np.hstack([-rt, (drt @ (f - s[:2]))[:, None], rt])
        nu = local_xy - rt @ (f - s[:2])
        return nu, local_cov + jac @ joint @ jac.T

    def _covariance(self, idx: list[int]) -> F64:
        """The block of the global covariance I^-1 at state indices ``idx``; its columns are kept until the next
        join (the global map does not change between joins), so each is solved for once per local map."""
        missing = [i for i in dict.fromkeys(idx) if i not in self._columns]
        if missing:
            tic = self._clock() if self._clock else 0.0
            cols = self.map.covariance_columns(missing)
            for k, i in enumerate(missing):
                self._columns[i] = cols[:, k]
            if self._clock is not None:
                self.profile.setdefault("columns", []).append(self._clock() - tic)
        out = np.array([self._columns[j][idx] for j in idx])
        return np.asarray(0.5 * (out + out.T), np.float64)

    def joined(self) -> tuple[F64, F64]:
        """``robot_estimate="joined"``: the robot as joining the current local map now would place it (module
        docstring), its pose and covariance (3, 3) in the global frame."""
        if self._joined is not None and self._joined[0] == self._version:
            return self._joined[1].copy(), self._joined[2].copy()
        x, P = np.asarray(self.local.x), np.asarray(self.local.P)
        common = self._common(x, P)
        if self.start < 0 or not common:
            pose, cov = self.composed_pose, self.composed_cov  # nothing in common: the composition is exact
        else:
            pose, cov = fuse_local_map(*self._fusion_inputs(common, x, P))
        self._joined = (self._version, pose, cov)
        return pose.copy(), cov.copy()

    def join(self) -> None:
        """Fuse the current local map into the global map and start the next one at its end pose."""
        tic = self._clock() if self._clock else 0.0
        loc = self.local
        if loc.n == 0 and self.local_distance_m == 0.0 and self.local_scans == 0:
            return  # nothing happened since the last join
        features = np.array(self.local_global, np.int64)
        x, P = np.array(loc.x), np.array(loc.P)
        if self.config.local_map_estimate == "smoothed" and loc.n and self._record.moved:
            x, P = self._record.smoothed(loc.pose, loc.estimates())  # never moved: no pose to solve for
        keep = self._gate(features, x, P) & (features >= 0)
        rows = np.concatenate([np.arange(3), (3 + 2 * np.flatnonzero(keep)[:, None] + np.arange(2)).reshape(-1)])
        tic_map = self._clock() if self._clock else 0.0
        end = self.map.join(self.start, x[:3], features[keep], x[rows], P[np.ix_(rows, rows)])
        tic_cov = self._clock() if self._clock else 0.0
        self.start = end
        self._start_pose = self.map.pose(end)
        self._start_cov = self.map.pose_covariance(end)
        if self._clock is not None:
            self.profile.setdefault("global_join", []).append(tic_cov - tic_map)
            self.profile.setdefault("start_covariance", []).append(self._clock() - tic_cov)
        self.rejected_joined += loc.rejected
        self.local = EkfSlam(self.config.local)
        self._record = LocalRecord()
        self.local_scans, self.local_distance_m = 0, 0.0
        self._columns = {}
        self.local_global, self.local_of = [], {}
        self._version += 1
        self.observer.log("slsjf/local_maps", Scalar(float(len(self.map.maps))))
        self.observer.log("slsjf/iterations", Scalar(float(self.map.iterations[-1])))
        if self._clock is not None:
            self.profile.setdefault("join", []).append(self._clock() - tic)
