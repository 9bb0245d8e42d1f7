"""Navigation mode of the topo-metric map: route, qualitative position, guidance (section IV of [1]_).

Pure numpy, no I/O. The pieces, in the paper's order:

- :func:`plan_route`: Dijkstra over the map's nodes "taking into account the orientation of
  the robot in each node" (IV-A). States are (node, heading of arrival); see its docstring
  for the cost rule.
- :func:`heading_deviation_rad`: the qualitative direction read off the x-translation in pixels
  between the current image and the matched map image with "a rough camera calibration (only
  based on image size and camera vision field)" (IV-B, Fig. 3).
- :class:`QualitativePose`: on a loop closure the position is the node's, the heading the
  node's corrected by that deviation; between loop closures, the last corrected pose composed
  with the odometry since then (IV-B).
- :mod:`slamreplay.algorithms.topometric.pathfollow`: the global path discretized every centimetre, the
  local path, the target point and the PID (IV-C).
- :class:`Navigator`: ties them together around a pluggable image localizer (image and odometry
  since the last image -> :class:`VisualMatch` or None), so the closed-loop runner and the replay
  pipeline run the same code and give the same outputs.

The navigation-mode loop-closure detector itself (bag of words, filter, 2-point RANSAC with the
translation threshold off) is :class:`slamreplay.algorithms.topometric.navigation.Localizer`; the replay
layer adapts it to :data:`ImageLocalizer`.

References
----------
.. [1] E. Battesti, S. Bazeille, D. Filliat, "Qualitative localization using vision and odometry for
   path following in topo-metric maps", ECMR 2011, section IV.
"""

from __future__ import annotations

import heapq
import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from slamreplay.algorithms.common import se2
from slamreplay.algorithms.observe import NULL_OBSERVER, LineStrips, Observer, Points, Pose, Scalar
from slamreplay.algorithms.topometric.pathfollow import Command, FollowerConfig, PathFollower, discretize

F64 = NDArray[np.float64]


# ---------------------------------------------------------------------------------------
# The map as a graph, and Dijkstra with orientation (IV-A)


@dataclass(frozen=True, slots=True, eq=False)
class NavGraph:
    """What navigation needs of a topo-metric map: node poses (map frame) and undirected edges.

    Parameters
    ----------
    poses : (n, 3) ``[x_m, y_m, yaw_rad]`` of each location (the relaxed poses); the yaw is the
        direction the camera looked when the location's image was recorded.
    edges : (m, 2) int node indices; each is travelled both ways.
    """

    poses: F64
    edges: NDArray[np.int64]

    def __post_init__(self) -> None:
        poses = np.array(self.poses, dtype=np.float64, copy=True)
        if poses.ndim != 2 or poses.shape[1] != 3 or not np.all(np.isfinite(poses)):
            raise ValueError(f"poses must be a finite (n, 3) array, got shape {poses.shape}")
        edges = np.array(self.edges, dtype=np.int64, copy=True).reshape(-1, 2)
        if edges.size and (edges.min() < 0 or edges.max() >= len(poses)):
            raise ValueError(f"edges must index the {len(poses)} poses, got indices in "
                             f"[{edges.min()}, {edges.max()}]")
        poses.flags.writeable = False
        edges.flags.writeable = False
        object.__setattr__(self, "poses", poses)
        object.__setattr__(self, "edges", edges)

    @property
    def n_nodes(self) -> int:
        return len(self.poses)


@dataclass(frozen=True, slots=True)
class RouteConfig:
    """Costs of :func:`plan_route` (metres and metres per radian)."""

    turn_cost_m_per_rad: float = 0.5  # a half turn costs as much as ~1.6 m of driving
    against_map_factor: float = 4.0  # an edge driven against the recorded view costs this many times its length
    min_edge_m: float = 0.01  # shorter edges are rotations on the spot: they travel along the node's heading

    def __post_init__(self) -> None:
        if not (self.turn_cost_m_per_rad >= 0 and self.against_map_factor >= 1 and self.min_edge_m > 0):
            raise ValueError("turn_cost_m_per_rad must be >= 0, against_map_factor >= 1 and min_edge_m > 0")


