"""Drawing a growing trajectory in Rerun at a bounded cost.

Re-logging the whole polyline at every step costs O(n^2). Instead the full polyline is
logged at ``checkpoints`` evenly spaced times and, at every step, only the tail since the
last checkpoint goes to ``<path>/tail``: at any time cursor the two together show the whole
trajectory so far, for O(n * n / checkpoints) points in total.
"""

from __future__ import annotations

import numpy as np

from algorithms.observe import LineStrips
from replay.pipeline import ReplayObserver


class TrajectoryLog:
    """One growing polyline on entity ``path``."""

    def __init__(self, observer: ReplayObserver, path: str, expected_points: int, checkpoints: int = 100) -> None:
        self.observer, self.path = observer, path
        self.every = max(1, expected_points // checkpoints)
        self.points: list[tuple[float, float]] = []
        self._checkpoint = 0

    def append(self, x: float, y: float) -> None:
        """Add a point (at the observer's current time) and draw."""
        self.points.append((x, y))
        n = len(self.points)
        if n - self._checkpoint >= self.every:
            self.observer.log(self.path, LineStrips((np.asarray(self.points),)))
            self._checkpoint = n - 1
        self.observer.log(f"{self.path}/tail", LineStrips((np.asarray(self.points[self._checkpoint:]),)))

    def array(self) -> np.ndarray:
        return np.asarray(self.points, dtype=np.float64).reshape(-1, 2)
