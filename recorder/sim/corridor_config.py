"""The parameters of ``sim-corridor`` (:class:`CorridorConfig`) and its tours, apart from the simulator so that
the renderer and the wheel odometry can take one without importing the simulator that uses them, and the
command line reads its options (``record sim-corridor --help``) without importing numpy."""

from __future__ import annotations

import dataclasses
import itertools
import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Final

from slamreplay.recorder.sim.bounds import MAX_IMAGE_SIDE_PX, MAX_IMAGES, MAX_SAMPLES, too_many

if TYPE_CHECKING:
    import numpy as np
    from numpy.typing import NDArray

    F64 = NDArray[np.float64]

# The tours (corridor_plan.py's docstring draws them): waypoints on the corridor centrelines, metres.
TOURS: Final[dict[str, tuple[tuple[float, float], ...]]] = {
    "outer": ((0, 0), (16, 0), (16, 10), (0, 10), (0, 0)),
    "left": ((0, 0), (7, 0), (7, 10), (0, 10), (0, 0)),
    "right": ((0, 0), (7, 0), (16, 0), (16, 10), (7, 10), (7, 0), (0, 0)),
    "right-cw": ((0, 0), (7, 0), (7, 10), (16, 10), (16, 0), (7, 0), (0, 0)),
    "rooms": ((0, 0), (12, 0), (12, -2.6), (12, 0), (16, 0), (16, 10), (4.3, 10), (4.3, 12.6), (4.3, 10),
              (0, 10), (0, 5), (-2.9, 5), (0, 5), (0, 0)),
}


