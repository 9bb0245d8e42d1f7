"""Multi-robot D-SLAM: one shared map EIF, one Covariance Intersection localization per robot.

The extension the paper names ([1]_, conclusion: "since the mapping problem is treated as a
static estimation problem, the multi-robot SLAM problem can be a simple extension, provided data
association issues can be resolved"). D-SLAM's map state holds absolute feature positions only,
and its updates (eqs. 9-10) use only the recast measurement ``z_map``, which does not depend on
the robot's pose. Measurements of any robot are therefore information about the same state, and
every robot's recast scans go into one information matrix and vector: the map is one
:class:`~slamreplay.algorithms.dslam.filter.DSlam`'s map, unchanged (the information matrix keeps
only feature-feature links, exactly sparse, whatever robot made them).

What is per robot is what the paper keeps for its one robot (section 2.3): the pose estimate
and its covariance (odometry prediction, the measurement pose of eq. 12, fused by CI), the
robot's noise models (its own odometry and sensor), and the conservative joint covariance of
the features near it (:mod:`slamreplay.algorithms.dslam.covariance`, the features ``z_loc``
uses). A robot's vicinity covariance is not updated by the other robots' scans: information
only ever shrinks the true covariance, so a bound left stale stays a bound (and a Kalman update
of an upper-bound prior gives an upper bound of the posterior); it is recomputed exactly when
the robot's scan sees fewer than two of its features, as for one robot.

Bootstrap (not in the paper; DSlam's rule for a robot that moves before two features are mapped,
widened to each robot): a robot's scan that sees new features and no mapped one may start the new
features from the robot's own pose, with their joint covariance, as long as that robot has not yet
been located against the map and has added fewer than two features (one robot: the map has fewer
than two features, DSlam's rule). A robot's
pose until then comes from its start prior and its own odometry only, so this information is
independent of the map's. Without it (``robot_bootstrap=False``) only the first robot to see
features starts the map, and a robot can add features only where it sees two mapped ones: a
landmark cluster no scan connects to the first one is never mapped (MRCLAM: docs/dslam.md).

Known landmark ids are shared (one id, one feature, whichever robot saw it first); unknown-id
association would need the cross-robot data association the paper leaves open, and is not
offered.

The map frame is the reference robot's initial frame (paper eq. 5): that robot starts exactly
at the origin (phase I applies to it while it stands still). Every other robot is placed in the
map frame by :meth:`MultiDSlam.start` with a pose and a covariance, given from outside (the
pipeline uses the ground-truth start poses, the assumption of known initial poses that
multi-robot SLAM papers commonly make); afterwards it localizes against the shared map only.

References
----------
.. [1] Z. Wang, S. Huang, G. Dissanayake, "Implementation issues and experimental evaluation
   of D-SLAM", FSR 2005.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Mapping
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from slamreplay.algorithms.dslam.covariance import CovarianceCache
from slamreplay.algorithms.dslam.filter import DSlam, DSlamConfig, ScanResult
from slamreplay.algorithms.dslam.information import InformationMatrix
from slamreplay.algorithms.dslam.localization import PoseStatus
from slamreplay.algorithms.dslam.recovery import RecoveryReport
from slamreplay.algorithms.observe import NULL_OBSERVER, Observer

F64 = NDArray[np.float64]

# DSlamConfig fields that describe one robot (its noise, its localization); every other field describes the one
# shared map and must be the same for all robots.
ROBOT_FIELDS = frozenset({"odometry_noise", "default_range_sigma_m", "default_bearing_sigma_rad",
                          "association_params", "ci_criterion", "localization_gate_probability",
                          "map_gate_probability"})


@dataclass
class RobotState:
    """One robot's localization state (section 2.3), in the map frame."""

    config: DSlamConfig
    pose: F64  # (3,) x, y, yaw
    pose_cov: F64  # (3, 3)
    moved: bool  # False only for the reference robot before it moves (phase I)
    covariance: CovarianceCache  # the joint covariance of the features near this robot
    max_range: float = 0.0  # the largest range this robot has read (its vicinity radius)
    started: bool = False
    scans: int = 0
    created: int = 0  # features this robot's scans added to the map
    localized: bool = False  # whether a scan has located it against the map (eq. 12)


