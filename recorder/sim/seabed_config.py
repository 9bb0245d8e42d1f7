"""The parameters of ``sim-seabed`` (:class:`SeabedSimConfig`), apart from the simulator so that the command
line reads its options (``record sim-seabed --help``) without importing numpy and OpenCV."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

from slamreplay.recorder.sim.bounds import MAX_IMAGE_SIDE_PX, MAX_IMAGES, MAX_SEABED_PX, too_many


@dataclass(frozen=True, slots=True)
class SeabedSimConfig:
    """Parameters of ``sim-seabed``. Lengths in metres unless the name says px.

    ``image_spacing`` and ``leg_spacing`` are fractions of the image footprint (the side of an
    image at the nominal altitude): consecutive images overlap by ``1 - image_spacing``, adjacent
    legs by ``1 - leg_spacing``.
    """

    texture: str = field(default="", metadata={"help": "seabed texture: empty for a procedural one made from the "
                                                        "seed, else an image file or a folder of frames to tile"})
    image_px: int = field(default=256, metadata={"help": "side of the square camera image, pixels"})
    metres_per_pixel: float = field(default=0.01, metadata={"help": "seabed metres per image pixel at the nominal "
                                                                     "altitude"})
    legs: int = field(default=4, metadata={"help": "number of survey legs (parallel lines joined by U-turns)"})
    leg_length_m: float = field(default=8.0, metadata={"help": "length of a leg, metres"})
    leg_spacing: float = field(default=0.35, metadata={"help": "distance between legs, in image footprints "
                                                                "(adjacent legs overlap by 1 - this)"})
    image_spacing: float = field(default=0.3, metadata={"help": "distance between consecutive images, in image "
                                                                 "footprints (they overlap by 1 - this)"})
    heading_wobble_deg: float = field(default=4.0, metadata={"help": "largest heading deviation along a leg, "
                                                                      "degrees"})
    scale_amplitude: float = field(default=0.06, metadata={"help": "altitude change as an image scale amplitude "
                                                                    "(0.06: scales 0.94 to 1.06)"})
    vignetting: float = field(default=0.5, metadata={"help": "strength of the lamp's uneven light, 0 (none) to 1"})
    noise_sigma: float = field(default=2.0, metadata={"help": "Gaussian sensor noise, grey levels"})
    odom_sigma: float = field(default=0.03, metadata={"help": "odometry noise, relative to the distance moved (and "
                                                               "radians per radian turned)"})
    frame_rate_hz: float = field(default=1.0, metadata={"help": "images per second"})

    def __post_init__(self) -> None:
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            if f.name != "texture" and not math.isfinite(value):
                raise ValueError(f"{f.name} must be finite, got {value}")
        if (isinstance(self.image_px, bool) or not isinstance(self.image_px, int)
                or not 32 <= self.image_px <= MAX_IMAGE_SIDE_PX):
            raise ValueError(f"image_px must be an integer from 32 to {MAX_IMAGE_SIDE_PX}, got {self.image_px!r}")
        if isinstance(self.legs, bool) or not isinstance(self.legs, int) or self.legs < 1:
            raise ValueError(f"legs must be an integer >= 1, got {self.legs!r}")
        for name in ("metres_per_pixel", "leg_length_m", "frame_rate_hz"):
            if getattr(self, name) <= 0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)}")
        for name in ("leg_spacing", "image_spacing"):
            if not 0.05 <= getattr(self, name) <= 1.0:
                raise ValueError(f"{name} must be in [0.05, 1] (a fraction of the image footprint)")
        if not 0.0 <= self.scale_amplitude <= 0.3:
            raise ValueError(f"scale_amplitude must be in [0, 0.3], got {self.scale_amplitude}")
        if not 0.0 <= self.vignetting < 1.0:
            raise ValueError(f"vignetting must be in [0, 1), got {self.vignetting}")
        for name in ("heading_wobble_deg", "noise_sigma", "odom_sigma"):
            if getattr(self, name) < 0:
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)}")
        images = self.legs * (self.leg_length_m / (self.image_spacing * self.footprint_m) + 1)
        width_m = (self.legs - 1) * self.leg_spacing * self.footprint_m + 2 * self.footprint_m
        seabed_px = width_m * (self.leg_length_m + 2 * self.footprint_m) / self.metres_per_pixel ** 2
        for problem in (too_many("images (legs x leg_length_m / image spacing)", images, MAX_IMAGES,
                                 "survey fewer or shorter legs"),
                        too_many("seabed pixels to render (survey area / metres_per_pixel^2)", seabed_px,
                                 MAX_SEABED_PX, "survey a smaller area or use a larger metres_per_pixel")):
            if problem:
                raise ValueError(problem)

    @property
    def footprint_m(self) -> float:
        """Side of an image on the seabed at the nominal altitude."""
        return self.image_px * self.metres_per_pixel