@dataclass(frozen=True, slots=True)
class Route:
    """A planned route: the node sequence, its cost and its length (m)."""

    nodes: tuple[int, ...]
    cost: float
    length_m: float


def plan_route(graph: NavGraph, start: int, goal: int, start_yaw: float | None = None,
               cfg: RouteConfig = RouteConfig()) -> Route | None:
    """Cheapest node sequence from ``start`` to ``goal``, orientation included (Dijkstra).

    The paper computes the path "using Dijkstra algorithm [13], taking into account the
    orientation of the robot in each node" (section IV-A) without giving the rule. Ours:
    a search state is (node, heading on arrival), so the search runs over directed edges.
    Driving edge i -> j sets the heading to the bearing from i to j (to node j's recorded
    heading when the edge is shorter than ``min_edge_m``: a rotation on the spot) and costs

        length * (against_map_factor if that heading is more than 90 deg from node j's
        recorded heading, else 1) + turn_cost_m_per_rad * |heading change at i|.

    The first term keeps a route from reversing through a corridor against the recorded
    views (the camera would then see nothing it knows, so no loop closure corrects the
    odometry) unless there is no other way; the second prefers straight routes and counts
    the initial turn from ``start_yaw`` (default: the start node's recorded heading).
    Ties break on the state index, so the result is deterministic.

    Returns None when the goal cannot be reached; raises ValueError for a bad node index.
    """
    n = graph.n_nodes
    for name, node in (("start", start), ("goal", goal)):
        if not 0 <= node < n:
            raise ValueError(f"{name} node {node} is not in the map (it has nodes 0..{n - 1})")
    p = graph.poses
    heading0 = float(p[start, 2] if start_yaw is None else start_yaw)
    if start == goal:
        return Route((start,), 0.0, 0.0)
    # Directed edges: both directions of every undirected edge, self-loops and duplicates dropped.
    e = graph.edges[graph.edges[:, 0] != graph.edges[:, 1]]
    directed = np.unique(np.concatenate([e, e[:, ::-1]]), axis=0) if len(e) else np.zeros((0, 2), np.int64)
    src, dst = directed[:, 0], directed[:, 1]
    d = p[dst, :2] - p[src, :2]
    length = np.hypot(d[:, 0], d[:, 1])
    heading = np.where(length >= cfg.min_edge_m, np.arctan2(d[:, 1], d[:, 0]), p[dst, 2])
    against = (length >= cfg.min_edge_m) & (np.abs(se2.wrap_angle(heading - p[dst, 2])) > 0.5 * np.pi)
    drive = length * np.where(against, cfg.against_map_factor, 1.0)
    out_of: list[list[int]] = [[] for _ in range(n)]
    for k, i in enumerate(src.tolist()):
        out_of[i].append(k)
    # State m < len(directed): arrived by directed edge m; state len(directed): at the start.
    m0 = len(directed)
    best = np.full(m0 + 1, np.inf)
    parent = np.full(m0 + 1, -1, np.int64)
    best[m0] = 0.0
    queue: list[tuple[float, int]] = [(0.0, m0)]
    while queue:
        cost, s = heapq.heappop(queue)
        if cost > best[s]:
            continue
        node, yaw = (start, heading0) if s == m0 else (int(dst[s]), float(heading[s]))
        if node == goal:
            chain = []
            while s != m0:
                chain.append(int(dst[s]))
                s = int(parent[s])
            nodes = (start, *reversed(chain))
            steps = np.diff(p[list(nodes), :2], axis=0)
            return Route(nodes, float(cost), float(np.hypot(steps[:, 0], steps[:, 1]).sum()))
        for k in out_of[node]:
            c = cost + float(drive[k]) + cfg.turn_cost_m_per_rad * abs(float(se2.wrap_angle(heading[k] - yaw)))
            if c < best[k]:
                best[k], parent[k] = c, s
                heapq.heappush(queue, (c, k))
    return None


