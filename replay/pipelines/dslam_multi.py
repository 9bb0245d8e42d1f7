"""Pipeline ``dslam-multi``: every robot of a multi-robot recording builds one D-SLAM map.

The algorithm is :mod:`slamreplay.algorithms.dslam.multi`: one shared map EIF fed by every robot's
recast scans (eqs. 9-10), one odometry + CI localization per robot (eq. 12). The run reads each
robot's topics under its namespace (``/robotN/odom``, ``/robotN/landmarks/range_bearing``,
``/robotN/ground_truth/pose``: ``record mrclam --robot all``), all in the one replay order, and
routes each message to its robot by that namespace.

Frames and the one use of ground truth in the estimate: the map frame is robot 1's initial
frame (paper eq. 5), robot 1's pose at its first odometry message. Every other robot starts, at
its own first odometry message, at its ground-truth pose expressed in that frame (the
ground-truth poses of both robots there, interpolated), with the prior covariance
``diag(start_sigma_m^2, start_sigma_m^2, start_sigma_rad^2)``: known initial poses, as
multi-robot SLAM papers commonly assume. Ground truth is used for nothing else but scoring, which
is done as in ``dslam``: through robot 1's ground-truth start, with no fitted alignment.

Each robot has its own noise: a key the user (or a preset) did not set takes that robot's value
from its sensor model in the recording (``slamreplay inspect``), else the default. Messages of a
robot wait until its start pose is known (the ground truth just after its first odometry message).
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections import deque
from dataclasses import dataclass, field
from typing import Any, ClassVar, cast

import numpy as np
import rerun.blueprint as rrb

from slamreplay.algorithms.common import se2
from slamreplay.algorithms.common.motion import between1
from slamreplay.algorithms.dslam import ScanStatus
from slamreplay.algorithms.dslam.multi import MultiDSlam
from slamreplay.algorithms.observe import CovarianceEllipses, Image, Points, Pose, Scalar, Segments
from slamreplay.recorder.messages import (
    TOPIC_GROUND_TRUTH_LANDMARKS,
    TOPIC_GROUND_TRUTH_POSE,
    TOPIC_ODOM,
    TOPIC_RANGE_BEARING,
    GroundTruthPose,
    LandmarkMap,
    OdometryPose,
    RangeBearingScan,
)
from slamreplay.replay.engine import views
from slamreplay.replay.engine.pipeline import MetricSpec, Pipeline, ReplayContext, recording_sensor_model, robots_in
from slamreplay.replay.engine.reader import ROBOT_NAMESPACE, Envelope
from slamreplay.replay.engine.trajectory import TrajectoryLog
from slamreplay.replay.errors import ReplayError
from slamreplay.replay.evaluation.metrics import position_errors, rmse
from slamreplay.replay.evaluation.nees_series import NEES_ARTIFACT, NeesSeries, nees_artifact
from slamreplay.replay.metric_registry import specs
from slamreplay.replay.pipelines.dslam import DSlamPipeline, DSlamPipelineConfig
from slamreplay.replay.pipelines.landmark_slam import (
    METRICS,
    ROBOT_NEES_BAND,
    landmark_scores,
    pose_nees,
    truth_pose_at,
    world_cov,
    world_pose,
    world_xy,
)

MAX_ROBOTS = 9  # robots /robot1/ .. /robot9/ (the pipeline's topics are declared up front)
REFERENCE = "1"  # the robot whose initial frame is the map frame


def robot_topic(robot: str, topic: str) -> str:
    return f"/robot{robot}{topic}"


@dataclass(frozen=True, slots=True)
class DSlamMultiConfig(DSlamPipelineConfig):
    """``dslam``'s keys (each robot's noise keys default to its own sensor model) plus the start prior."""

    start_sigma_m: float = field(default=0.01, metadata={"help": (
        "prior sigma (m) of each robot's start position in robot 1's frame, from ground truth; 0: exact")})
    start_sigma_rad: float = field(default=0.01, metadata={"help": (
        "prior sigma (rad) of each robot's start heading in robot 1's frame, from ground truth; 0: exact")})

    robot_bootstrap: bool = field(default=True, metadata={"help": (
        "each robot's first features may start from its own pose until the map locates it "
        "(algorithms/dslam/multi.py); false: only while the whole map has fewer than two features")})

    def __post_init__(self) -> None:
        DSlamPipelineConfig.__post_init__(self)
        for name in ("start_sigma_m", "start_sigma_rad"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise ValueError(f"{name} must be finite and >= 0, got {value}")
        if self.association == "unknown":
            raise ValueError("association must be 'known' or 'auto' with landmark ids: dslam-multi shares features "
                             "between robots by landmark id")
        if self.composite_max_scans:
            raise ValueError(f"composite_max_scans must be 0 for dslam-multi (composite scans are single-robot), "
                             f"got {self.composite_max_scans}")


@dataclass
class _Robot:
    """What the pipeline keeps of one robot: its config, start, odometry, estimates and truth."""

    name: str
    config: DSlamMultiConfig
    traj: dict[str, TrajectoryLog]
    t0: int | None = None  # log time of its first odometry message
    start_w: np.ndarray | None = None  # its ground-truth pose then (world frame)
    prev_odom: np.ndarray | None = None
    t_est: list[int] = field(default_factory=list)
    est: list[np.ndarray] = field(default_factory=list)  # world frame
    t_gt: list[int] = field(default_factory=list)
    gt: list[np.ndarray] = field(default_factory=list)
    scan_poses: list[tuple[int, np.ndarray, np.ndarray]] = field(default_factory=list)  # map frame
    nees: list[tuple[int, float]] = field(default_factory=list)  # (t, NEES) at its scans with truth: nees.json's
    scans: int = 0
    dropped_unknown: int = 0


def _metric_specs() -> dict[str, MetricSpec]:
    out = {k: v for k, v in METRICS.items() if k != "data_association_errors"}
    out.update(specs("ape_rmse_m"))  # every robot's estimates, pooled
    for k in range(1, MAX_ROBOTS + 1):
        out.update(specs(f"robot{k}_ape_rmse_m", f"robot{k}_nees_mean", f"robot{k}_scans"))
    out.update(specs("robots", "info_nnz_blocks", "info_nnz_blocks_per_landmark"))
    return out


class DSlamMultiPipeline(Pipeline):
    name = "dslam-multi"
    summary = ("multi-robot D-SLAM: every robot's recast scans in one shared map EIF, each robot localized by its "
               "own CI (all robots of a /robotN/ recording)")
    multi_robot = True
    required_topics = (robot_topic(REFERENCE, TOPIC_ODOM), robot_topic(REFERENCE, TOPIC_RANGE_BEARING))
    optional_topics = (TOPIC_GROUND_TRUTH_LANDMARKS, robot_topic(REFERENCE, TOPIC_GROUND_TRUTH_POSE),
                       *(robot_topic(str(k), t) for k in range(2, MAX_ROBOTS + 1)
                         for t in (TOPIC_ODOM, TOPIC_RANGE_BEARING, TOPIC_GROUND_TRUTH_POSE)))
    start_topic = robot_topic(REFERENCE, TOPIC_ODOM)
    Config = DSlamMultiConfig
    metrics = _metric_specs()
    # "paper": dslam's, and the map started only by the first robot to see two features (DSlam's own rule)
    presets: ClassVar[dict[str, dict[str, Any]]] = {
        "paper": {**DSlamPipeline.presets["paper"], "robot_bootstrap": False}}

    def __init__(self, config: DSlamMultiConfig, ctx: ReplayContext) -> None:
        super().__init__(config, ctx)
        present = ctx.info.logical_topics()
        names = robots_in(ctx.info)
        if len(names) > MAX_ROBOTS or any(not n.isdigit() or not 1 <= int(n) <= MAX_ROBOTS for n in names):
            raise ReplayError(f"dslam-multi replays robots 1..{MAX_ROBOTS}; {ctx.info.path.name} has robots "
                              f"{', '.join(names)}")
        for name in names:
            for topic in (TOPIC_ODOM, TOPIC_RANGE_BEARING, TOPIC_GROUND_TRUTH_POSE):
                t = robot_topic(name, topic)
                if t not in present or present[t].message_count == 0:
                    why = ("its start pose in robot 1's frame comes from ground truth"
                           if topic == TOPIC_GROUND_TRUTH_POSE else "every robot needs odometry and scans")
                    raise ReplayError(f"{ctx.info.path.name}: robot {name} has no {t} messages, which dslam-multi "
                                      f"needs ({why})")
        self.robots = {n: _Robot(n, self._robot_config(n), {k: TrajectoryLog(ctx.observer, f"world/trajectory/robot{n}"
                                                                             f"/{k}") for k in ("estimate", "truth")})
                       for n in names}
        try:
            self.slam = MultiDSlam({n: r.config.algorithm("known") for n, r in self.robots.items()}, REFERENCE,
                                   observer=ctx.observer, clock=time.perf_counter,
                                   robot_bootstrap=config.robot_bootstrap)
        except ValueError as err:
            raise ReplayError(f"invalid config for pipeline dslam-multi: {err}") from err
        self.T: np.ndarray | None = None  # robot 1's ground-truth start: map frame -> world
        self.queue: deque[Envelope] = deque()  # messages waiting for their robot's start pose
        self.truth_ids: np.ndarray | None = None
        self.truth_xy: np.ndarray | None = None
        self.scans = 0
        self.statuses: dict[ScanStatus, int] = {}
        self.step_s: list[float] = []

    def _robot_config(self, name: str) -> DSlamMultiConfig:
        """The run's config with robot ``name``'s sensor model for every key neither the user nor a preset set."""
        model = recording_sensor_model(self.ctx.info, name)
        if model is None:
            return cast(DSlamMultiConfig, self.config)
        own = {k: v for k, v in DSlamPipeline.config_from_sensor_model(model).items()
               if self.ctx.config_sources.get(k, "default") in ("default", "recording")}
        cfg = dataclasses.replace(self.config, **own)
        self.ctx.log(f"robot {name}: " + ", ".join(f"{k} {v:.4g}" for k, v in sorted(own.items())) +
                     " (its sensor model)")
        return cast(DSlamMultiConfig, cfg)

    # -- frames
    def _world_pose(self, pose: np.ndarray) -> np.ndarray:
        assert self.T is not None
        return world_pose(self.T, pose)

    def _world_xy(self, xy: np.ndarray) -> np.ndarray:
        assert self.T is not None
        return world_xy(self.T, xy)

    def _world_cov(self, cov: np.ndarray) -> np.ndarray:
        assert self.T is not None
        return world_cov(self.T, cov)

    # -- messages
    def step(self, env: Envelope) -> None:
        msg = env.msg
        if isinstance(msg, LandmarkMap):
            self.truth_ids, self.truth_xy = np.asarray(msg.landmark_ids), np.asarray(msg.positions_m)
            labels = tuple(str(i) for i in self.truth_ids.tolist())
            self.ctx.observer.log_static("world/landmarks/truth", Points(self.truth_xy, labels=labels, radius=0.06))
            return
        ns = ROBOT_NAMESPACE.match(env.topic)
        if ns is None:
            return
        robot = self.robots[ns.group()[len("/robot"):]]
        if isinstance(msg, GroundTruthPose):
            robot.t_gt.append(env.log_time_ns)
            robot.gt.append(msg.xy_yaw)
            robot.traj["truth"].append(msg.x_m, msg.y_m)
            if robot.start_w is None and robot.t0 is not None and env.log_time_ns >= robot.t0:
                self._place(robot)
        else:
            if isinstance(msg, OdometryPose) and robot.t0 is None:
                robot.t0 = env.log_time_ns
                if robot.t_gt and robot.t_gt[-1] >= robot.t0:
                    self._place(robot)
            self.queue.append(env)
        self._drain()

    def _place(self, robot: _Robot) -> None:
        """Its ground-truth pose at its first odometry message: robot 1's fixes the map frame, the others start."""
        assert robot.t0 is not None
        robot.start_w = truth_pose_at(robot.t0, robot.t_gt, robot.gt, clamp=True)
        if robot.name == REFERENCE:
            self.T = robot.start_w
            self.ctx.log(f"map frame: robot {REFERENCE}'s start, world pose {np.round(self.T, 4).tolist()}")

    def _ready(self, robot: _Robot) -> bool:
        return robot.start_w is not None and self.T is not None

    def _drain(self) -> None:
        """Process the waiting messages in replay order, up to the first whose robot has no start yet."""
        while self.queue:
            env = self.queue[0]
            ns = ROBOT_NAMESPACE.match(env.topic)
            assert ns is not None
            robot = self.robots[ns.group()[len("/robot"):]]
            if not self._ready(robot):
                return
            self.queue.popleft()
            self._start(robot)
            if isinstance(env.msg, OdometryPose):
                self._odometry(robot, env.log_time_ns, env.msg.xy_yaw)
            elif isinstance(env.msg, RangeBearingScan):
                self._scan(robot, env.log_time_ns, env.msg)

    def _start(self, robot: _Robot) -> None:
        state = self.slam.robot(robot.name)
        if state.started:
            return
        assert robot.start_w is not None and self.T is not None
        c = self.config
        pose = se2.between(self.T, robot.start_w)
        self.slam.start(robot.name, pose, np.diag([c.start_sigma_m**2, c.start_sigma_m**2, c.start_sigma_rad**2]))
        self.ctx.log(f"robot {robot.name} starts at {np.round(pose, 4).tolist()} in robot {REFERENCE}'s frame "
                     f"(ground truth; sigma {c.start_sigma_m} m, {c.start_sigma_rad} rad)")

    def _odometry(self, robot: _Robot, t: int, odom: np.ndarray) -> None:
        if robot.prev_odom is not None:
            self.slam.predict(robot.name, between1(robot.prev_odom, odom))
        robot.prev_odom = odom
        pose = self._world_pose(self.slam.robot(robot.name).pose)
        robot.t_est.append(t)
        robot.est.append(pose)
        robot.traj["estimate"].append(float(pose[0]), float(pose[1]))

    def _scan(self, robot: _Robot, t: int, msg: RangeBearingScan) -> None:
        ids = np.asarray(msg.landmark_ids)
        keep = ids >= 0
        robot.dropped_unknown += int(np.sum(~keep))
        cfg, user = robot.config, self.ctx.user_set
        sr = cfg.range_sigma_m if user("range_sigma_m") else msg.range_sigma_m
        sb = cfg.bearing_sigma_rad if user("bearing_sigma_rad") else msg.bearing_sigma_rad
        tic = time.perf_counter()
        res = self.slam.observe(robot.name, msg.ranges_m[keep], msg.bearings_rad[keep], ids[keep], sr, sb)
        self.step_s.append(time.perf_counter() - tic)
        self.scans += 1
        robot.scans += 1
        self.statuses[res.status] = self.statuses.get(res.status, 0) + 1
        robot.scan_poses.append((t, res.pose, res.pose_cov))
        obs = self.ctx.observer
        pose_w = self._world_pose(res.pose)
        obs.log(f"world/robots/robot{robot.name}", Pose(pose_w, label=f"robot {robot.name}"))
        obs.log(f"world/robots/robot{robot.name}/covariance",
                CovarianceEllipses(pose_w[None, :2], self._world_cov(res.pose_cov[:2, :2])[None]))
        if robot.t_gt and robot.t_gt[0] <= t:  # against the latest ground truth (the replay has not read on)
            truth = truth_pose_at(t, robot.t_gt, robot.gt, clamp=True)
            obs.log(f"metrics/robot{robot.name}_position_error_m",
                    Scalar(float(np.hypot(pose_w[0] - truth[0], pose_w[1] - truth[1]))))
        world_xy = self._world_xy(self.slam.estimates())
        seen = [f for f in res.features.tolist() if f >= 0]
        obs.log(f"world/associations/robot{robot.name}", Segments(np.repeat(pose_w[None, :2], len(seen), 0),
                                                                  world_xy[seen]))
        if self.scans % self.config.map_every_scans == 0:
            self._draw_map(world_xy)

    def _draw_map(self, world_xy: np.ndarray) -> None:
        labels = tuple(str(i) for i in self.slam.feature_ids)
        self.ctx.observer.log("world/landmarks/estimate", Points(world_xy, labels=labels, radius=0.07))
        if len(world_xy):
            covs = self._world_cov(self.slam.marginal_covariances())
            self.ctx.observer.log("world/landmarks/estimate/covariance", CovarianceEllipses(world_xy, covs))

    # -- the end
    def finish(self) -> dict[str, float]:
        for robot in self.robots.values():  # a robot whose truth ends before its first odometry: the last truth
            if robot.start_w is None and robot.t0 is not None and robot.t_gt:
                self._place(robot)
        self._drain()
        if self.queue:
            waiting = sorted({e.topic for e in self.queue})
            self.ctx.log(f"{len(self.queue)} messages never got their robot's start pose and were not used: "
                         f"{', '.join(waiting)}")
        for robot in self.robots.values():
            for traj in robot.traj.values():
                traj.finish()
            if robot.dropped_unknown:
                self.ctx.log(f"robot {robot.name}: {robot.dropped_unknown} observations without an id were dropped")
        metrics: dict[str, float] = {"steps": float(self.scans), "robots": float(len(self.robots))}
        if self.T is None or not self.slam.n:
            self.ctx.log("nothing was mapped")
            return metrics
        if self.slam.rejected:
            self.ctx.log(f"{self.slam.rejected} observations failed the outlier gate and were not used")
        report = self.slam.finalize()
        counts = ", ".join(f"{status.value} {n}" for status, n in self.statuses.items())
        self.ctx.log(f"final recovery: {report.method}; {self.slam.n} features; scans by status: {counts}")
        world_xy = self._world_xy(self.slam.estimates())
        self._draw_map(world_xy)
        links = self.slam.info.links()
        self.ctx.observer.log("world/information/links", Segments(world_xy[links[:, 0]], world_xy[links[:, 1]]))
        self.ctx.observer.log("dslam/information/sparsity", Image(self.slam.info.sparsity_image()))
        metrics.update(self._robot_metrics())
        metrics.update(self._landmark_metrics(world_xy))
        blocks = float(self.slam.info.nnz_blocks)
        metrics.update(info_nnz_blocks=blocks, info_nnz_blocks_per_landmark=blocks / self.slam.n)
        return metrics

    def _robot_metrics(self) -> dict[str, float]:
        out: dict[str, float] = {}
        errors, nees_all = [], []
        for robot in self.robots.values():
            out[f"robot{robot.name}_scans"] = float(robot.scans)
            t_gt, gt = np.asarray(robot.t_gt, dtype=np.int64), np.asarray(robot.gt).reshape(-1, 3)
            err, _ = position_errors(np.asarray(robot.t_est, dtype=np.int64), np.asarray(robot.est).reshape(-1, 3),
                                     t_gt, gt)
            if len(err):
                out[f"robot{robot.name}_ape_rmse_m"] = rmse(err)
                errors.append(err)
            robot.nees = []
            for t, pose, cov in robot.scan_poses:
                if t < robot.t_gt[0] or t > robot.t_gt[-1]:
                    continue
                truth = cast(np.ndarray, truth_pose_at(t, robot.t_gt, robot.gt, clamp=True))  # inside its span
                value = pose_nees(cast(np.ndarray, self.T), truth, pose, cov)
                if value is not None:
                    robot.nees.append((t, value))
            nees = [v for _, v in robot.nees]
            if nees:
                out[f"robot{robot.name}_nees_mean"] = float(np.mean(nees))
                nees_all += nees
        if errors:
            out["ape_rmse_m"] = rmse(np.concatenate(errors))
        if nees_all:
            out["robot_nees_mean"] = float(np.mean(nees_all))
        return out

    def _landmark_metrics(self, world_xy: np.ndarray) -> dict[str, float]:
        out = {"landmarks_mapped": float(len(world_xy))}
        if self.truth_xy is None or self.truth_ids is None:
            return out
        out["landmarks_true"] = float(len(self.truth_ids))
        lookup = {int(i): k for k, i in enumerate(self.truth_ids.tolist())}
        pairs = [(f, lookup[i]) for f, i in enumerate(self.slam.feature_ids) if i in lookup]
        out.update(landmark_scores(world_xy, self.truth_xy, pairs,
                                   lambda f: self._world_cov(self.slam.marginal_covariances()[f])))
        return out

    def artifacts(self) -> dict[str, bytes]:
        """``nees.json`` with a series per robot (``robot1``, ...): its pose NEES at its scans with ground truth."""
        series = {f"robot{r.name}": NeesSeries(f"robot {r.name}'s pose NEES at its scans (3 when consistent)", 3,
                                               ROBOT_NEES_BAND, np.asarray([t for t, _ in r.nees], np.int64),
                                               np.asarray([v for _, v in r.nees], np.float64),
                                               metric=f"robot{r.name}_nees_mean")
                  for r in self.robots.values() if r.nees}
        return {NEES_ARTIFACT: nees_artifact(series)} if series else {}

    trajectory_metrics = False  # several robots: ape_rmse_m and robot{k}_ape_rmse_m are its own

    def trajectory(self) -> tuple[np.ndarray, np.ndarray] | None:
        """None: several robots have no one trajectory file (each is drawn under ``world/trajectory/robotN``)."""
        return None

    def timings(self) -> dict[str, float]:
        if not self.step_s:
            return {}
        steps = np.asarray(self.step_s)
        out = {"scan_step_mean_s": float(steps.mean()), "scan_step_p95_s": float(np.percentile(steps, 95))}
        for stage, values in sorted(self.slam.profile.items()):
            out[f"{stage}_mean_s"] = float(np.mean(values))
        return out

    @classmethod
    def blueprint(cls, bounds: views.Bounds | None = None) -> rrb.Blueprint:
        return views.layout(
            views.summary_tab(bounds, ("metrics/**",), "Each robot's position error (m) at its scans"),
            views.tab("Map over time", views.map_view("Map: shared estimate, truth; every robot", "world", bounds),
                      views.log_view(), columns=[3, 2]),
            views.tab("Filter internals",
                      views.image_view("Information matrix sparsity (paper Fig. 3d)", "/dslam/information")),
            views.tab("Log", views.log_view("Log", "log", "dslam")),
        )

