"""Simulator ``sim-corridor``: a forward camera on a wheeled robot driven round an indoor floor plan.

The floor plan (:mod:`slamreplay.recorder.sim.corridor_plan`, about 22 m x 18 m) has corridors forming two
loops, a dead end and two rooms. Its walls are lined with panels cut from real photos of office
corridors (``recorder/sim/textures``, BSD-3-Clause, from RTAB-Map), so places look different;
a few runs of panels are repeated on purpose elsewhere, so some places look alike, as in the
visual loop-closure experiments of [1]_. A teleoperator (a deterministic pure-pursuit
controller) drives the ``route`` at ``speed_mps`` (0.4 m/s, the paper's Pioneer): the default
route revisits corridors in the same direction (loop closures) and drives some of them the
other way round (a forward camera then sees other views: no loop closure expected).

The camera looks along the body's +x axis from ``camera_height_m``, is a pinhole with
``hfov_deg`` of horizontal field of view (46 degrees, about the Canon VC-C50i of [1]_ at its wide
end), no pitch and square pixels: ``f = (W / 2) / tan(hfov / 2)`` and ``K = [[f, 0, cx], [0, f,
cy], [0, 0, 1]]`` with ``cx = (W - 1) / 2``, ``cy = (H - 1) / 2``. Images are ray cast (one ray per
column, the perpendicular distance against fish-eye) and texture mapped with ``cv2.remap`` from a
mip-mapped atlas; the floor and ceiling are plain shading.

Recorded topics (times in integer ns from :data:`EPOCH_NS`, never the wall clock):

- ``/camera/calibration``: the intrinsics above, once at the start;
- ``/ground_truth/pose`` and ``/odom`` at ``odom_rate_hz``: the true pose in ``world`` (metres;
  the robot starts at the origin facing +x) and the drifting wheel odometry
  (:class:`~slamreplay.recorder.sim.wheel_odometry.WheelOdometry`) starting at (0, 0, 0);
- ``/camera/image`` at ``camera_rate_hz``: the mono8 image rendered from the true pose at the
  same stamp as a pose, written after it.

The metadata's ``parameters`` and ``seed`` name the world: :func:`world_from_metadata` rebuilds it.

References
----------
.. [1] S. Bazeille, E. Battesti, D. Filliat, "Qualitative localization using vision and odometry
   for path following in topo-metric maps", ECMR 2011.
"""

from __future__ import annotations

import dataclasses
import json
import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Final

import numpy as np
from numpy.typing import NDArray

from slamreplay.recorder.errors import RecorderError
from slamreplay.recorder.messages import (
    TOPIC_CAMERA_CALIBRATION,
    TOPIC_CAMERA_IMAGE,
    TOPIC_GROUND_TRUTH_POSE,
    TOPIC_ODOM,
    CameraCalibration,
    CameraImage,
    GroundTruthPose,
    OdometryPose,
)
from slamreplay.recorder.sensor_model import SensorModel
from slamreplay.recorder.sim.corridor_plan import TOURS, PurePursuit
from slamreplay.recorder.sim.corridor_render import CorridorWorld
from slamreplay.recorder.sim.unicycle import arc_step, between, wrap_angle
from slamreplay.recorder.sim.wheel_odometry import WheelOdometry
from slamreplay.recorder.writer import METADATA_NAME, Recorder

__all__ = ["EPOCH_NS", "SIMULATOR", "CorridorConfig", "CorridorSummary", "CorridorWorld", "WheelOdometry",
           "drive_route", "simulate_corridor", "world_from_file", "world_from_metadata"]

SIMULATOR: Final = "sim-corridor"
EPOCH_NS: Final = 1_000_000_000
MAX_DURATION_S: Final = 4 * 3600.0  # a route that takes longer is a controller fault

Progress = Callable[[int, int], None]
F64 = NDArray[np.float64]


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
        if self.image_width < 32 or self.image_height < 24:
            raise ValueError(f"image_width and image_height must be >= 32 x 24, got {self.image_width} x "
                             f"{self.image_height}")
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

    @property
    def focal_px(self) -> float:
        """Focal length in pixels, from ``hfov_deg``."""
        return 0.5 * self.image_width / math.tan(math.radians(0.5 * self.hfov_deg))

    @property
    def camera_matrix(self) -> F64:
        """The (3, 3) pinhole matrix K (pixel centres at integer coordinates)."""
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