# ---------------------------------------------------------------------------------------
# Qualitative localization (IV-B)


def heading_deviation_rad(dx_px: float, width_px: int, hfov_rad: float, rule: str = "linear") -> float:
    """Angle between the current and the recorded view direction, from the image x-translation.

    The paper assumes "that the image movement is caused only by a rotation of the robot" and
    converts the x-translation with "a rough camera calibration (only based on image size and
    camera vision field)" (section IV-B, Fig. 3: 33 px in a 320 px wide image give 4.73 deg).

    ``rule="linear"`` (the default, the paper's): ``dx_px * hfov_rad / width_px``; with the
    Canon VC-C50i's 46 deg wide angle it gives 4.74 deg for Fig. 3's 33 px, and Fig. 3's numbers
    imply hfov = 45.9 deg. ``rule="pinhole"``: ``atan(dx_px / f)`` with
    ``f = width_px / 2 / tan(hfov / 2)``: 5.00 deg at 46 deg (it would need hfov = 43.7 deg).

    Sign: ``dx_px`` > 0 when the scene appears shifted towards +x (right) in the current image
    relative to the map image, which a turn to the left (counter-clockwise, positive yaw) does;
    the result is then positive.
    """
    if width_px <= 0 or not 0 < hfov_rad < math.pi:
        raise ValueError(f"width_px must be > 0 and hfov_rad in (0, pi), got {width_px}, {hfov_rad}")
    if rule == "linear":
        return float(dx_px) * hfov_rad / width_px
    if rule == "pinhole":
        return math.atan(float(dx_px) * 2.0 * math.tan(0.5 * hfov_rad) / width_px)
    raise ValueError(f"rule must be 'linear' or 'pinhole', got {rule!r}")


@dataclass(frozen=True, slots=True)
class VisualMatch:
    """A navigation-mode loop closure: the matched map node and the 2D image motion.

    ``dx_px`` is in pixels of the image handed to the localizer, with the sign convention of
    :func:`heading_deviation_rad`.
    """

    node: int
    dx_px: float
    rotation_rad: float = 0.0
    scale: float = 1.0
    inliers: int = 0


# image (H, W) uint8, odometry [dx, dy, dyaw] since the previous image in its robot frame (None
# at the first image) -> the match or None.
ImageLocalizer = Callable[[NDArray[np.uint8], F64 | None], VisualMatch | None]


class QualitativePose:
    """The qualitative position estimate of section IV-B, in the map frame.

    On a loop closure with node k the pose becomes node k's position with node k's heading
    plus the deviation; between loop closures it is that pose composed with the odometry
    accumulated since (``se2.between(odom_at_correction, odom_now)``).
    """

    def __init__(self, start_pose: ArrayLike, odom: ArrayLike) -> None:
        self.anchor = np.asarray(start_pose, np.float64).copy()
        self.anchor_odom = np.asarray(odom, np.float64).copy()
        self.pose = self.anchor.copy()

    def predict(self, odom: ArrayLike) -> F64:
        """The pose at odometry reading ``odom`` (cumulative, odom frame)."""
        self.pose = se2.compose(self.anchor, se2.between(self.anchor_odom, np.asarray(odom, np.float64)))
        return self.pose.copy()

    def correct(self, node_pose: ArrayLike, deviation_rad: float, odom: ArrayLike, keep_along_m: float = 0.0) -> F64:
        """Loop closure at odometry reading ``odom``: the node's position, its heading plus the deviation.

        ``keep_along_m`` > 0 (beyond the paper): keep the estimate's offset from the node along the
        node's recorded heading, clamped to +-``keep_along_m``; only the offset across it is reset.
        """
        node = np.asarray(node_pose, np.float64)
        u = np.array([math.cos(node[2]), math.sin(node[2])])
        along = float(np.clip((self.pose[:2] - node[:2]) @ u, -keep_along_m, keep_along_m))
        xy = node[:2] + along * u
        self.anchor = np.array([xy[0], xy[1], float(se2.wrap_angle(node[2] + deviation_rad))])
        self.anchor_odom = np.asarray(odom, np.float64).copy()
        self.pose = self.anchor.copy()
        return self.pose.copy()


