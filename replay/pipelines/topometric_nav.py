"""Pipeline ``topometric-nav``: replay of a ``slamreplay navigate`` run (Battesti, Bazeille, Filliat, ECMR 2011, IV).

The recording's metadata names the map (path and sha256), the start and goal nodes, the guidance
configuration and the seed; the pipeline loads the map (``map_path`` overrides the recorded path,
but its sha256 must match: another map cannot reproduce the run), plans the same route and runs
the same :class:`~slamreplay.algorithms.topometric.guidance.Navigator` on the recorded odometry and images:
``/odom`` -> :meth:`~Navigator.on_odometry`, ``/camera/image`` -> :meth:`~Navigator.on_image`,
``/cmd_vel`` -> :meth:`~Navigator.control`. Each replayed localization and command is compared
with the recorded ``/nav/localization`` and ``/cmd_vel``: ``replay_mismatches`` counts the
differences (0: the replay reproduces the run exactly). The recording also holds a fingerprint of
the navigation code that made it: a replay by other code says so in its log (its mismatches then
measure what the change does, they are not a determinism fault) and ``code_matches_recording`` is 0.

Logged: the map's nodes and edges (``world/map``), the current image (``camera/image``), the global path and
the route's nodes, the local path at each image, the target point at
each tick, the matched node and the heading correction (``topo/nav/heading_correction_deg``), the
true, odometry and estimated trajectories (``world/trajectory/{truth,odometry,estimate}``), and
the path the drive is scored against (``world/nav/reference_path``).

Scoring, as the paper's Fig. 4 compares the replay and the mapping trajectories, both true
(:func:`slamreplay.replay.tools.navigate.reference_path`): the cross-track error is the distance of the *true*
position (``/ground_truth/pose``) to the *true path*, the route's nodes at the mapping drive's
ground-truth poses stored in the map (``truth_poses``), discretized like the global path; the goal
distance is to the goal node's true pose. A map without them (an older map, or mapping without
ground truth) falls back to the planned path in map coordinates (map frame = world frame), where
the map's own error counts as path-following error; the log says which was used.
"""

from __future__ import annotations

import dataclasses
import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
import rerun.blueprint as rrb

from slamreplay.algorithms.common import se2
from slamreplay.algorithms.observe import Image, LineStrips, Points, Pose, Scalar, Segments, Text
from slamreplay.algorithms.topometric.guidance import GuidanceConfig, Navigator, NavUpdate
from slamreplay.algorithms.topometric.pathfollow import distance_to_polyline
from slamreplay.recorder.messages import (
    TOPIC_CAMERA_IMAGE,
    TOPIC_CMD_VEL,
    TOPIC_GROUND_TRUTH_POSE,
    TOPIC_NAV_LOCALIZATION,
    TOPIC_ODOM,
    CameraImage,
    GroundTruthPose,
    NavLocalization,
    OdometryPose,
    VelocityCommand,
)
from slamreplay.recorder.writer import METADATA_NAME
from slamreplay.replay.engine import views
from slamreplay.replay.engine.pipeline import Pipeline, ReplayContext
from slamreplay.replay.engine.reader import Envelope
from slamreplay.replay.engine.trajectory import TrajectoryLog
from slamreplay.replay.errors import ReplayError
from slamreplay.replay.metric_registry import specs
from slamreplay.replay.tools.navigate import (
    SOURCE,
    MapLocalizer,
    guidance_from_dict,
    load_nav_map,
    localization_message,
    nav_code_fingerprint,
    reference_path,
)

AS_RECORDED = -1.0  # a guidance key of TopometricNavConfig left at the recording's value


