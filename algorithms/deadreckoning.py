"""Dead reckoning: the robot pose from odometry alone, the baseline every SLAM must beat."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from algorithms.common import se2


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

    def step(self, odom_pose: ArrayLike) -> NDArray[np.float64]:
        """The pose estimate after the cumulative odometry pose ``odom_pose`` ([x, y, theta])."""
        o = np.asarray(odom_pose, dtype=np.float64)
        if self._first_odom is None:
            self._first_odom = o
        return se2.compose(self._start, se2.between(self._first_odom, o))