# ---------------------------------------------------------------------------------------
# The navigator


@dataclass(frozen=True, slots=True)
class GuidanceConfig:
    """Parameters of :class:`Navigator`."""

    hfov_deg: float = 46.0  # camera field of view (Canon VC-C50i wide angle; Fig. 3)
    deviation_rule: str = "linear"  # see heading_deviation_rad
    visual_correction: bool = True  # False: odometry only (the paper's Fig. 4 comparison)
    # An image each time odometry says the robot moved this far or turned this much. The paper: 50 cm or
    # 10 deg (section V), 40 cm in Fig. 6. Beyond the paper, 0.3 m by measurement (docs/topometric.md: with
    # the paper's localization rule, mean cross-track 0.023 m against 0.042 m at 0.5 m on the 0 -> 38 drive,
    # 0.101 m against 0.134 m on the 5 -> 72 shortcut, 3 seeds each).
    image_every_m: float = 0.3
    image_every_deg: float = 10.0
    max_correction_m: float = 0.0  # > 0: ignore a match whose node is farther than this from the estimate
    # 0 = the paper's rule (IV-B), the default: a correction puts the position on the node's. > 0 (beyond the
    # paper): keep the estimate's offset from the node along the node's heading, clamped to +-keep_along_m,
    # since the detector often matches a node 0.5-0.8 m ahead. Measured (docs/topometric.md, 3 seeds each):
    # 1.0 m gave mean cross-track 0.016 m against 0.023 m on the 0 -> 38 drive but 0.189 m against 0.101 m on
    # the 5 -> 72 shortcut, so the paper's rule is the default.
    keep_along_m: float = 0.0
    route: RouteConfig = field(default_factory=RouteConfig)
    follower: FollowerConfig = field(default_factory=FollowerConfig)

    def __post_init__(self) -> None:
        if not 0 < self.hfov_deg < 180:
            raise ValueError(f"hfov_deg must be in (0, 180), got {self.hfov_deg}")
        if self.deviation_rule not in ("linear", "pinhole"):
            raise ValueError(f"deviation_rule must be 'linear' or 'pinhole', got {self.deviation_rule!r}")
        if not (self.image_every_m > 0 and self.image_every_deg > 0 and self.max_correction_m >= 0):
            raise ValueError("image_every_m and image_every_deg must be > 0, max_correction_m >= 0")
        if not (math.isfinite(self.keep_along_m) and self.keep_along_m >= 0):
            raise ValueError(f"keep_along_m must be finite and >= 0 (0: the paper's rule), got {self.keep_along_m}")


@dataclass(frozen=True, slots=True, eq=False)
class NavUpdate:
    """What one processed image gave: the estimate after it, and the match (node -1: none)."""

    pose: F64  # (3,) map frame
    node: int
    dx_px: float
    deviation_rad: float
    corrected: bool  # the match moved the estimate (visual correction on, within max_correction_m)


