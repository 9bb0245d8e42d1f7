"""Settings of the pole extractor (:class:`PoleConfig`, method in ``poles.py``), apart from it so that the command
line reads them (``record ros2 --help``) without importing numpy."""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from typing import Any


@dataclass(frozen=True, slots=True)
class PoleConfig:
    """Settings of the pole extractor; recorded in the recording's parameters."""

    jump_m: float = field(default=0.5, metadata={"help": (
        "range jump between consecutive readings that separates two segments, metres")})
    min_points: int = field(default=3, metadata={"help": (
        "fewest readings a pole is made of (fewer: no circle can be told from a point)")})
    min_diameter_m: float = field(default=0.05, metadata={"help": "smallest pole or trunk diameter kept, metres"})
    max_diameter_m: float = field(default=1.0, metadata={"help": (
        "largest pole or trunk diameter kept, metres (wider: a wall, a car, a person)")})
    max_range_m: float = field(default=30.0, metadata={"help": "readings farther than this are ignored, metres"})
    circle_fit: bool = field(default=True, metadata={"help": (
        "fit a circle to each pole's points (false: the diameter-from-width estimate of Guivant and Nebot only)")})
    max_fit_rms_m: float = field(default=0.05, metadata={"help": (
        "a fit whose points stray farther (rms) from the circle is not a pole, metres")})
    range_sigma_m: float = field(default=0.05, metadata={"help": (
        "range noise of the beam, added to the fit's covariance, metres (1 sigma)")})
    bearing_sigma_rad: float = field(default=0.01, metadata={"help": (
        "bearing noise of the beam, added to the fit's covariance, radians (1 sigma)")})

    def __post_init__(self) -> None:
        for name in ("jump_m", "min_diameter_m", "max_diameter_m", "max_range_m", "max_fit_rms_m"):
            if not getattr(self, name) > 0:
                raise ValueError(f"pole extractor: {name} must be > 0, got {getattr(self, name)}")
        if self.min_diameter_m >= self.max_diameter_m:
            raise ValueError("pole extractor: min_diameter_m must be < max_diameter_m")
        if self.min_points < 2:
            raise ValueError(f"pole extractor: min_points must be >= 2, got {self.min_points}")
        if self.range_sigma_m < 0 or self.bearing_sigma_rad < 0:
            raise ValueError("pole extractor: range_sigma_m and bearing_sigma_rad must be >= 0")

    def as_dict(self) -> dict[str, Any]:
        return asdict(self)
