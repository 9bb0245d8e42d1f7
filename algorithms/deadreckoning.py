"""Dead reckoning: the robot pose from odometry alone, the baseline every SLAM must beat."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from slamreplay.algorithms.common import se2


@dataclass(frozen=True, slots=True)
class DeadReckoningConfig:
    """No parameters: dead reckoning composes odometry increments exactly."""


class DeadReckoning:
    """Compose odometry increments onto a known start pose.

    With cumulative odometry poses o_0, o_1, ... (odom frame) and the start pose T0 (map
    frame), the estimate is x_k = T0 ⊕ (⊖o_0 ⊕ o_k): the odometry trajectory moved rigidly
    so that it starts at T0.
    """

    def __init__(self, start_pose: ArrayLike, config: DeadReckoningConfig = DeadReckoningConfig()) -> None:
        start = np.asarray(start_pose, dtype=np.float64)
        if start.shape != (3,) or not np.all(np.isfinite(start)):
            raise ValueError(f"start_pose must be a finite (3,) [x, y, theta], got {start!r}")
        self.config = config
        self._start = start
        self._first_odom: NDArray[np.float64] | None = None
        self._inv_first = (0.0, 0.0, 0.0)
        sx, sy, sth = (float(v) for v in start)
        self._start_f = (sx, sy, sth)

    def step(self, odom_pose: ArrayLike) -> NDArray[np.float64]:
        """The pose estimate after the cumulative odometry pose ``odom_pose`` ([x, y, theta])."""
        o = np.asarray(odom_pose, dtype=np.float64)
        if o.shape != (3,):
            raise ValueError(f"odom_pose must be a (3,) [x, y, theta], got shape {o.shape}")
        if self._first_odom is None:
            self._first_odom = o
            ix, iy, ith = (float(v) for v in se2.inverse(o))
            self._inv_first = (ix, iy, ith)
        # se2.compose(start, se2.between(first, o)) on Python floats: the same formulas, evaluated in the same
        # order, without numpy's per-call overhead on 3-vectors (this runs at the odometry rate)
        ix, iy, ith = self._inv_first
        x, y, th = o.tolist()
        c, s = math.cos(ith), math.sin(ith)
        bx, by, bth = ix + c * x - s * y, iy + s * x + c * y, _wrap(ith + th)
        sx, sy, sth = self._start_f
        c, s = math.cos(sth), math.sin(sth)
        return np.array([sx + c * bx - s * by, sy + s * bx + c * by, _wrap(sth + bth)])


def _wrap(theta: float) -> float:
    """se2.wrap_angle of one float (the same operations: half-open [-pi, pi))."""
    w = (theta + math.pi) % (2.0 * math.pi) - math.pi
    return w - 2.0 * math.pi if w >= math.pi else w