class Navigator:
    """Path following on a topo-metric map with the qualitative localization (section IV).

    Call, in time order: :meth:`on_odometry` with every cumulative odometry reading,
    :meth:`on_image` with every image taken (:meth:`image_due` says when one is due), and
    :meth:`control` once per control period. Deterministic given the inputs and the localizer.

    Parameters
    ----------
    graph : the map.
    start, goal : node indices; the robot starts at the start node's pose.
    localizer : see :data:`ImageLocalizer`; None: no vision at all.
    cfg : parameters.
    start_odom : the odometry reading at the start.
    observer : receives ``world/nav/...`` and ``topo/nav/...`` observations.

    Raises
    ------
    ValueError
        When a node is not in the map or the goal cannot be reached from the start.
    """

    def __init__(self, graph: NavGraph, start: int, goal: int, localizer: ImageLocalizer | None,
                 cfg: GuidanceConfig | None = None, start_odom: ArrayLike = (0.0, 0.0, 0.0),
                 observer: Observer = NULL_OBSERVER) -> None:
        self.graph, self.localizer, self.observer = graph, localizer, observer
        self.cfg = cfg = cfg or GuidanceConfig()
        route = plan_route(graph, start, goal, cfg=cfg.route)
        if route is None:
            raise ValueError(f"goal node {goal} cannot be reached from start node {start}: the map has no path")
        self.route = route
        self.route_xy = graph.poses[list(route.nodes), :2].copy()
        self.global_path = discretize(self.route_xy, cfg.follower.spacing_m)
        self.odom = np.asarray(start_odom, np.float64).copy()
        self.position = QualitativePose(graph.poses[start], self.odom)
        self.follower = PathFollower(self.global_path, cfg.follower)
        self.last_image_odom: F64 | None = None
        self.images = self.matches = self.corrections = 0
        self.local_path = self.follower.replan(self.position.pose)
        observer.log("world/nav/global_path", LineStrips((self.global_path,)))
        observer.log("world/nav/route", Points(self.route_xy, labels=tuple(str(k) for k in route.nodes)))

    @property
    def estimate(self) -> F64:
        """The current pose estimate (3,), map frame."""
        return self.position.pose.copy()

    @property
    def reached(self) -> bool:
        return self.follower.reached

    def on_odometry(self, odom: ArrayLike) -> F64:
        """A new cumulative odometry reading; returns the estimate."""
        self.odom = np.asarray(odom, np.float64).copy()
        return self.position.predict(self.odom)

    def image_due(self) -> bool:
        """Whether odometry moved ``image_every_m`` or turned ``image_every_deg`` since the last image."""
        if self.last_image_odom is None:
            return True
        rel = se2.between(self.last_image_odom, self.odom)
        return bool(math.hypot(rel[0], rel[1]) >= self.cfg.image_every_m
                    or abs(math.degrees(rel[2])) >= self.cfg.image_every_deg)

    def on_image(self, pixels: NDArray[np.uint8]) -> NavUpdate:
        """Process one image: localize (section IV-B), then recompute the local path (IV-C)."""
        motion = None if self.last_image_odom is None else se2.between(self.last_image_odom, self.odom)
        self.last_image_odom = self.odom.copy()
        self.images += 1
        match = self.localizer(pixels, motion) if self.localizer is not None else None
        node, dx, dev, corrected = -1, 0.0, 0.0, False
        if match is not None:
            if not 0 <= match.node < self.graph.n_nodes:
                raise ValueError(f"localizer returned node {match.node}, not in the map")
            self.matches += 1
            node, dx = int(match.node), float(match.dx_px)
            dev = heading_deviation_rad(dx, int(pixels.shape[1]), math.radians(self.cfg.hfov_deg),
                                        self.cfg.deviation_rule)
            node_pose = self.graph.poses[node]
            jump = math.hypot(*(node_pose[:2] - self.position.pose[:2]))
            if self.cfg.visual_correction and not (0 < self.cfg.max_correction_m < jump):
                self.position.correct(node_pose, dev, self.odom, self.cfg.keep_along_m)
                self.corrections += 1
                corrected = True
            self.observer.log("topo/nav/heading_correction_deg", Scalar(math.degrees(dev)))
            self.observer.log("world/nav/matched_node", Pose(node_pose.copy(), label=str(node)))
        self.local_path = self.follower.replan(self.position.pose)
        self.observer.log("world/nav/local_path", LineStrips((self.local_path,)))
        return NavUpdate(self.position.pose.copy(), node, dx, dev, corrected)

    def control(self, dt_s: float) -> Command:
        """The velocity command for the next ``dt_s`` seconds (target point and PID, section IV-C)."""
        cmd = self.follower.command(self.position.pose, dt_s)
        if cmd.target is not None:
            self.observer.log("world/nav/target", Points(cmd.target[None, :]))
        return cmd