def check_configs(configs: Mapping[str, DSlamConfig], reference: str) -> None:
    """ValueError unless ``configs`` names ``reference`` and agrees on every map field (module docstring)."""
    if not configs:
        raise ValueError("configs must name at least one robot")
    if reference not in configs:
        raise ValueError(f"reference robot {reference!r} is not one of the robots {sorted(configs)}")
    first = configs[reference]
    for name, cfg in configs.items():
        if cfg.association != "known":
            raise ValueError(f"robot {name!r}: association must be 'known' (multi-robot D-SLAM shares features by "
                             f"landmark id), got {cfg.association!r}")
        if cfg.composite_max_scans:
            raise ValueError(f"robot {name!r}: composite_max_scans must be 0 (composite scans are single-robot), "
                             f"got {cfg.composite_max_scans}")
        for f in dataclasses.fields(DSlamConfig):
            if f.name not in ROBOT_FIELDS and getattr(cfg, f.name) != getattr(first, f.name):
                raise ValueError(f"robot {name!r}: {f.name} describes the shared map and must equal the reference "
                                 f"robot's ({getattr(cfg, f.name)!r} != {getattr(first, f.name)!r})")


class _SharedMap(DSlam):
    """The shared map: a DSlam whose bootstrap rule is set per robot by :class:`MultiDSlam`."""

    bootstrap: bool = False  # the robot being processed may start features of its own

    def _may_bootstrap(self, seen_mapped: int) -> bool:
        return self.n < 2 or (self.bootstrap and not seen_mapped)