@dataclass(frozen=True, slots=True)
class CorridorConfig:
    """Parameters of ``sim-corridor``. Lengths in metres, angles in degrees unless the name says rad."""

    texture: str = field(default="", metadata={"help": "wall textures: empty for the photo panels shipped in "
                                                        "recorder/sim/textures, else a folder of images"})
    image_width: int = field(default=320, metadata={"help": "image width, pixels"})
    image_height: int = field(default=240, metadata={"help": "image height, pixels"})
    hfov_deg: float = field(default=46.0, metadata={"help": "horizontal field of view, degrees (46: the Canon "
                                                             "VC-C50i of Bazeille et al. 2011, wide end)"})
    camera_height_m: float = field(default=0.6, metadata={"help": "camera height above the floor"})
    wall_height_m: float = field(default=2.5, metadata={"help": "wall height (the ceiling)"})
    corridor_width_m: float = field(default=1.8, metadata={"help": "corridor width, 1.2 to 2.4"})
    plain_fraction: float = field(default=0.05, metadata={"help": "share of plain painted wall panels (no photo)"})
    twins: int = field(default=3, metadata={"help": "runs of three panels repeated elsewhere (places that look "
                                                     "alike)"})
    route: str = field(default="rooms,left,right-cw", metadata={"help": "comma-separated tours: " + ", ".join(TOURS)})
    laps: int = field(default=1, metadata={"help": "times the whole route is driven"})
    speed_mps: float = field(default=0.4, metadata={"help": "cruise speed (0.4: the paper's Pioneer)"})
    turn_rate_dps: float = field(default=30.0, metadata={"help": "largest turn rate, degrees per second"})
    lookahead_m: float = field(default=0.6, metadata={"help": "pure-pursuit look-ahead distance"})
    steer_jitter_dps: float = field(default=2.0, metadata={"help": "teleoperator's steering wobble, degrees per "
                                                                    "second (1 sigma, smooth)"})
    camera_rate_hz: float = field(default=5.0, metadata={"help": "images per second"})
    odom_rate_hz: float = field(default=20.0, metadata={"help": "odometry and ground-truth poses per second (an "
                                                                 "integer multiple of camera_rate_hz)"})
    wheel_base_m: float = field(default=0.33, metadata={"help": "distance between the wheels"})
    odom_wheel_ratio_error: float = field(default=0.001, metadata={"help": "right/left wheel diameter error "
                                                                            "(heading bias about this / wheel_base "
                                                                            "rad per metre, counter-clockwise if > 0)"})
    odom_wheelbase_error: float = field(default=0.01, metadata={"help": "relative wheel-base error (turns under-read "
                                                                         "by this fraction if > 0)"})
    odom_scale_error: float = field(default=0.005, metadata={"help": "relative error of both wheels' radius "
                                                                      "(distances over-read if > 0)"})
    odom_sigma_m: float = field(default=0.01, metadata={"help": "random distance error, metres after 1 m "
                                                                 "(grows with the square root of distance)"})
    odom_sigma_rad: float = field(default=0.01, metadata={"help": "random heading error, rad per sqrt(rad) turned"})
    odom_sigma_rad_per_m: float = field(default=0.003, metadata={"help": "random heading error, rad per sqrt(m) "
                                                                          "travelled"})
    noise_sigma: float = field(default=2.0, metadata={"help": "Gaussian sensor noise, grey levels"})
    brightness_jitter: float = field(default=0.03, metadata={"help": "image-to-image gain change (auto exposure), "
                                                                      "1 sigma"})
    compression: str = field(default="jpeg", metadata={"help": "image storage: jpeg, png or raw"})

    def __post_init__(self) -> None:
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            if isinstance(value, bool) or (f.type == "int" and not isinstance(value, int)):
                raise ValueError(f"{f.name} must be an integer, got {value!r}")
            if isinstance(value, float | int) and not math.isfinite(value):
                raise ValueError(f"{f.name} must be finite, got {value}")
        if not (32 <= self.image_width <= MAX_IMAGE_SIDE_PX and 24 <= self.image_height <= MAX_IMAGE_SIDE_PX):
            raise ValueError(f"image_width and image_height must be from 32 x 24 to {MAX_IMAGE_SIDE_PX} x "
                             f"{MAX_IMAGE_SIDE_PX}, got {self.image_width} x {self.image_height}")
        if not 10.0 <= self.hfov_deg <= 150.0:
            raise ValueError(f"hfov_deg must be in [10, 150] (a pinhole camera), got {self.hfov_deg}")
        if not 0.0 < self.camera_height_m < self.wall_height_m:
            raise ValueError(f"camera_height_m must be in (0, wall_height_m = {self.wall_height_m}), "
                             f"got {self.camera_height_m}")
        if not 1.2 <= self.corridor_width_m <= 2.4:
            raise ValueError(f"corridor_width_m must be in [1.2, 2.4], got {self.corridor_width_m}")
        if not 0.0 <= self.plain_fraction <= 1.0:
            raise ValueError(f"plain_fraction must be in [0, 1], got {self.plain_fraction}")
        bad = [r.strip() for r in self.route.split(",") if r.strip() not in TOURS]
        if bad:
            raise ValueError(f"route names unknown tours {bad}: choose from {', '.join(TOURS)}")
        if self.laps < 1 or self.twins < 0:
            raise ValueError(f"laps must be >= 1 and twins >= 0, got {self.laps} and {self.twins}")
        for name in ("speed_mps", "turn_rate_dps", "lookahead_m", "camera_rate_hz", "odom_rate_hz", "wheel_base_m"):
            if getattr(self, name) <= 0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)}")
        ratio = self.odom_rate_hz / self.camera_rate_hz
        if abs(ratio - round(ratio)) > 1e-9 or round(ratio) < 1:
            raise ValueError(f"odom_rate_hz ({self.odom_rate_hz}) must be an integer multiple of camera_rate_hz "
                             f"({self.camera_rate_hz})")
        if abs(1e9 / self.odom_rate_hz - round(1e9 / self.odom_rate_hz)) > 1e-6:
            raise ValueError(f"odom_rate_hz must give a whole number of ns per step, got {self.odom_rate_hz}")
        for name in ("odom_wheel_ratio_error", "odom_wheelbase_error", "odom_scale_error"):
            if abs(getattr(self, name)) >= 0.1:
                raise ValueError(f"{name} must be in (-0.1, 0.1), got {getattr(self, name)}")
        for name in ("steer_jitter_dps", "odom_sigma_m", "odom_sigma_rad", "odom_sigma_rad_per_m", "noise_sigma",
                     "brightness_jitter"):
            if getattr(self, name) < 0:
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)}")
        if self.brightness_jitter > 0.3:
            raise ValueError(f"brightness_jitter must be <= 0.3, got {self.brightness_jitter}")
        if self.compression not in ("jpeg", "png", "raw"):
            raise ValueError(f"compression must be jpeg, png or raw, got {self.compression!r}")
        if self.twins > 100:
            raise ValueError(f"twins must be at most 100, got {self.twins}")
        legs = [TOURS[tour.strip()] for tour in self.route.split(",")]
        drive_s = self.laps * sum(math.dist(a, b) for pts in legs for a, b in itertools.pairwise(pts)
                                  ) / self.speed_mps
        for problem in (too_many("images (route length x laps / speed_mps x camera_rate_hz)",
                                 drive_s * self.camera_rate_hz, MAX_IMAGES, "drive fewer laps or lower the rate"),
                        too_many("odometry samples (route length x laps / speed_mps x odom_rate_hz)",
                                 drive_s * self.odom_rate_hz, MAX_SAMPLES, "drive fewer laps or lower the rate")):
            if problem:
                raise ValueError(problem)

    @property
    def focal_px(self) -> float:
        """Focal length in pixels, from ``hfov_deg``."""
        return 0.5 * self.image_width / math.tan(math.radians(0.5 * self.hfov_deg))

    @property
    def camera_matrix(self) -> F64:
        """The (3, 3) pinhole matrix K (pixel centres at integer coordinates)."""
        import numpy as np  # here, not at the top: the command line imports this module without numpy

        f = self.focal_px
        return np.array([[f, 0.0, 0.5 * (self.image_width - 1)], [0.0, f, 0.5 * (self.image_height - 1)],
                         [0.0, 0.0, 1.0]])

    @classmethod
    def from_dict(cls, values: Mapping[str, Any]) -> CorridorConfig:
        """A config from a mapping of field values; ValueError names unknown fields."""
        names = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(values) - names)
        if unknown:
            raise ValueError(f"unknown sim-corridor parameters {unknown}")
        return cls(**dict(values))
