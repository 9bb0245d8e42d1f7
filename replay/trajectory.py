"""Drawing a growing trajectory in Rerun at a bounded cost.

Re-logging the whole polyline at every step costs O(n^2). Instead a point is kept only when
the robot has moved ``min_spacing_m`` from the last kept one (a polyline needs no 100 Hz
samples), the full polyline is logged at ``checkpoints`` evenly spaced sizes, and at every
kept point only the tail since the last checkpoint goes to ``<path>/tail``: at any time cursor
the two together show the whole trajectory so far.
"""

from __future__ import annotations

import math

import numpy as np

from algorithms.observe import LineStrips
from replay.pipeline import ReplayObserver


class TrajectoryLog:
    """One growing polyline on entity ``path``."""

    def __init__(self, observer: ReplayObserver, path: str, expected_points: int, checkpoints: int = 100,
                 min_spacing_m: float = 0.05) -> None:
        self.observer, self.path = observer, path
        self.min_spacing_m = min_spacing_m
        self.every = max(1, expected_points // checkpoints)
        self.points: list[tuple[float, float]] = []
        self._checkpoint = 0
        self._pending: tuple[float, float] | None = None

    def append(self, x: float, y: float) -> None:
        """Offer a point (at the observer's current time); draw when it is kept."""
        if self.points and math.hypot(x - self.points[-1][0], y - self.points[-1][1]) < self.min_spacing_m:
            self._pending = (x, y)
            return
        self._pending = None
        self.points.append((x, y))
        n = len(self.points)
        if n - self._checkpoint >= self.every:
            self.observer.log(self.path, LineStrips((np.asarray(self.points),)))
            self._checkpoint = n - 1
        self.observer.log(f"{self.path}/tail", LineStrips((np.asarray(self.points[self._checkpoint:]),)))

    def finish(self) -> None:
        """Draw the whole polyline, ending at the last offered point, at the current time."""
        if self._pending is not None:
            self.points.append(self._pending)
            self._pending = None
        if self.points:
            self.observer.log(self.path, LineStrips((np.asarray(self.points),)))
            self.observer.log(f"{self.path}/tail", LineStrips(()))