@dataclass(frozen=True, slots=True)
class TopometricNavConfig:
    """Parameters of the ``topometric-nav`` pipeline."""

    map_path: str = field(default="", metadata={"help": "the map file or topometric run directory; empty: the "
                                                        "path recorded by `slamreplay navigate`"})
    goal_radius_m: float = field(default=0.5, metadata={"help": "goal_reached needs the true final position "
                                                                "this close to the goal node"})
    keep_along_m: float = field(default=AS_RECORDED, metadata={"help": (
        "localization rule: 0 resets the position to the matched node (the paper, IV-B); > 0 (beyond the paper) "
        "keeps the estimate's offset along the node's heading, clamped to +-keep_along_m; negative: as recorded. "
        "A value other than the recording's replays the recorded drive with that rule: replay_mismatches then "
        "count what it changes")})
    image_every_m: float = field(default=AS_RECORDED, metadata={"help": (
        "an image is processed each time odometry moved this far (the paper, section V: 0.5 m); negative: as "
        "recorded; larger than the recording's skips recorded images")})
    image_every_deg: float = field(default=AS_RECORDED, metadata={"help": (
        "... or turned this much (the paper: 10 degrees); negative: as recorded")})

    def __post_init__(self) -> None:
        if not self.goal_radius_m > 0:
            raise ValueError(f"goal_radius_m must be > 0, got {self.goal_radius_m}")
        for name in ("keep_along_m", "image_every_m", "image_every_deg"):
            value = getattr(self, name)
            if not math.isfinite(value):
                raise ValueError(f"{name} must be finite (negative: as recorded), got {value}")
        for name in ("image_every_m", "image_every_deg"):
            if getattr(self, name) == 0:
                raise ValueError(f"{name} must be > 0 (or negative: as recorded), got 0")

    def guidance(self, recorded: GuidanceConfig) -> GuidanceConfig:
        """The recorded guidance with this config's keys that are set (>= 0) in place of the recorded values."""
        keys = ("keep_along_m", "image_every_m", "image_every_deg")
        return dataclasses.replace(recorded, **{k: getattr(self, k) for k in keys if getattr(self, k) >= 0})


