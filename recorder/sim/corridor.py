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
from dataclasses import dataclass
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
from slamreplay.recorder.sim.corridor_config import CorridorConfig
from slamreplay.recorder.sim.corridor_plan import PurePursuit
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
