"""The floor plan, the teleoperated tours and the route-following controller of ``sim-corridor``.

Floor plan (metres, corridor centrelines; ``w`` is the corridor width)::

        y
     14 |         +------+  room A (door at x = 4.3)
        |         |      |
     10 |  +------|==||==|--------------+----------------------+   north corridor, y = 10
        |  |                            |                      |
 room B |  |          left loop         |     right loop       |
  (door |  |     (7 x 10 m, centre)     |  (9 x 10 m, centre)  |
  y = 5)|  |                            |                      |
      0 |  +----------------------------+-----------+----------+   south corridor, y = 0
        |  x = 0 (west)            x = 7 (middle)   |x = 12    x = 16 (east)
     -3 |                                           +  dead end
        +----------------------------------------------------------> x

The robot starts at (0, 0) facing +x (world = odom frame at the start). Each tour starts and
ends there:

- ``outer``: the outer loop counter-clockwise (52 m);
- ``left``: the left loop counter-clockwise, up the middle corridor (34 m);
- ``right``: the right loop counter-clockwise, up the east corridor (52 m with the way there and back);
- ``right-cw``: the right loop clockwise: the north, east and south corridors in the opposite
  direction to the other tours (52 m);
- ``rooms``: the outer loop counter-clockwise with side trips into the dead end and both rooms,
  turning round in each (69 m).
"""

from __future__ import annotations

import math
from typing import Final

import numpy as np
from numpy.typing import NDArray

from slamreplay.recorder.sim.corridor_config import TOURS as TOURS  # re-exported

F64 = NDArray[np.float64]
Rect = tuple[float, float, float, float]  # x0, y0, x1, y1

SHARP_TURN_RAD: Final = math.radians(100.0)  # stop at the corner and turn on the spot
SHORT_LEG_M: Final = 3.5  # legs into rooms: stop at the corner too, so as to pass doors straight
TURN_IN_PLACE_RAD: Final = math.radians(40.0)


def floor_plan(width_m: float) -> list[Rect]:
    """The free space as a union of axis-aligned rectangles (module docstring's plan)."""
    h = 0.5 * width_m
    room_a_y0 = 10 + h + 0.3
    room_b_x1 = -h - 0.3
    return [
        (-h, -h, 16 + h, h), (-h, 10 - h, 16 + h, 10 + h),  # south, north
        (-h, -h, h, 10 + h), (7 - h, -h, 7 + h, 10 + h), (16 - h, -h, 16 + h, 10 + h),  # west, middle, east
        (12 - h, -3.5, 12 + h, 0.0),  # dead end
        (2.0, room_a_y0, 6.6, room_a_y0 + 3.2), (3.8, 10.0, 4.8, room_a_y0 + 0.1),  # room A and its door
        (room_b_x1 - 3.6, 3.0, room_b_x1, 7.0), (room_b_x1 - 0.1, 4.5, 0.0, 5.5),  # room B and its door
    ]


def route_waypoints(route: str, laps: int) -> F64:
    """Waypoints ``(n, 2)`` of the comma-separated ``route`` tours, repeated ``laps`` times."""
    names = [r.strip() for r in route.split(",")]
    points: list[tuple[float, float]] = [(0.0, 0.0)]
    for _ in range(laps):
        for name in names:
            points += [(float(x), float(y)) for x, y in TOURS[name][1:]]
    return np.array(points)


class PurePursuit:
    """Follows a waypoint polyline at a set speed, slowing for turns (a deterministic teleoperator).

    Smooth corners are cut by pure pursuit [1]_ with a look-ahead ``lookahead_m``; at sharp ones
    (more than 100 degrees, or leading into a short leg such as a doorway) the robot drives to the
    corner and turns on the spot. ``command`` returns ``(v, w)``; ``done`` is set at the last waypoint.

    References
    ----------
    .. [1] R. C. Coulter, "Implementation of the pure pursuit path tracking algorithm", CMU-RI-TR-92-01, 1992.
    """

    def __init__(self, waypoints: F64, speed_mps: float, max_turn_radps: float, lookahead_m: float) -> None:
        pts = np.asarray(waypoints, dtype=np.float64)
        keep = np.concatenate([[True], np.hypot(*np.diff(pts, axis=0).T) > 1e-9])
        self.points = pts[keep]
        if len(self.points) < 2:
            raise ValueError("waypoints must hold at least two distinct points")
        d = np.diff(self.points, axis=0)
        self.lengths = np.hypot(d[:, 0], d[:, 1])
        self.dirs = d / self.lengths[:, None]
        n = len(self.lengths)
        self.sharp = np.ones(n, dtype=bool)  # at the end of leg k; the last end is a stop
        for k in range(n - 1):
            turn = math.acos(float(np.clip(self.dirs[k] @ self.dirs[k + 1], -1.0, 1.0)))
            self.sharp[k] = turn > SHARP_TURN_RAD or self.lengths[k + 1] < SHORT_LEG_M or self.lengths[k] < SHORT_LEG_M
        self.speed, self.max_turn, self.lookahead = speed_mps, max_turn_radps, lookahead_m
        self.leg = 0
        self.done = False

    def _carrot(self, xy: F64) -> tuple[F64, float]:
        """The look-ahead point and the distance along the path left on the current leg."""
        k = self.leg
        s = float(np.clip((xy - self.points[k]) @ self.dirs[k], 0.0, self.lengths[k]))
        ahead = s + self.lookahead
        while ahead > self.lengths[k] and not self.sharp[k]:
            ahead -= self.lengths[k]
            k += 1
        ahead = min(ahead, float(self.lengths[k]))
        return self.points[k] + ahead * self.dirs[k], float(self.lengths[self.leg]) - s

    def command(self, pose: F64) -> tuple[float, float]:
        """Speed (m/s) and turn rate (rad/s) to apply from ``pose`` ``[x, y, yaw]``."""
        xy = np.asarray(pose[:2], dtype=np.float64)
        while not self.done:
            carrot, left = self._carrot(xy)
            corner = self.points[self.leg + 1]
            reached = float(np.hypot(*(corner - xy))) < 0.08 if self.sharp[self.leg] else left < 0.5 * self.lookahead
            if not reached:
                break
            if self.leg + 1 >= len(self.lengths):
                self.done = True
            else:
                self.leg += 1
        if self.done:
            return 0.0, 0.0
        delta = carrot - xy
        dist = float(np.hypot(*delta))
        alpha = float((math.atan2(delta[1], delta[0]) - pose[2] + math.pi) % (2 * math.pi) - math.pi)
        if abs(alpha) > TURN_IN_PLACE_RAD:
            return 0.0, math.copysign(self.max_turn, alpha)
        v = self.speed * max(0.25, 1.0 - abs(alpha) / TURN_IN_PLACE_RAD)
        if self.sharp[self.leg]:
            v = min(v, max(0.05, 0.8 * left))  # brake into a stop at the corner
        w = v * 2.0 * math.sin(alpha) / max(dist, 1e-3)
        if abs(w) > self.max_turn:
            v *= self.max_turn / abs(w)
            w = math.copysign(self.max_turn, w)
        return v, w