@dataclass(frozen=True, slots=True)
class CorridorSummary:
    """What :func:`simulate_corridor` wrote."""

    path: Path
    messages: int
    images: int
    poses: int
    path_length_m: float
    duration_s: float
    odom_final_error_m: float  # position drift of the odometry at the end
    start_ns: int
    end_ns: int


def sensor_model(config: CorridorConfig) -> SensorModel:
    """The wheel odometry's random error (``wheel_odometry.py``, the same units) and the pinhole camera."""
    k = config.camera_matrix
    return SensorModel(translation_sigma_per_sqrt_m=config.odom_sigma_m,
                       heading_sigma_per_sqrt_m=config.odom_sigma_rad_per_m,
                       heading_sigma_per_sqrt_rad=config.odom_sigma_rad,
                       fov_rad=math.radians(config.hfov_deg), fx_px=float(k[0, 0]), fy_px=float(k[1, 1]),
                       cx_px=float(k[0, 2]), cy_px=float(k[1, 2]), width_px=config.image_width,
                       height_px=config.image_height,
                       source=f"{SIMULATOR}: the random odometry noise it simulated (its systematic wheel errors, see "
                              f"parameters, left out) and its camera")


def simulate_corridor(out: Path, config: CorridorConfig, seed: int, progress: Progress | None = None
                      ) -> CorridorSummary:
    """Drive the route of ``config`` through its world and record it to ``out`` (an MCAP file).

    Parameters
    ----------
    out : the recording to create; must not exist (the Recorder never overwrites).
    config : the scenario.
    seed : seeds the wall textures, the steering wobble, the odometry and the sensor noise
        (independent streams). Same seed and config give identical messages.
    progress : called as ``progress(done, total)`` in poses.

    Raises
    ------
    RecorderError : ``out`` exists, its directory does not, or the textures cannot be read.
    """
    _, rng_route, rng_odom, rng_noise = np.random.default_rng(seed).spawn(4)
    world = CorridorWorld.from_config(config, seed)
    truth = drive_route(world.route, config, rng_route)
    odometry = WheelOdometry(config, rng_odom)
    period = round(1e9 / config.odom_rate_hz)
    every = round(config.odom_rate_hz / config.camera_rate_hz)
    total = len(truth)
    images = 0
    with Recorder(out, source={"simulator": SIMULATOR}, seed=seed, parameters=dataclasses.asdict(config),
                  robot={"drive": "differential", "wheel_base_m": config.wheel_base_m,
                         "camera": f"forward, +x of the body, {config.camera_height_m} m high, "
                                   f"hfov {config.hfov_deg} deg", "world": world.describe()},
                  sensor_model=sensor_model(config)) as rec:
        rec.write(TOPIC_CAMERA_CALIBRATION, CameraCalibration(EPOCH_NS, config.image_width, config.image_height,
                                                              config.camera_matrix))
        for k in range(total):
            stamp = EPOCH_NS + k * period
            if k > 0:
                odometry.step(between(truth[k - 1], truth[k]))
            odom = odometry.pose
            rec.write(TOPIC_GROUND_TRUTH_POSE, GroundTruthPose(stamp, truth[k, 0], truth[k, 1],
                                                               float(wrap_angle(truth[k, 2]))))
            rec.write(TOPIC_ODOM, OdometryPose(stamp, odom[0], odom[1], float(wrap_angle(odom[2]))))
            if k % every == 0:
                image = world.render(truth[k], rng_noise)
                rec.write(TOPIC_CAMERA_IMAGE, CameraImage(stamp, image, frame_id="camera",
                                                          compression=config.compression))  # type: ignore[arg-type]
                images += 1
            if progress is not None:
                progress(k + 1, total)
        messages = rec.message_count
    steps = np.diff(truth[:, :2], axis=0)
    drift = float(np.hypot(*(odometry.pose[:2] - truth[-1, :2])))
    return CorridorSummary(Path(out), messages, images, total, float(np.hypot(steps[:, 0], steps[:, 1]).sum()),
                           (total - 1) * period / 1e9, drift, EPOCH_NS, EPOCH_NS + (total - 1) * period)