class TopometricNavPipeline(Pipeline):
    name = "topometric-nav"
    summary = "topo-metric navigation replay: Dijkstra route, qualitative visual localization, path following"
    required_topics = (TOPIC_ODOM, TOPIC_CAMERA_IMAGE, TOPIC_CMD_VEL)
    optional_topics = (TOPIC_GROUND_TRUTH_POSE, TOPIC_NAV_LOCALIZATION)
    start_topic = TOPIC_ODOM
    Config = TopometricNavConfig
    # "paper": the navigation rules of [Battesti, Bazeille, Filliat 2011, IV-V] in place of the recorded ones;
    # a replay cannot change where the recorded robot drove, only what the navigator makes of its images
    # (estimate_error_m_mean, visual_corrections, replay_mismatches): `slamreplay navigate` drives with them.
    presets: ClassVar[dict[str, dict[str, Any]]] = {
        "paper": {"keep_along_m": 0.0, "image_every_m": 0.5, "image_every_deg": 10.0},
    }
    preset_notes: ClassVar[dict[str, str]] = {
        "keep_along_m": "the paper sets the position to the loop-closure node's (IV-B), as `slamreplay navigate` "
                        "does by default since measured (docs/topometric.md); the extra (> 0) keeps the estimate's "
                        "along-track offset from the node, since the detector often matches a node 0.5-0.8 m ahead",
        "image_every_m": "the paper processes an image every 50 cm or 10 degrees (section V; 40 cm in Fig. 6); "
                         "`slamreplay navigate` takes one every 0.3 m (GuidanceConfig.image_every_m): measured "
                         "closer to the path (docs/topometric.md)",
        "image_every_deg": "the paper: 10 degrees (section V); the same as the default",
    }
    metrics = specs("goal_reached", "goal_distance_m", "cross_track_error_m_mean", "cross_track_error_m_max",
                    "cross_track_error_m_final", "visual_corrections", "loop_closure_rate", "images", "route_length_m",
                    "estimate_error_m_mean", "replay_mismatches", "code_matches_recording")

    @classmethod
    def blueprint(cls, bounds: views.Bounds | None = None) -> rrb.Blueprint:
        return views.layout(
            views.summary_tab(bounds, ("metrics/cross_track_error_m",), "Cross-track error (m)"),
            views.tab("Navigation", views.map_view("Map: nodes, global and local path, target, trajectories",
                                                   "world", bounds),
                      rrb.Vertical(views.image_view("Current image", "/camera/image"),
                                   views.series_view("Heading correction (deg)", "topo/nav/heading_correction_deg"),
                                   views.series_view("Cross-track error (m)", "metrics/cross_track_error_m")),
                      columns=[3, 2]),
            views.tab("Data", views.data_view()),
            views.tab("Log", views.log_view("Log", "log", "topo/nav/log")),
        )

    def __init__(self, config: TopometricNavConfig, ctx: ReplayContext) -> None:
        super().__init__(config, ctx)
        rec = _recorded(ctx)
        path = config.map_path or rec["map"]["path"]
        nav_map = load_nav_map(path)
        if nav_map.sha256 != rec["map"]["sha256"]:
            raise ReplayError(f"map {nav_map.path} (sha256 {nav_map.sha256[:12]}...) is not the map this navigation "
                              f"was recorded with ({rec['map']['path']}, sha256 {rec['map']['sha256'][:12]}...): "
                              f"another map cannot reproduce the run; use that map (--set map_path=...)")
        self.map = nav_map
        self.start, self.goal = int(rec["start"]), int(rec["goal"])
        try:
            recorded = guidance_from_dict(rec["guidance"])
            guidance = config.guidance(recorded)
        except (TypeError, ValueError) as err:
            raise ReplayError(f"the recording's guidance configuration is unreadable: {err}") from err
        # With the recorded spacing every recorded image is processed (the runner took it when due).
        self.check_due = (guidance.image_every_m, guidance.image_every_deg) != (recorded.image_every_m,
                                                                              recorded.image_every_deg)
        changed = {k: (getattr(recorded, k), getattr(guidance, k)) for k in ("keep_along_m", "image_every_m",
                                                                            "image_every_deg")
                   if getattr(recorded, k) != getattr(guidance, k)}
        for k, (was, now) in changed.items():
            ctx.log(f"guidance {k} {now} instead of the recorded {was}: the recorded drive replayed with another "
                    f"rule; replay_mismatches count what it changes")
        self.dt = float(rec["control_period_s"])
        # The navigate runner's generators: odometry, localizer, image noise (replay/tools/navigate.py).
        rng_loc = np.random.default_rng(int(rec["seed"])).spawn(3)[1]
        try:
            self.nav = Navigator(nav_map.graph, self.start, self.goal, MapLocalizer(nav_map.topomap, self.start,
                                                                                     rng_loc),
                                 guidance, observer=ctx.observer)
        except ValueError as err:
            raise ReplayError(f"map {nav_map.path}: {err}") from err
        self.code_matches = rec["code"] == nav_code_fingerprint()
        if not self.code_matches:
            ctx.observer.log("log", Text(f"this replay runs other navigation code than the recording's (fingerprint "
                                         f"{nav_code_fingerprint()}, recorded {rec['code'] or 'none'}): "
                                         f"replay_mismatches then measure the change, not a fault", level="WARN"))
        p = nav_map.graph.poses
        ctx.observer.log_static("world/map/nodes", Points(p[:, :2], labels=tuple(map(str, range(len(p)))),
                                                          radius=0.06))
        e = nav_map.graph.edges
        ctx.observer.log_static("world/map/edges", Segments(p[e[:, 0], :2], p[e[:, 1], :2]))
        ctx.log(f"route {self.start} -> {self.goal}: {len(self.nav.route.nodes)} nodes, "
                f"{self.nav.route.length_m:.2f} m, visual correction {'on' if guidance.visual_correction else 'off'}")
        self.truth = TrajectoryLog(ctx.observer, "world/trajectory/truth")
        self.odometry = TrajectoryLog(ctx.observer, "world/trajectory/odometry")
        self.estimate = TrajectoryLog(ctx.observer, "world/trajectory/estimate")
        self.odom0: np.ndarray | None = None
        self.pending: NavLocalization | None = None
        self.last_cmd: tuple[float, float] | None = None
        self.compared = 0
        self.mismatches = 0
        self.gt_xy: list[np.ndarray] = []
        self.gt_t: list[int] = []
        self.gt_step: list[int] = []  # replay step of each ground-truth pose (the series' step axis)
        self.gt: list[np.ndarray] = []
        self.est_t: list[int] = []
        self.est: list[np.ndarray] = []
        self.path_t: list[int] = []  # the estimate at every odometry message: the run's trajectory.tum
        self.path: list[np.ndarray] = []

    def step(self, env: Envelope) -> None:
        msg, obs = env.msg, self.ctx.observer
        if isinstance(msg, GroundTruthPose):
            self.gt_t.append(env.log_time_ns)
            self.gt_step.append(env.index)
            self.gt.append(msg.xy_yaw)
            self.truth.append(msg.x_m, msg.y_m)
            obs.log("world/robot_truth", Pose(msg.xy_yaw))
        elif isinstance(msg, OdometryPose):
            odom = msg.xy_yaw
            if self.odom0 is None:
                self.odom0 = odom
            est = self.nav.on_odometry(odom)
            dead = se2.compose(self.map.graph.poses[self.start], se2.between(self.odom0, odom))
            self.odometry.append(float(dead[0]), float(dead[1]))
            self.estimate.append(float(est[0]), float(est[1]))
            self.path_t.append(env.log_time_ns)
            self.path.append(est)
            obs.log("world/robot", Pose(est))
        elif isinstance(msg, CameraImage):
            if self.check_due and not self.nav.image_due():
                return  # a sparser image spacing than the recording's: this image is not processed
            gray = msg.pixels if msg.pixels.ndim == 2 else msg.pixels.mean(axis=2).astype(np.uint8)
            obs.log("camera/image", Image(gray))
            update = self.nav.on_image(gray)
            self.pending = localization_message(env.log_time_ns, update)
            self.est_t.append(env.log_time_ns)
            self.est.append(update.pose)
            self._log_update(update)
        elif isinstance(msg, NavLocalization):
            self._compare_localization(msg)
        elif isinstance(msg, VelocityCommand):
            cmd = self.nav.control(self.dt)
            obs.log("topo/nav/heading_error_deg", Scalar(math.degrees(cmd.heading_error_rad)))
            replayed = (0.0, 0.0) if cmd.reached else (cmd.linear_mps, cmd.angular_radps)
            recorded = (msg.linear_mps, msg.angular_radps)
            # The runner sends 0 at its last tick (goal, wall or time limit): only a moving command is compared then.
            if recorded != (0.0, 0.0) or cmd.reached:
                self._count(replayed == recorded, f"command {replayed} != recorded {recorded}")

    def _log_update(self, update: NavUpdate) -> None:
        obs = self.ctx.observer
        obs.log("world/nav/estimate", Pose(update.pose))
        if update.node >= 0:
            what = "correction" if update.corrected else "loop closure (correction off)"
            obs.log("topo/nav/log", Text(f"image {self.nav.images}: {what} at node {update.node}, x-translation "
                                         f"{update.dx_px:.1f} px -> {math.degrees(update.deviation_rad):.2f} deg"))
        obs.log("metrics/loop_closure_rate", Scalar(self.nav.matches / self.nav.images))

    def _compare_localization(self, recorded: NavLocalization) -> None:
        replayed, self.pending = self.pending, None
        if replayed is None:
            self._count(False, f"recorded localization at {recorded.stamp_ns} ns has no image before it")
            return
        same = dataclasses.astuple(replayed) == dataclasses.astuple(recorded)
        self._count(same, f"localization {replayed} != recorded {recorded}")

    def _count(self, same: bool, why: str) -> None:
        self.compared += 1
        if not same:
            self.mismatches += 1
            if self.mismatches <= 5:
                self.ctx.log(f"replay differs from the recording: {why}")

    def trajectory(self) -> tuple[np.ndarray, np.ndarray] | None:
        """The navigator's position estimate at every odometry message (world frame)."""
        if not self.path:
            return None
        return np.asarray(self.path_t, np.int64), np.asarray(self.path, np.float64).reshape(-1, 3)

    def finish(self) -> dict[str, float]:
        for t in (self.truth, self.odometry, self.estimate):
            t.finish()
        nav = self.nav
        metrics: dict[str, float] = {
            "visual_corrections": float(nav.corrections), "images": float(nav.images),
            "route_length_m": nav.route.length_m, "replay_mismatches": float(self.mismatches),
            "code_matches_recording": float(self.code_matches),
        }
        if nav.images:
            metrics["loop_closure_rate"] = nav.matches / nav.images
        self.ctx.log(f"{nav.images} images, {nav.matches} loop closures, {nav.corrections} corrections; "
                     f"{self.compared} recorded outputs compared, {self.mismatches} differ")
        if not self.gt:
            metrics["goal_reached"] = float(nav.reached)
            self.ctx.log("no ground truth: cross-track errors do not apply; goal_reached is the navigator's own")
            return metrics
        gt = np.array(self.gt)
        scored = reference_path(self.map.topomap, nav.route.nodes, nav.cfg.follower.spacing_m)
        self.ctx.log(f"cross-track error and goal distance {scored.describe()}")
        self.ctx.observer.log_static("world/nav/reference_path", LineStrips((scored.xy,)))
        xt = distance_to_polyline(gt[:, :2], scored.xy)
        self.ctx.observer.send_series("metrics/cross_track_error_m", np.array(self.gt_step), np.array(self.gt_t), xt)
        goal_d = float(np.hypot(*(gt[-1, :2] - scored.goal_xy)))
        metrics.update(cross_track_error_m_mean=float(xt.mean()), cross_track_error_m_max=float(xt.max()),
                       cross_track_error_m_final=float(xt[-1]),
                       goal_distance_m=goal_d,
                       goal_reached=float(nav.reached and goal_d <= self.config.goal_radius_m))
        if self.est:
            t_gt = np.array(self.gt_t, np.int64)
            ref = se2.interpolate((np.array(self.est_t) - t_gt[0]).astype(float), (t_gt - t_gt[0]).astype(float), gt)
            metrics["estimate_error_m_mean"] = float(np.hypot(*(np.array(self.est)[:, :2] - ref[:, :2]).T).mean())
        return metrics


def _recorded(ctx: ReplayContext) -> dict[str, Any]:
    """The navigate run's parameters and seed from the recording's metadata; ReplayError if it has none."""
    record = ctx.info.metadata.get(METADATA_NAME, {})
    try:
        source = json.loads(record.get("source", "{}"))
        params = json.loads(record.get("parameters", "{}"))
        if source.get("simulator") != SOURCE:
            raise ReplayError(f"{Path(ctx.info.path).name} was not recorded by `slamreplay navigate` (its source is "
                              f"{source or 'not stated'}): topometric-nav replays navigation runs")
        out = {k: params[k] for k in ("map", "start", "goal", "guidance", "control_period_s")}
        out["seed"] = int(record["seed"])
        out["code"] = str(params.get("code", ""))
        _ = out["map"]["path"], out["map"]["sha256"]
    except (json.JSONDecodeError, KeyError, TypeError, ValueError) as err:
        raise ReplayError(f"{Path(ctx.info.path).name}: the navigate metadata is incomplete or unreadable "
                          f"({type(err).__name__}: {err})") from err
    return out