class MultiDSlam:
    """D-SLAM with one shared map and one localization per robot (module docstring).

    Parameters
    ----------
    configs : robot name -> its DSlamConfig; fields outside ``ROBOT_FIELDS`` must agree.
    reference : the robot whose initial frame is the map frame (it starts at the origin, exactly).
    observer, clock : as for :class:`~slamreplay.algorithms.dslam.filter.DSlam`.
    robot_bootstrap : each robot's first features may start from its own pose (module docstring); False: only
        while the whole map holds fewer than two features, as for one robot.
    """

    def __init__(self, configs: Mapping[str, DSlamConfig], reference: str, observer: Observer = NULL_OBSERVER,
                 clock: Callable[[], float] | None = None, robot_bootstrap: bool = True) -> None:
        check_configs(configs, reference)
        self.reference = reference
        self.robot_bootstrap = robot_bootstrap
        self.slam = _SharedMap(configs[reference], observer, clock)  # its map is the shared map
        self.robots = {name: RobotState(cfg, np.zeros(3), np.zeros((3, 3)), name != reference, CovarianceCache())
                       for name, cfg in configs.items()}
        self.robots[reference].started = True
        self._active: str | None = None

    # -- the shared map
    @property
    def n(self) -> int:
        """Mapped features."""
        return self.slam.n

    @property
    def info(self) -> InformationMatrix:
        """The shared information matrix (features only)."""
        return self.slam.info

    @property
    def feature_ids(self) -> list[int]:
        """The landmark id of each feature."""
        return self.slam.feature_ids

    @property
    def rejected(self) -> int:
        """Observations rejected by the outlier gate so far (all robots)."""
        return self.slam.rejected

    @property
    def profile(self) -> dict[str, list[float]]:
        return self.slam.profile

    def estimates(self) -> F64:
        """Feature estimates (N, 2) in the map frame."""
        return self.slam.estimates()

    def marginal_covariances(self) -> F64:
        """Exact marginal covariances (N, 2, 2) of all features (for scoring)."""
        return self.slam.marginal_covariances()

    def finalize(self) -> RecoveryReport:
        """The exact EIF estimate, then the final relinearisation of every robot's map measurements."""
        return self.slam.finalize()

    # -- the robots
    def robot(self, name: str) -> RobotState:
        """The localization state of robot ``name``; ValueError naming the robots for an unknown one."""
        if name not in self.robots:
            raise ValueError(f"robot must be one of {sorted(self.robots)}, got {name!r}")
        return self.robots[name]

    def start(self, name: str, pose: ArrayLike, cov: ArrayLike) -> None:
        """Place robot ``name`` (not the reference) in the map frame: pose (3,) and its covariance (3, 3).

        Raises ValueError for the reference robot, a robot already moved by odometry or scans, or a
        non-finite pose or a covariance that is not symmetric positive semidefinite.
        """
        state = self.robot(name)
        if name == self.reference:
            raise ValueError(f"robot {name!r} is the reference: it starts at the map origin by definition")
        if state.scans:
            raise ValueError(f"robot {name!r} has already observed: start it before its first scan")
        x = np.asarray(pose, dtype=np.float64)
        c = np.asarray(cov, dtype=np.float64)
        if x.shape != (3,) or not np.all(np.isfinite(x)):
            raise ValueError(f"pose must be 3 finite numbers, got {x!r}")
        if c.shape != (3, 3) or not np.all(np.isfinite(c)) or not np.allclose(c, c.T) or \
                np.linalg.eigvalsh(0.5 * (c + c.T)).min() < -1e-12:
            raise ValueError(f"cov must be a symmetric positive semidefinite (3, 3) matrix, got {c!r}")
        state.pose, state.pose_cov, state.started = x.copy(), 0.5 * (c + c.T), True

    def predict(self, name: str, increment: ArrayLike) -> None:
        """Propagate robot ``name`` by one odometry increment ``[dx, dy, dtheta]`` (its own frame and noise)."""
        self._enter(name)
        try:
            self.slam.predict(increment)
        finally:
            self._exit(name)

    def observe(self, name: str, ranges: ArrayLike, bearings: ArrayLike, ids: ArrayLike,
                range_sigma: float = 0.0, bearing_sigma: float = 0.0) -> ScanResult:
        """One scan of robot ``name``: its localization (CI), then the shared map's update (eqs. 3-4, 9-10).

        Arguments as :meth:`DSlam.observe` (known ids). ValueError for an unknown robot or one not started.
        """
        self._enter(name)
        try:
            if ids is not None:
                self._share_bounds(self.robots[name].covariance, np.asarray(ids).ravel().tolist())
            result = self.slam.observe(ranges, bearings, ids, range_sigma, bearing_sigma)
            state = self.robots[name]
            state.scans += 1
            state.created += len(result.new_features)
            m = result.measurement
            state.localized = state.localized or (m is not None and m.status is PoseStatus.OK)
            return result
        finally:
            self._exit(name)

    def _share_bounds(self, cov: CovarianceCache, ids: list[int]) -> None:
        """Give ``cov`` a marginal bound of each mapped feature of ``ids`` it has none of (made by another robot).

        Association gates every reading of a mapped feature with the feature's marginal bound. A bound
        another robot's cache holds stays a bound (information only shrinks the covariance); the
        tightest one (least trace) is taken, the exact marginal when no cache has one. It joins
        ``cov`` outside its vicinity set (inserted, then marginalised out), uncorrelated with it.
        """
        by_id = self.slam.associator.by_id
        for f in sorted({by_id[i] for i in ids if i in by_id}):
            if cov.known([f]):
                continue
            bounds = [c.marginals([f])[0] for c in (r.covariance for r in self.robots.values()) if c.known([f])]
            bound = (min(bounds, key=lambda m: float(np.trace(m))) if bounds
                     else self.slam.marginal_covariances()[f])
            cov.insert([f], bound)
            cov.drop([f])

    def _enter(self, name: str) -> None:
        """Load robot ``name``'s localization state into the shared filter."""
        state = self.robot(name)
        if not state.started:
            raise ValueError(f"robot {name!r} has no start pose in the map frame: call start() first")
        assert self._active is None
        s = self.slam
        s.config = state.config
        s.associator.params = state.config.association_params
        s.pose, s.pose_cov, s.moved, s.covariance, s.max_range = (state.pose, state.pose_cov, state.moved,
                                                                   state.covariance, state.max_range)
        s.bootstrap = self.robot_bootstrap and state.created < 2 and not state.localized
        self._active = name

    def _exit(self, name: str) -> None:
        """Store the filter's localization state back into robot ``name``'s."""
        s, state = self.slam, self.robots[name]
        state.pose, state.pose_cov, state.moved, state.covariance, state.max_range = (s.pose, s.pose_cov, s.moved,
                                                                                      s.covariance, s.max_range)
        self._active = None