def drive_route(waypoints: F64, config: CorridorConfig, rng: np.random.Generator) -> F64:
    """True poses ``(n, 3)`` [x_m, y_m, yaw_rad (unwrapped)] at ``odom_rate_hz`` along ``waypoints``.

    The teleoperator is :class:`~slamreplay.recorder.sim.corridor_plan.PurePursuit` plus a smooth random
    steering wobble (an AR(1) process of ``steer_jitter_dps``, only while moving); each step is an
    exact unicycle arc.
    """
    dt = 1.0 / config.odom_rate_hz
    pilot = PurePursuit(waypoints, config.speed_mps, math.radians(config.turn_rate_dps), config.lookahead_m)
    keep = math.exp(-dt / 1.5)  # the wobble's correlation time: 1.5 s
    sigma = math.radians(config.steer_jitter_dps) * math.sqrt(1.0 - keep**2)
    pose = np.zeros(3)
    poses = [pose]
    wobble = 0.0
    for _ in range(int(MAX_DURATION_S / dt)):
        v, w = pilot.command(pose)
        if pilot.done:
            return np.array(poses)
        wobble = keep * wobble + sigma * float(rng.standard_normal())
        if v > 0:
            w += wobble
        pose = pose + arc_step(pose[2], v, w, dt)
        poses.append(pose)
    raise RecorderError(f"the robot did not finish route {config.route!r} in {MAX_DURATION_S:.0f} s of simulated "
                        "time: the controller is stuck")


def world_from_metadata(metadata: Mapping[str, Any]) -> tuple[CorridorWorld, CorridorConfig, int]:
    """Rebuild the world of a ``sim-corridor`` recording.

    Parameters
    ----------
    metadata : ``RecordingInfo.metadata`` (``{"slamreplay.recording": {...}}``) or the inner
        ``slamreplay.recording`` record itself: JSON strings ``source`` and ``parameters``, and ``seed``.

    Returns
    -------
    (world, config, seed)

    Raises
    ------
    RecorderError : not a sim-corridor recording, or a field is missing or unreadable.
    """
    record = metadata.get(METADATA_NAME, metadata)
    if not isinstance(record, Mapping):
        raise RecorderError(f"metadata record {METADATA_NAME} is not a mapping")
    for key in ("source", "seed", "parameters"):
        if key not in record:
            raise RecorderError(f"metadata has no {key!r}: not a slamreplay recording made by {SIMULATOR}")
    try:
        source = _json(record["source"])
        parameters = _json(record["parameters"])
        seed = int(record["seed"])
    except (ValueError, TypeError) as err:
        raise RecorderError(f"metadata source, parameters or seed is unreadable: {err}") from err
    if not isinstance(source, Mapping) or source.get("simulator") != SIMULATOR:
        raise RecorderError(f"not a {SIMULATOR} recording: its source is {source!r}")
    return _build(parameters, seed, "the recording's parameters")


def world_from_file(path: str | Path) -> tuple[CorridorWorld, CorridorConfig, int]:
    """Build the world of a JSON file ``{"config": {...}, "seed": N}`` (as written by ``CorridorWorld.to_json``).

    Missing config fields take their defaults. RecorderError when the file cannot be read or is invalid.
    """
    try:
        spec = json.loads(Path(path).read_text())
    except (OSError, ValueError) as err:
        raise RecorderError(f"cannot read world file {path}: {err}") from err
    if not isinstance(spec, dict) or "seed" not in spec:
        raise RecorderError(f"world file {path} must be a JSON object {{\"config\": {{...}}, \"seed\": N}}")
    try:
        seed = int(spec["seed"])
    except (TypeError, ValueError) as err:
        raise RecorderError(f"world file {path}: seed must be an integer, got {spec['seed']!r}") from err
    return _build(spec.get("config", {}), seed, f"world file {path}")


def _build(values: object, seed: int, what: str) -> tuple[CorridorWorld, CorridorConfig, int]:
    if not isinstance(values, Mapping):
        raise RecorderError(f"{what}: config must be a JSON object, got {type(values).__name__}")
    try:
        config = CorridorConfig.from_dict(values)
    except (TypeError, ValueError) as err:
        raise RecorderError(f"{what}: invalid sim-corridor config: {err}") from err
    return CorridorWorld.from_config(config, seed), config, seed


def _json(value: object) -> object:
    return json.loads(value) if isinstance(value, str) else value
