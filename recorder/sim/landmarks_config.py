"""The parameters of ``sim-landmarks`` (:class:`LandmarkSimConfig`), apart from the simulator so that the
command line reads its options (``record sim-landmarks --help``) without importing numpy and scipy."""

from __future__ import annotations

import dataclasses
import math
import numbers
from dataclasses import dataclass, field
from typing import Final

from slamreplay.recorder.sim.bounds import MAX_LANDMARKS, MAX_SAMPLES

PAPER_AREA_M: Final = 40.0
GRID_BORDER_M: Final = 0.5  # 14 columns 3 m apart span 39 m: centred in the paper's 40 m square


@dataclass(frozen=True, slots=True)
class LandmarkSimConfig:
    """Parameters of ``sim-landmarks``; the defaults are the D-SLAM paper's section 4.2 scenario.

    ``area_m`` is the side of the square world. When ``None`` it is the paper's 40 m, grown to
    ``(columns - 1) * landmark_spacing_m + 1 m`` when the grid does not fit, where the landmarks
    fill ``columns = ceil(sqrt(landmarks))`` columns row by row, centred in the square. An
    explicit ``area_m`` must hold the grid at its spacing. ``odom_speed_bias`` is a scale error
    (0.01 = odometry reads 1 % fast); sigmas are per odometry sample.
    """

    duration_s: float = field(default=1800.0, metadata={"help": (
        "simulated time, seconds (the paper drives 30 minutes)")})
    landmarks: int = field(default=196, metadata={"help": (
        "number of point landmarks, laid out on a square grid row by row")})
    area_m: float | None = field(default=None, metadata={"help": (
        "side of the square world, metres (default: the paper's 40 m, grown when the grid does not fit)")})
    landmark_spacing_m: float = field(default=3.0, metadata={"help": (
        "distance between neighbouring landmarks of the grid, metres")})
    speed_mps: float = field(default=0.2, metadata={"help": (
        "forward speed of the robot, metres per second")})
    max_turn_rate_radps: float = field(default=0.1, metadata={"help": (
        "largest turn rate, radians per second (sets the tightest turning radius)")})
    sensor_range_m: float = field(default=5.0, metadata={"help": (
        "range of the range-bearing sensor, metres")})
    sensor_fov_deg: float = field(default=180.0, metadata={"help": (
        "field of view of the sensor, degrees, centred on the heading (360: all round)")})
    range_sigma_m: float = field(default=0.05, metadata={"help": (
        "range noise of a landmark sighting, metres (1 sigma)")})
    bearing_sigma_deg: float = field(default=1.0, metadata={"help": (
        "bearing noise of a landmark sighting, degrees (1 sigma)")})
    odom_speed_sigma_mps: float = field(default=0.02, metadata={"help": (
        "odometry speed noise per sample, metres per second (1 sigma)")})
    odom_turn_sigma_radps: float = field(default=0.02, metadata={"help": (
        "odometry turn-rate noise per sample, radians per second (1 sigma)")})
    odom_speed_bias: float = field(default=0.0, metadata={"help": (
        "odometry scale error, a fraction in (-0.5, 0.5) (0.01: odometry reads 1.01 m per metre driven)")})
    odom_turn_bias_radps: float = field(default=0.0, metadata={"help": (
        "constant odometry turn-rate error, radians per second")})
    stationary_s: float = field(default=5.0, metadata={"help": (
        "seconds standing still at the start (D-SLAM's phase I sees landmarks from a known pose)")})
    odom_rate_hz: float = field(default=10.0, metadata={"help": (
        "odometry and ground-truth samples per second")})
    scan_rate_hz: float = field(default=5.0, metadata={"help": (
        "sensor sweeps (scans) per second")})

    def __post_init__(self) -> None:
        if isinstance(self.landmarks, bool) or not isinstance(self.landmarks, numbers.Integral):
            raise ValueError(f"landmarks must be an integer, got {self.landmarks!r}")
        if not 1 <= self.landmarks <= MAX_LANDMARKS:
            raise ValueError(f"landmarks must be in [1, {MAX_LANDMARKS:,}], got {self.landmarks}")
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            if f.name != "landmarks" and value is not None and not math.isfinite(value):
                raise ValueError(f"{f.name} must be finite, got {value}")
        positive = ("duration_s", "landmark_spacing_m", "speed_mps", "max_turn_rate_radps", "sensor_range_m",
                    "odom_rate_hz", "scan_rate_hz")
        for name in positive:
            if getattr(self, name) <= 0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)}")
        for name in ("range_sigma_m", "bearing_sigma_deg", "odom_speed_sigma_mps", "odom_turn_sigma_radps",
                     "stationary_s"):
            if getattr(self, name) < 0:
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)}")
        if not 0 < self.sensor_fov_deg <= 360:
            raise ValueError(f"sensor_fov_deg must be in (0, 360], got {self.sensor_fov_deg}")
        if not -0.5 < self.odom_speed_bias < 0.5:
            raise ValueError(f"odom_speed_bias is a scale error and must be in (-0.5, 0.5), got {self.odom_speed_bias}")
        if self.duration_s * self.odom_rate_hz < 1:
            msg = f"duration_s must last at least one odometry period (1/odom_rate_hz), got {self.duration_s}"
            raise ValueError(msg)
        samples = self.duration_s * max(self.odom_rate_hz, self.scan_rate_hz)
        if samples > MAX_SAMPLES:
            msg = (f"duration_s {self.duration_s:g} at {max(self.odom_rate_hz, self.scan_rate_hz):g} Hz is "
                   f"{samples:,.0f} samples, more than {MAX_SAMPLES:,}: record a shorter drive (or several)")
            raise ValueError(msg)
        need = self.grid_extent_m + 2 * GRID_BORDER_M
        if self.area_m is not None and self.area_m < need:
            msg = (f"area_m {self.area_m} m cannot hold {self.landmarks} landmarks {self.landmark_spacing_m} m apart: "
                   f"use area_m >= {need} m, fewer landmarks, a smaller landmark_spacing_m, or area_m None")
            raise ValueError(msg)
        if self.side_m < 4 * self.boundary_margin_m:
            msg = (f"area_m {self.side_m} m is too small for a robot turning on a {self.turn_radius_m:.2f} m radius: "
                   f"use area_m >= {4 * self.boundary_margin_m:.2f} m, or lower speed_mps / raise max_turn_rate_radps")
            raise ValueError(msg)

    @property
    def odom_period_ns(self) -> int:
        """Time between odometry (and ground-truth) samples, whole nanoseconds."""
        return max(1, round(1e9 / self.odom_rate_hz))

    @property
    def columns(self) -> int:
        """Landmarks per grid row."""
        return math.isqrt(self.landmarks - 1) + 1

    @property
    def grid_extent_m(self) -> float:
        """Width of the landmark grid (first to last column), metres."""
        return (self.columns - 1) * self.landmark_spacing_m

    @property
    def side_m(self) -> float:
        """Side of the square world, metres (``area_m`` or the rule in the class docstring)."""
        if self.area_m is not None:
            return float(self.area_m)
        return max(PAPER_AREA_M, self.grid_extent_m + 2 * GRID_BORDER_M)

    @property
    def turn_radius_m(self) -> float:
        """Tightest turning radius, metres."""
        return self.speed_mps / self.max_turn_rate_radps

    @property
    def boundary_margin_m(self) -> float:
        """Within this distance of a wall, the robot steers back toward the centre (module docstring)."""
        return 2.0 * self.turn_radius_m + 0.5
