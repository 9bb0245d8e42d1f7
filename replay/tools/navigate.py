"""Closed-loop navigation on a topo-metric map with the simulator in the loop (``slamreplay navigate``).

Section IV of Battesti, Bazeille, Filliat (ECMR 2011): the robot starts at a map node, Dijkstra
plans the route to the goal node, and the :class:`~slamreplay.algorithms.topometric.guidance.Navigator`
follows it with the qualitative position (the last loop closure's node, heading corrected from the
image x-translation, plus odometry since). Here the ``sim-corridor`` world closes the loop: each
control period the robot moves by the command (an exact unicycle arc), the wheel odometry drifts
(:class:`~slamreplay.recorder.sim.wheel_odometry.WheelOdometry`), and when odometry says the robot moved
``image_every_m`` or turned ``image_every_deg`` the camera renders from the *true* pose.

Everything goes to one recording, in this order at each control tick (same log time, file order):
``/ground_truth/pose``, ``/odom``, then if an image was taken ``/camera/image`` (PNG, lossless)
and ``/nav/localization``, then ``/cmd_vel``. The metadata holds the map's path and sha256, the
start and goal, the guidance configuration, the world, the seed and a fingerprint of the loaded
navigation code (:func:`nav_code_fingerprint`), so the ``topometric-nav`` pipeline replays the same
code on the same inputs and must give the same localizations and commands, in any process.
Randomness: ``default_rng(seed).spawn(3)`` = odometry noise, localizer (RANSAC), image noise.

Scoring (:func:`reference_path`), as the paper's Fig. 4 compares the replay trajectory with the
mapping trajectory, both measured by laser SLAM: when the map holds the mapping drive's ground
truth (``TopoMap.truth_poses``, written by the ``topometric`` pipeline from ``/ground_truth/pose``),
the cross-track error is the distance of the robot's *true* position to the *true path* (the
route's nodes at their true poses, discretized like the global path) and the goal distance is to
the goal node's true pose, so the map's own metric error does not count as path-following error.
Without it (older maps, mapping without ground truth) both fall back to the map path and the goal
node's map pose (map frame taken as world frame), and the summary and metrics say so.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from slamreplay.algorithms.common import se2
from slamreplay.algorithms.topometric import Localizer, NavigationConfig, TopoMap
from slamreplay.algorithms.topometric.guidance import (
    GuidanceConfig,
    NavGraph,
    Navigator,
    NavUpdate,
    RouteConfig,
    VisualMatch,
)
from slamreplay.algorithms.topometric.pathfollow import FollowerConfig, discretize, distance_to_polyline
from slamreplay.recorder.codec.protobuf import yaw_from_quaternion
from slamreplay.recorder.errors import RecorderError
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
from slamreplay.recorder.writer import METADATA_NAME, Recorder
from slamreplay.replay.engine.reader import MCAP_MAGIC, RecordingReader
from slamreplay.replay.errors import ReplayError
from slamreplay.replay.tools.codeprint import code_fingerprint
from slamreplay.replay.tools.topomap_io import load_map

SOURCE = "navigate"
EPOCH_NS = 1_000_000_000
MAP_FILE = "map.npz"
# What a navigation replay runs: the localizer, the guidance and the map reader (not the mapper).
NAV_CODE = ("slamreplay.algorithms.common.se2",
            *(f"slamreplay.algorithms.topometric.{m}" for m in ("bayes", "config", "features", "guidance", "navigation",
                                                               "pathfollow", "topomap", "validation", "vocabulary")),
            "slamreplay.replay.tools.navigate", "slamreplay.replay.tools.topomap_io")
Progress = Callable[[int, int], None]


# ---------------------------------------------------------------------------------------
# The map


@dataclass(frozen=True, slots=True)
class NavMap:
    """A loaded topo-metric map file: where it is, its sha256, the map and its graph."""

    path: Path
    sha256: str
    topomap: TopoMap
    graph: NavGraph


@dataclass(frozen=True, slots=True, eq=False)
class ReferencePath:
    """What a drive is scored against: a discretized path (k, 2), the goal point (2,), and their frame.

    ``frame`` is ``"truth"`` (the route's nodes at the mapping drive's true poses) or ``"map"``
    (at the nodes' map poses: the fallback when the map has no ground truth for every route node).
    """

    xy: NDArray[np.float64]
    goal_xy: NDArray[np.float64]
    frame: str

    def describe(self) -> str:
        """One line for logs: which path the cross-track error and goal distance are measured to."""
        if self.frame == "truth":
            return ("scored against the true path (route nodes at their mapping ground-truth poses) and the goal "
                    "node's true pose")
        return ("scored against the map path (route nodes at their map poses, map frame = world frame): the map "
                "has no ground truth for its route, so the map's own error counts as path-following error")


def reference_path(topomap: TopoMap, route: tuple[int, ...] | list[int], spacing_m: float) -> ReferencePath:
    """The path a drive along ``route`` (node indices, start to goal) is scored against.

    The route's nodes at their true poses (``topomap.truth_poses``) when every one is known, else
    at their map poses; discretized every ``spacing_m`` like the navigator's global path (IV-C).
    """
    nodes = np.asarray(route, np.int64)
    if nodes.size == 0:
        raise ValueError("route must name at least one node")
    truth = topomap.truth_poses
    if truth is not None and np.all(np.isfinite(truth[nodes, :2])):
        at, frame = truth[nodes, :2], "truth"
    else:
        at, frame = topomap.poses[nodes, :2], "map"
    return ReferencePath(discretize(at, spacing_m), at[-1].copy(), frame)


def map_file(path: str | Path) -> Path:
    """The map file of ``path``: ``RUN_DIR/map.npz`` for a ``topometric`` run directory, else the file."""
    p = Path(path)
    if p.is_dir():
        p = p / MAP_FILE
        if not p.is_file():
            raise ReplayError(f"{path} has no {MAP_FILE}: give the run directory of a `topometric` pipeline run "
                              f"(slamreplay run REC.mcap --pipeline topometric --out RUN_DIR) or a map file")
    elif not p.is_file():
        raise ReplayError(f"map {path}: no such file or directory")
    return p.resolve()


def nav_code_fingerprint() -> str:
    """Fingerprint of the navigation code this process has loaded, with the numpy and OpenCV versions."""
    import cv2

    return f"{code_fingerprint(NAV_CODE)} numpy {np.__version__} opencv {cv2.__version__}"


def load_nav_map(path: str | Path) -> NavMap:
    """Load a map for navigation; ReplayError when it is missing, unreadable or has no node."""
    p = map_file(path)
    try:
        raw = p.read_bytes()
    except OSError as err:
        raise ReplayError(f"map {p}: cannot read it: {err.strerror or err}") from err
    try:
        topomap = load_map(raw)
    except ReplayError as err:
        detail = str(err).replace("<bytes>", p.name)
        raise ReplayError(f"map {p} is not a usable topo-metric map (the map.npz a `topometric` run writes): "
                          f"{detail}") from err
    if topomap.n_locations == 0:
        raise ReplayError(f"map {p} has no location: nothing to navigate on")
    edges = np.stack([topomap.edge_i, topomap.edge_j], axis=1)
    return NavMap(p, hashlib.sha256(raw).hexdigest(), topomap, NavGraph(topomap.poses, edges))


class MapLocalizer:
    """The map's navigation-mode loop-closure detector as an
    :data:`~slamreplay.algorithms.topometric.guidance.ImageLocalizer`.

    Translation threshold off (section IV-A); the x-translation is rescaled from the detector's
    working resolution to the pixels of the image handed in.
    """

    def __init__(self, topomap: TopoMap, start: int, rng: np.random.Generator) -> None:
        self.detector = Localizer(topomap, NavigationConfig(), start)
        self.rng = rng
        self.width = topomap.config.features.width

    def __call__(self, pixels: NDArray[np.uint8], motion: NDArray[np.float64] | None) -> VisualMatch | None:
        found = self.detector.localize(pixels, motion, self.rng)
        if found is None:
            return None
        m = found.motion
        return VisualMatch(found.location, m.tx_px * pixels.shape[1] / self.width, m.rotation_rad, m.scale,
                           m.n_inliers)


def guidance_from_dict(values: Mapping[str, Any]) -> GuidanceConfig:
    """A :class:`GuidanceConfig` from ``dataclasses.asdict`` output (as stored in a recording)."""
    v = dict(values)
    route = RouteConfig(**v.pop("route", {}))
    follower = FollowerConfig(**v.pop("follower", {}))
    return GuidanceConfig(**v, route=route, follower=follower)


# ---------------------------------------------------------------------------------------
# The world


def load_world(world: str | Path) -> tuple[Any, Any, int]:
    """``(CorridorWorld, CorridorConfig, seed)`` from a ``sim-corridor`` (or ``navigate``) recording or a world file."""
    from slamreplay.recorder.sim.corridor import CorridorConfig, CorridorWorld, world_from_file, world_from_metadata

    p = Path(world)
    if not p.is_file():
        raise ReplayError(f"world {world}: no such file (give a sim-corridor recording or a world JSON file)")
    with open(p, "rb") as f:
        is_mcap = f.read(8) == MCAP_MAGIC
    try:
        if not is_mcap:
            return world_from_file(p)
        record = RecordingReader(p).info.metadata.get(METADATA_NAME, {})
        if json.loads(record.get("source", "{}")).get("simulator") == SOURCE:
            spec = json.loads(record["parameters"])["world"]
            config = CorridorConfig.from_dict(spec["config"])
            return CorridorWorld.from_config(config, int(spec["seed"])), config, int(spec["seed"])
        return world_from_metadata(record)
    except RecorderError as err:
        what = "a recording whose metadata does not describe a sim-corridor world" if is_mcap else \
            'not a world JSON file {"config": {...}, "seed": N}'
        raise ReplayError(f"world {world}: {what} ({err}); give the sim-corridor recording the map was made "
                          f"from, or a world JSON file") from err
    except (KeyError, TypeError, ValueError) as err:
        raise ReplayError(f"world {world}: its metadata does not describe a world ({err})") from err


# ---------------------------------------------------------------------------------------
# The closed loop


@dataclass(frozen=True, slots=True)
class NavigateSummary:
    """What :func:`navigate` did (truth-based figures use the simulator's true poses)."""

    path: Path
    messages: int
    route: tuple[int, ...]
    route_length_m: float
    duration_s: float
    images: int
    loop_closures: int
    visual_corrections: int
    reached: bool  # the navigator declared the goal reached
    collided: bool  # the robot touched a wall (the run stops there unless through_walls)
    goal_distance_m: float  # true final position to the goal node (its true pose when the map has it)
    cross_track_mean_m: float  # true positions to the reference path (see scored_against)
    cross_track_max_m: float
    cross_track_final_m: float
    scored_against: str = "truth"  # "truth": the true path; "map": the map path (the map has no ground truth)


def navigate(map_path: str | Path, world: str | Path, goal: int, out: str | Path, *, start: int = 0, seed: int = 0,
             visual_correction: bool = True, guidance: GuidanceConfig | None = None, control_period_s: float = 0.1,
             through_walls: bool = False, clearance_m: float = 0.1, max_duration_s: float = 0.0,
             progress: Progress | None = None, overrides: Mapping[str, Any] | None = None) -> NavigateSummary:
    """Drive from map node ``start`` to ``goal`` in the simulated world and record everything to ``out``.

    Parameters
    ----------
    map_path : a ``topometric`` run directory (its ``map.npz``) or a map file.
    world : a ``sim-corridor`` recording (its metadata names the world) or a world JSON file
        ``{"config": {...}, "seed": N}``. The map frame is taken as the world frame (the mapping
        pipeline starts its map at the ground-truth start pose). The robot starts where the start
        node's image was taken (its true pose) when the map has ground truth, else at its map pose.
    visual_correction : False drives on odometry only (loop closures are still detected and recorded).
    overrides : GuidanceConfig fields set over ``guidance`` (the CLI's ``--preset paper``, ``--keep-along-m``...);
        a bad name or value is a ReplayError.
    guidance : navigation parameters (default :class:`GuidanceConfig`); its ``visual_correction`` is
        overridden by the argument.
    control_period_s : the fixed control period; odometry and ground truth are recorded at each tick.
    through_walls : keep driving through walls (to see where odometry alone goes); by default the run
        stops at the first pose closer than ``clearance_m`` to a wall.
    max_duration_s : simulated time limit; 0 means 3 x the route length at the forward speed + 60 s.
    progress : ``progress(done, total)`` in control ticks (the total is the limit).

    Raises
    ------
    ReplayError : bad map, world, nodes or output path.

    Notes
    -----
    Cross-track errors and the goal distance: the robot's true positions against
    :func:`reference_path` (the true path when the map holds the mapping ground truth, else the
    map path); ``scored_against`` in the summary says which.
    """
    nav_map = load_nav_map(map_path)
    the_world, world_cfg, world_seed = load_world(world)
    n = nav_map.graph.n_nodes
    for name, node in (("--start", start), ("--goal", goal)):
        if not 0 <= node < n:
            raise ReplayError(f"{name} {node} is not a node of map {nav_map.path} (it has nodes 0..{n - 1})")
    if start == goal:
        raise ReplayError(f"--start and --goal are both node {goal}: nothing to navigate; choose another goal")
    if Path(out).exists():
        raise ReplayError(f"{out} already exists; slamreplay never overwrites a recording: choose another --out "
                          f"or delete it")
    if not control_period_s > 0 or round(control_period_s * 1e9) <= 0:
        raise ReplayError(f"control_period_s must be > 0, got {control_period_s}")
    try:
        cfg = dataclasses.replace(guidance or GuidanceConfig(hfov_deg=world_cfg.hfov_deg),
                                  visual_correction=visual_correction, **dict(overrides or {}))
    except (TypeError, ValueError) as err:
        raise ReplayError(f"navigation settings: {err}") from err
    rng_odom, rng_loc, rng_noise = np.random.default_rng(seed).spawn(3)
    localizer = MapLocalizer(nav_map.topomap, start, rng_loc)
    try:
        nav = Navigator(nav_map.graph, start, goal, localizer, cfg)
    except ValueError as err:
        raise ReplayError(f"map {nav_map.path}: {err}") from err
    from slamreplay.recorder.sim.corridor import WheelOdometry
    from slamreplay.recorder.sim.unicycle import arc_step

    odometry = WheelOdometry(world_cfg, rng_odom)
    known = nav_map.topomap.truth_poses
    # Start where the start node's image was taken: its map pose carries the map's error.
    truth = known[start].copy() if known is not None and np.all(np.isfinite(known[start])) else \
        nav_map.graph.poses[start].copy()
    if not through_walls and not the_world.is_free(truth[:2], clearance_m):
        raise ReplayError(f"start node {start} at ({truth[0]:.2f}, {truth[1]:.2f}) m is not in free space of the "
                          f"world: is the map from a recording of this world?")
    period_ns = round(control_period_s * 1e9)
    dt = period_ns / 1e9
    limit = max_duration_s or 3.0 * nav.route.length_m / cfg.follower.linear_speed_mps + 60.0
    ticks = int(limit / dt) + 1
    parameters = {
        "map": {"path": str(nav_map.path), "sha256": nav_map.sha256}, "start": start, "goal": goal,
        "guidance": dataclasses.asdict(cfg), "control_period_s": dt, "through_walls": through_walls,
        "clearance_m": clearance_m, "max_duration_s": limit,
        "world": {"simulator": "sim-corridor", "config": dataclasses.asdict(world_cfg), "seed": world_seed},
        "code": nav_code_fingerprint(),
    }
    robot = {"drive": "differential", "wheel_base_m": world_cfg.wheel_base_m,
             "camera": f"forward, hfov {world_cfg.hfov_deg} deg, {world_cfg.image_width}x{world_cfg.image_height}"}
    trail = [truth[:2].copy()]
    collided = blocked = False
    try:
        with Recorder(out, source={"simulator": SOURCE}, seed=seed, parameters=parameters, robot=robot) as rec:
            for k in range(ticks):
                stamp = EPOCH_NS + k * period_ns
                odom = odometry.pose
                rec.write(TOPIC_GROUND_TRUTH_POSE, GroundTruthPose(stamp, truth[0], truth[1],
                                                                   float(se2.wrap_angle(truth[2]))))
                odom_msg = OdometryPose(stamp, odom[0], odom[1], float(se2.wrap_angle(odom[2])))
                rec.write(TOPIC_ODOM, odom_msg)
                nav.on_odometry(as_recorded(odom_msg))  # exactly what a replay reads back
                if nav.image_due():
                    image = the_world.render(truth, rng_noise)
                    rec.write(TOPIC_CAMERA_IMAGE, CameraImage(stamp, image, "camera", "png"))
                    rec.write(TOPIC_NAV_LOCALIZATION, localization_message(stamp, nav.on_image(image)))
                cmd = nav.control(dt)
                stop = cmd.reached or blocked or k == ticks - 1
                v, w = (0.0, 0.0) if stop else (cmd.linear_mps, cmd.angular_radps)
                rec.write(TOPIC_CMD_VEL, VelocityCommand(stamp, v, w))
                if progress is not None:
                    progress(k + 1, ticks)
                if stop:
                    break
                moved = truth + arc_step(truth[2], v, w, dt)
                if not through_walls and not the_world.is_free(moved[:2], clearance_m):
                    collided = blocked = True  # the bumper: the robot stays put, the run ends at the next tick
                    moved = truth.copy()
                elif not the_world.is_free(moved[:2], 0.0):
                    collided = True
                odometry.step(se2.between(truth, moved))
                truth = moved
                trail.append(truth[:2].copy())
            messages = rec.message_count
    except RecorderError as err:
        raise ReplayError(str(err)) from err
    ref = reference_path(nav_map.topomap, nav.route.nodes, cfg.follower.spacing_m)
    xt = distance_to_polyline(np.array(trail), ref.xy)
    return NavigateSummary(Path(out), messages, nav.route.nodes, nav.route.length_m, k * dt, nav.images,
                           nav.matches, nav.corrections, nav.reached, collided,
                           float(np.hypot(*(truth[:2] - ref.goal_xy))),
                           float(xt.mean()), float(xt.max()), float(xt[-1]), ref.frame)


def as_recorded(msg: OdometryPose) -> NDArray[np.float64]:
    """``[x, y, yaw]`` of a pose as it reads back from a recording (the heading is stored as a
    quaternion about +z, as :mod:`slamreplay.recorder.codec.protobuf` does: it comes back a few ulps off)."""
    half = 0.5 * msg.yaw_rad
    return np.array([msg.x_m, msg.y_m, yaw_from_quaternion(math.cos(half), 0.0, 0.0, math.sin(half))])


def localization_message(stamp_ns: int, update: NavUpdate) -> NavLocalization:
    """The recorded form of one :class:`NavUpdate`."""
    p = update.pose
    return NavLocalization(stamp_ns, float(p[0]), float(p[1]), float(p[2]), update.node, update.dx_px,
                           update.deviation_rad, update.corrected)
