"""A uniform grid over the feature estimates: the features near a point in time independent of N.

Data association with unknown ids (section 3.1 of [1]_) compares a scan with the mapped features
in the robot's vicinity; finding them by testing every feature is O(N) per scan. The grid keeps
each feature in the square cell of side ``cell_m`` that holds its estimate; a query visits the
cells overlapping the disc and tests only their features. Estimates move when the state is
recovered: the filter re-files the features a recovery changed (all of them after a global
solve).

References
----------
.. [1] Z. Wang, S. Huang, G. Dissanayake, "Implementation issues and experimental evaluation
   of D-SLAM", FSR 2005, section 3.1.
"""

from __future__ import annotations

import math
from typing import cast

import numpy as np
from numpy.typing import NDArray

F64 = NDArray[np.float64]


class Grid:
    """Features filed by the cell of their estimate."""

    def __init__(self, cell_m: float = 5.0) -> None:
        if not cell_m > 0:
            raise ValueError(f"cell_m must be > 0, got {cell_m}")
        self.cell_m = cell_m
        self.cells: dict[tuple[int, int], set[int]] = {}
        self.where: list[tuple[int, int] | None] = []

    def file(self, features: list[int], positions: F64) -> None:
        """(Re-)file ``features`` at ``positions`` (k, 2)."""
        keys = np.floor(np.asarray(positions, dtype=np.float64).reshape(-1, 2) / self.cell_m).astype(np.int64)
        for f, (i, j) in zip(features, keys.tolist(), strict=True):
            key = (i, j)
            while f >= len(self.where):
                self.where.append(None)
            old = self.where[f]
            if old == key:
                continue
            if old is not None:
                self.cells[old].discard(f)
            self.cells.setdefault(key, set()).add(f)
            self.where[f] = key

    def rebuild(self, positions: F64) -> None:
        """File every feature afresh from ``positions`` (N, 2)."""
        self.cells, self.where = {}, []
        self.file(list(range(len(positions))), positions)

    def near(self, centre: F64, radius: float, positions: F64) -> list[int]:
        """Features whose estimate in ``positions`` (N, 2) is within ``radius`` of ``centre`` (2,), sorted."""
        c = self.cell_m
        i0, i1 = math.floor((centre[0] - radius) / c), math.floor((centre[0] + radius) / c)
        j0, j1 = math.floor((centre[1] - radius) / c), math.floor((centre[1] + radius) / c)
        cand: list[int] = []
        for i in range(i0, i1 + 1):
            for j in range(j0, j1 + 1):
                cell = self.cells.get((i, j))
                if cell:
                    cand.extend(cell)
        if not cand:
            return []
        idx = np.asarray(sorted(cand), dtype=np.int64)
        d = np.hypot(*(positions[idx] - centre).T)
        return cast(list[int], idx[d <= radius].tolist())
