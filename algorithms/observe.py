"""The observer: the only way intermediate results leave an algorithm.

Algorithms call ``observer.log(path, item)`` with one of the observation dataclasses below;
the replay layer decides what becomes of it (a Rerun entity, a test event, nothing) and
sets the time. Paths look like ``<algorithm>/<quantity>`` (``dslam/landmarks/mean``) or
follow the map-frame conventions (``world/...``). Observations hold plain numpy data.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal, Protocol

import numpy as np
from numpy.typing import NDArray

F64 = NDArray[np.float64]


@dataclass(frozen=True, slots=True, eq=False)
class Points:
    """2D points (n, 2) in metres (map frame) or pixels (image space), with optional labels."""

    positions: F64
    labels: tuple[str, ...] | None = None
    radius: float | None = None


@dataclass(frozen=True, slots=True, eq=False)
class Pose:
    """A planar pose ``[x, y, theta]``, drawn as a point with a heading arrow."""

    pose: F64
    label: str | None = None


@dataclass(frozen=True, slots=True, eq=False)
class LineStrips:
    """Polylines: each entry is an (k, 2) array."""

    strips: tuple[F64, ...]


@dataclass(frozen=True, slots=True, eq=False)
class Segments:
    """Line segments from ``starts`` (n, 2) to ``ends`` (n, 2): links, associations, graph edges."""

    starts: F64
    ends: F64


@dataclass(frozen=True, slots=True, eq=False)
class CovarianceEllipses:
    """Uncertainty of 2D positions: means (n, 2) and covariances (n, 2, 2), drawn at ``n_sigma``."""

    means: F64
    covariances: F64
    n_sigma: float = 2.0


@dataclass(frozen=True, slots=True)
class Scalar:
    """One value of a time series."""

    value: float


@dataclass(frozen=True, slots=True)
class Text:
    """A log line."""

    text: str
    level: Literal["DEBUG", "INFO", "WARN", "ERROR"] = "INFO"


@dataclass(frozen=True, slots=True, eq=False)
class Image:
    """An image: (H, W) or (H, W, 3) uint8, or (H, W) float (e.g. a correlation surface)."""

    pixels: NDArray[np.generic]


@dataclass(frozen=True, slots=True, eq=False)
class Bars:
    """A bar chart: one bar per entry of ``values`` (e.g. a posterior over locations)."""

    values: NDArray[np.float64]


@dataclass(frozen=True, slots=True)
class State:
    """A discrete state entered at this time (a scan's status, a loop closure): one lane of a state timeline."""

    state: str


@dataclass(frozen=True, slots=True)
class Markdown:
    """A document (tables of results), shown as rendered markdown."""

    text: str


Observation = (Points | Pose | LineStrips | Segments | CovarianceEllipses | Scalar | Text | Image | Bars | State
               | Markdown)


class Observer(Protocol):
    """Receives intermediate results. Implementations never change the algorithm's state."""

    def log(self, path: str, item: Observation) -> None: ...


class _NullObserver:
    """Discards everything."""

    def log(self, path: str, item: Observation) -> None:
        return None


NULL_OBSERVER: Observer = _NullObserver()
