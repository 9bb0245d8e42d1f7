"""Path following of the topo-metric navigation mode (Bazeille, Battesti, Filliat, 2011, section IV-C).

"The path linking this sequence of nodes is then discretized each centimeter to form the
global path [...]. The local path is a line between the position and a point of the global
path situated at 40 cm in front of the robot to which we add the global path after this
point. [...] the first point in the local path situated at more than 20 cm of the robot is
selected as a target. A heading direction error between this point and the robot position is
computed and used to estimate the rotation speed by using a PID controller. As the robot
translation speed is set to a constant [...]."

Choices the paper leaves open, stated here:

- "In front of the robot" is measured along the global path from the global-path point closest
  to the position, searched in a window around the previous one (``search_back_m``,
  ``search_ahead_m``) so a path that passes near itself is not short-cut.
- The target is the first local-path point *after the one closest to the robot* farther than
  20 cm (the local path starts where the robot was when it was computed, which soon lies
  behind it); none farther: the path's last point.
- The PID runs on the wrapped heading error, with the integral clamped (anti-windup) and the
  output saturated at ``max_angular_radps``.
- Beyond the paper: when the heading error exceeds ``turn_in_place_deg`` the forward speed is 0
  (a Pioneer turns on the spot; driving on at full speed would sweep a wide arc into a wall).
- The goal is reached when the position is within ``goal_tolerance_m`` of the path's end, or
  when the robot has passed it (progress at the end and the end behind the robot).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import cast

import numpy as np
from numpy.typing import ArrayLike, NDArray

from slamreplay.algorithms.common import se2

F64 = NDArray[np.float64]


def discretize(points: ArrayLike, spacing_m: float = 0.01) -> F64:
    """Resample a polyline (k, 2) every ``spacing_m`` of arc length (section IV-C: every centimetre).

    The first and last points are kept; consecutive duplicates are dropped first. The last
    interval is shorter than ``spacing_m`` unless the length is a multiple of it.
    """
    if not spacing_m > 0:
        raise ValueError(f"spacing_m must be > 0, got {spacing_m}")
    p = np.asarray(points, np.float64).reshape(-1, 2)
    if len(p) == 0 or not np.all(np.isfinite(p)):
        raise ValueError("points must be a non-empty finite (k, 2) array")
    seg = np.hypot(*np.diff(p, axis=0).T)
    keep = np.concatenate([[True], seg > 1e-12])
    p = p[keep]
    if len(p) == 1:
        return cast(F64, p.copy())
    s = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(p, axis=0).T))])
    n = math.floor(s[-1] / spacing_m + 1e-9)
    q = np.arange(n + 1) * spacing_m
    if s[-1] - q[-1] > 1e-9:
        q = np.append(q, s[-1])
    return np.stack([np.interp(q, s, p[:, 0]), np.interp(q, s, p[:, 1])], -1)


def distance_to_polyline(points: ArrayLike, polyline: ArrayLike) -> F64:
    """Shortest distance (m) of each point (n, 2) to a polyline (k, 2): the cross-track error."""
    pts = np.asarray(points, np.float64).reshape(-1, 2)
    line = np.asarray(polyline, np.float64).reshape(-1, 2)
    if len(line) == 1:
        return cast(F64, np.hypot(*(pts - line[0]).T))
    a, b = line[:-1], line[1:]
    ab = b - a
    denom = np.maximum(np.sum(ab * ab, axis=1), 1e-18)
    out = np.empty(len(pts))
    for start in range(0, len(pts), 512):  # bounded memory: 512 x k segments at a time
        p = pts[start:start + 512, None, :]
        t = np.clip(np.sum((p - a) * ab, axis=2) / denom, 0.0, 1.0)
        d = p - (a + t[..., None] * ab)
        out[start:start + 512] = np.sqrt(np.min(np.sum(d * d, axis=2), axis=1))
    return out


@dataclass(frozen=True, slots=True)
class FollowerConfig:
    """Parameters of :class:`PathFollower`; distances in metres, angles in radians unless named."""

    spacing_m: float = 0.01  # global-path discretization (IV-C)
    lookahead_m: float = 0.40  # the local path joins the global path this far ahead (IV-C)
    target_distance_m: float = 0.20  # the target is the first local-path point farther than this (IV-C)
    linear_speed_mps: float = 0.3  # constant forward speed (IV-C)
    kp: float = 2.0  # rad/s per rad of heading error; ~ pure pursuit's 2 v / d at 0.3 m/s and 0.2 m ...
    ki: float = 0.1  # ... a small integral against a steady turn bias ...
    kd: float = 0.05  # ... and a little damping
    integral_limit: float = 0.5  # rad s: anti-windup clamp of the error integral
    max_angular_radps: float = 1.5
    turn_in_place_deg: float = 60.0  # beyond the paper: above this heading error, turn on the spot
    goal_tolerance_m: float = 0.10
    search_back_m: float = 0.5
    search_ahead_m: float = 3.0

    def __post_init__(self) -> None:
        positive = ("spacing_m", "lookahead_m", "target_distance_m", "linear_speed_mps", "max_angular_radps",
                    "goal_tolerance_m", "search_ahead_m")
        for name in positive:
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)}")
        for name in ("kp", "ki", "kd", "integral_limit", "search_back_m"):
            if not getattr(self, name) >= 0:
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)}")
        if not 0 < self.turn_in_place_deg <= 180:
            raise ValueError(f"turn_in_place_deg must be in (0, 180], got {self.turn_in_place_deg}")


@dataclass(frozen=True, slots=True)
class Command:
    """One control output: velocities, the target point and the heading error behind them."""

    linear_mps: float
    angular_radps: float
    target: F64 | None  # (2,) map frame; None once the goal is reached
    heading_error_rad: float
    reached: bool


class PathFollower:
    """Local path, target point and PID heading control along a discretized global path (IV-C)."""

    def __init__(self, global_path: ArrayLike, cfg: FollowerConfig = FollowerConfig()) -> None:
        path = np.asarray(global_path, np.float64).reshape(-1, 2)
        if len(path) == 0:
            raise ValueError("global_path must hold at least one point")
        self.cfg = cfg
        self.path = path
        self.progress = 0  # index of the global-path point closest to the position
        self.local = path.copy()
        self.local_progress = 0
        self.integral = 0.0
        self.previous_error: float | None = None
        self.reached = False

    def _closest(self, pts: F64, xy: F64, lo: int, hi: int) -> int:
        lo, hi = max(lo, 0), min(hi, len(pts))
        d = np.sum((pts[lo:hi] - xy) ** 2, axis=1)
        return lo + int(np.argmin(d))

    def replan(self, pose: ArrayLike) -> F64:
        """The local path from ``pose`` (section IV-C): a line to the global-path point
        ``lookahead_m`` ahead of the closest one, then the global path after it; (k, 2)."""
        xy = np.asarray(pose, np.float64)[:2]
        per_m = 1.0 / self.cfg.spacing_m
        self.progress = self._closest(self.path, xy, self.progress - int(self.cfg.search_back_m * per_m),
                                      self.progress + int(self.cfg.search_ahead_m * per_m) + 1)
        join = min(self.progress + round(self.cfg.lookahead_m * per_m), len(self.path) - 1)
        line = discretize(np.stack([xy, self.path[join]]), self.cfg.spacing_m)
        self.local = np.concatenate([line, self.path[join + 1:]])
        self.local_progress = 0
        return self.local.copy()

    def command(self, pose: ArrayLike, dt_s: float) -> Command:
        """Rotation speed by PID on the heading error to the target; constant forward speed."""
        if not dt_s > 0:
            raise ValueError(f"dt_s must be > 0, got {dt_s}")
        p = np.asarray(pose, np.float64)
        xy, yaw = p[:2], float(p[2])
        cfg = self.cfg
        end = self.path[-1]
        if self.reached:
            return Command(0.0, 0.0, None, 0.0, True)
        per_m = 1.0 / cfg.spacing_m
        self.local_progress = self._closest(self.local, xy, self.local_progress,
                                            self.local_progress + int(cfg.search_ahead_m * per_m) + 1)
        to_end = end - xy
        at_end = self.local_progress == len(self.local) - 1
        if math.hypot(*to_end) <= cfg.goal_tolerance_m or (
                at_end and to_end @ np.array([math.cos(yaw), math.sin(yaw)]) < 0):
            self.reached = True
            return Command(0.0, 0.0, None, 0.0, True)
        ahead = self.local[self.local_progress:]
        far = np.flatnonzero(np.sum((ahead - xy) ** 2, axis=1) > cfg.target_distance_m ** 2)
        target = ahead[far[0]] if len(far) else self.local[-1]
        error = float(se2.wrap_angle(math.atan2(target[1] - xy[1], target[0] - xy[0]) - yaw))
        self.integral = float(np.clip(self.integral + error * dt_s, -cfg.integral_limit, cfg.integral_limit))
        derivative = 0.0 if self.previous_error is None else \
            float(se2.wrap_angle(error - self.previous_error)) / dt_s
        self.previous_error = error
        w = cfg.kp * error + cfg.ki * self.integral + cfg.kd * derivative
        w = float(np.clip(w, -cfg.max_angular_radps, cfg.max_angular_radps))
        v = 0.0 if abs(error) > math.radians(cfg.turn_in_place_deg) else cfg.linear_speed_mps
        return Command(v, w, target.copy(), error, False)
