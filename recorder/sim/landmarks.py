"""Simulator ``sim-landmarks``: a robot with a range-bearing sensor in a field of point landmarks.

By default this is the simulation of D-SLAM [1]_, section 4.2: a 40 m square with 196 point
landmarks on a 3 m grid, the robot starting at the bottom-left corner on a random trajectory at
0.2 m/s with turn rates up to 0.1 rad/s, and a 180-degree, 5 m range-bearing sensor. A short
stationary phase at the start lets D-SLAM's phase I see landmarks from a known pose.

Recorded topics (times are integer ns from :data:`EPOCH_NS`, never the wall clock):

- ``/ground_truth/landmarks``: the landmark map, once, at the first instant;
- ``/ground_truth/pose``: the true pose in ``world``, at the odometry rate;
- ``/odom``: the pose integrated from noisy odometry in ``odom`` (starts at (0, 0, 0)),
  same stamps as the ground truth and written after it;
- ``/landmarks/range_bearing``: one scan per sensor sweep, true landmark ids, noise sigmas.

Models
------
- Motion: a unicycle with exact constant-velocity arcs between odometry samples. The turn rate
  is an Ornstein-Uhlenbeck walk clipped to +-``max_turn_rate_radps``. Within
  ``2 * turning radius + 0.5 m`` of the boundary, a robot not heading within 45 degrees of the
  centre turns toward it at the maximum rate. A U-turn reaches at most ``(1 + 1/sqrt(2))`` turning
  radii toward a wall (heading into a corner), so the robot stays over 0.5 m (1 m by default) inside.
- Odometry: each sample's speed is ``v (1 + odom_speed_bias) + N(0, odom_speed_sigma_mps)`` and
  its turn rate ``w + odom_turn_bias_radps + N(0, odom_turn_sigma_radps)``, integrated by the same
  arcs. While the robot stands still the wheels do not turn and odometry reads exactly zero.
- Sensor: a landmark is detected when its true range is at most ``sensor_range_m`` and its true
  bearing within the field of view; range and bearing then get Gaussian noise, and a reading that
  noise pushes outside the sensor's limits is dropped (a sensor never reports beyond them).

References
----------
.. [1] Z. Wang, S. Huang, G. Dissanayake, "D-SLAM: Decoupled Localization and Mapping for
   Autonomous Robots", ISRR 2005, section 4.2.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Final

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from slamreplay.recorder.messages import (
    TOPIC_GROUND_TRUTH_LANDMARKS,
    TOPIC_GROUND_TRUTH_POSE,
    TOPIC_ODOM,
    TOPIC_RANGE_BEARING,
    GroundTruthPose,
    LandmarkMap,
    Message,
    OdometryPose,
    RangeBearingScan,
)
from slamreplay.recorder.sensor_model import SensorModel
from slamreplay.recorder.sim.landmarks_config import LandmarkSimConfig as LandmarkSimConfig  # re-exported
from slamreplay.recorder.sim.unicycle import arc_step, integrate, wrap_angle
from slamreplay.recorder.writer import Recorder

SIMULATOR: Final = "sim-landmarks"
EPOCH_NS: Final = 1_000_000_000  # first stamp of every simulated recording: fixed, nonzero, not the wall clock
START_OFFSET_M: Final = 1.5  # start pose: this far from both walls of the bottom-left corner
TURN_TAU_S: Final = 5.0  # correlation time of the turn-rate walk: a meandering path that covers the square
TURN_STD_FRACTION: Final = 0.5  # stationary std of the turn-rate walk, as a fraction of the maximum
STEER_TOLERANCE_RAD: Final = math.radians(45.0)
SCAN_BLOCK: Final = 1024  # scans per batched k-d tree query

Progress = Callable[[int, int], None]


@dataclass(frozen=True, slots=True)
class SimSummary:
    """What :func:`simulate_landmarks` wrote."""

    path: Path
    messages: int
    poses: int  # per pose topic: /odom and /ground_truth/pose each
    scans: int
    observations: int
    landmarks: int
    landmarks_observed: int
    area_m: float
    start_ns: int
    end_ns: int
    path_length_m: float


def landmark_positions(config: LandmarkSimConfig) -> NDArray[np.float64]:
    """Landmark positions ``(landmarks, 2)`` in ``world``, metres; landmark ``i`` is row ``i``.

    Row-major on a square grid of ``config.columns`` columns, centred in the square
    ``[0, side_m]^2``.
    """
    n, cols, step = config.landmarks, config.columns, config.landmark_spacing_m
    rows = -(-n // cols)
    i = np.arange(n)
    offset_x = 0.5 * (config.side_m - (cols - 1) * step)
    offset_y = 0.5 * (config.side_m - (rows - 1) * step)
    return np.stack([offset_x + (i % cols) * step, offset_y + (i // cols) * step], -1).astype(np.float64)


def simulate_motion(config: LandmarkSimConfig, n_steps: int, rng: np.random.Generator
                    ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """True velocities ``(n_steps,)`` held over each odometry period and poses ``(n_steps + 1, 3)``.

    Poses are ``[x_m, y_m, yaw_rad]`` in ``world`` (yaw unwrapped), starting in the bottom-left
    corner heading for the centre.
    """
    dt = config.odom_period_ns / 1e9
    side, margin, w_max = config.side_m, config.boundary_margin_m, config.max_turn_rate_radps
    decay = math.exp(-dt / TURN_TAU_S)
    kick = TURN_STD_FRACTION * w_max * math.sqrt(1.0 - decay * decay)
    eta = rng.standard_normal(n_steps).tolist()
    n_still = min(n_steps, math.ceil(config.stationary_s * config.odom_rate_hz - 1e-9))
    speed = np.zeros(n_steps)
    turn = np.zeros(n_steps)
    poses = np.empty((n_steps + 1, 3))
    x = y = START_OFFSET_M
    yaw = math.atan2(0.5 * side - y, 0.5 * side - x)
    poses[: n_still + 1] = (x, y, yaw)
    w = 0.0
    for k in range(n_still, n_steps):
        w = min(w_max, max(-w_max, decay * w + kick * eta[k]))
        if min(x, y, side - x, side - y) < margin:
            err = math.remainder(math.atan2(0.5 * side - y, 0.5 * side - x) - yaw, math.tau)
            if abs(err) > STEER_TOLERANCE_RAD:
                w = math.copysign(w_max, err)
        v = config.speed_mps
        dyaw = w * dt
        chord = v * dt * (math.sin(0.5 * dyaw) / (0.5 * dyaw) if dyaw != 0.0 else 1.0)
        x += chord * math.cos(yaw + 0.5 * dyaw)
        y += chord * math.sin(yaw + 0.5 * dyaw)
        yaw += dyaw
        speed[k], turn[k] = v, w
        poses[k + 1] = (x, y, yaw)
    return speed, turn, poses


def odometry_readings(config: LandmarkSimConfig, speed: NDArray[np.float64], turn: NDArray[np.float64],
                      rng: np.random.Generator) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Noisy, biased odometry velocities ``(n,)`` for the true ``speed`` and ``turn`` ``(n,)``."""
    noise = rng.standard_normal((2, len(speed)))
    moving = (speed != 0.0) | (turn != 0.0)
    v = speed * (1.0 + config.odom_speed_bias) + config.odom_speed_sigma_mps * noise[0]
    w = turn + config.odom_turn_bias_radps + config.odom_turn_sigma_radps * noise[1]
    return np.where(moving, v, 0.0), np.where(moving, w, 0.0)


def _scan_poses(period_ns: int, scan_rel_ns: NDArray[np.int64], speed: NDArray[np.float64], turn: NDArray[np.float64],
                poses: NDArray[np.float64]) -> NDArray[np.float64]:
    """True poses ``(m, 3)`` at scan times (ns after the epoch), along the arcs between odometry samples."""
    k = np.minimum(scan_rel_ns // period_ns, len(speed) - 1)
    into_s = (scan_rel_ns - k * period_ns) / 1e9
    return poses[k] + arc_step(poses[k, 2], speed[k], turn[k], into_s)


def _observe(config: LandmarkSimConfig, stamps_ns: NDArray[np.int64], scan_poses: NDArray[np.float64],
             landmarks: NDArray[np.float64], rng: np.random.Generator) -> Iterator[RangeBearingScan]:
    """One scan per pose: visibility by a batched k-d tree query, then Gaussian noise."""
    tree = cKDTree(landmarks)
    r_max, half_fov = config.sensor_range_m, 0.5 * math.radians(config.sensor_fov_deg)
    sigma_r, sigma_b = config.range_sigma_m, math.radians(config.bearing_sigma_deg)
    for start in range(0, len(scan_poses), SCAN_BLOCK):
        block = scan_poses[start:start + SCAN_BLOCK]
        near = tree.query_ball_point(block[:, :2], r=r_max, return_sorted=True)
        for j, (pose, found) in enumerate(zip(block, near, strict=True)):
            ids = np.asarray(found, dtype=np.int64)
            delta = landmarks[ids] - pose[:2]
            ranges = np.hypot(delta[:, 0], delta[:, 1])
            bearings = wrap_angle(np.arctan2(delta[:, 1], delta[:, 0]) - pose[2])
            seen = (ranges <= r_max) & (np.abs(bearings) <= half_fov)
            ids, ranges, bearings = ids[seen], ranges[seen], bearings[seen]
            noise = rng.standard_normal((2, len(ids)))
            ranges = ranges + sigma_r * noise[0]
            bearings = wrap_angle(bearings + sigma_b * noise[1])
            ok = (ranges >= 0.0) & (ranges <= r_max) & (np.abs(bearings) <= half_fov)
            yield RangeBearingScan(int(stamps_ns[start + j]), ranges[ok], bearings[ok], ids[ok],
                                   range_sigma_m=sigma_r, bearing_sigma_rad=sigma_b)


def sensor_model(config: LandmarkSimConfig) -> SensorModel:
    """The noise this simulation draws, in the units of the odometry noise model (`SensorModel`).

    Each odometry sample's speed and turn-rate noise (``odom_*_sigma``, per sample of ``dt``) moves the
    pose by ``sigma dt`` over ``speed dt`` metres, so per square-root metre travelled it is
    ``sigma sqrt(dt / speed)``; the turn noise does not grow with the angle turned (0 per sqrt(rad)).
    Biases are not noise and are not in the model: a biased recording says so in ``source``.
    """
    dt = 1.0 / config.odom_rate_hz
    per_sqrt_m = math.sqrt(dt / config.speed_mps)
    biased = config.odom_speed_bias != 0 or config.odom_turn_bias_radps != 0
    return SensorModel(
        translation_sigma_per_sqrt_m=config.odom_speed_sigma_mps * per_sqrt_m,
        heading_sigma_per_sqrt_m=config.odom_turn_sigma_radps * per_sqrt_m,
        heading_sigma_per_sqrt_rad=0.0,
        range_sigma_m=config.range_sigma_m, bearing_sigma_rad=math.radians(config.bearing_sigma_deg),
        outlier_rate=0.0, fov_rad=math.radians(config.sensor_fov_deg), max_range_m=config.sensor_range_m,
        source=f"{SIMULATOR}: the noise it simulated" + (
            " (plus odometry biases, which the model leaves out: see parameters)" if biased else ""))


def simulate_landmarks(out: Path, config: LandmarkSimConfig, seed: int, progress: Progress | None = None
                       ) -> SimSummary:
    """Simulate the landmark world of ``config`` and record it to ``out`` (an MCAP file).

    Parameters
    ----------
    out : the recording to create; must not exist (the Recorder never overwrites).
    config : the scenario; ``LandmarkSimConfig()`` is the D-SLAM paper's section 4.2.
    seed : seeds every random draw (trajectory, odometry noise, sensor noise: independent
        streams, so changing a noise sigma leaves the trajectory unchanged). Same seed and
        config give identical messages.
    progress : called as ``progress(done, total)`` while writing, in odometry samples.

    Returns
    -------
    SimSummary : counts, the world's size and the time span written.

    Raises
    ------
    RecorderError : ``out`` (or ``out.partial``) exists, or its directory does not.
    """
    rng_motion, rng_odom, rng_sensor = np.random.default_rng(seed).spawn(3)
    period_ns = config.odom_period_ns
    scan_period_ns = max(1, round(1e9 / config.scan_rate_hz))
    n_steps = math.floor(config.duration_s * 1e9 / period_ns + 1e-9)
    end_rel_ns = n_steps * period_ns
    landmarks = landmark_positions(config)
    speed, turn, truth = simulate_motion(config, n_steps, rng_motion)
    odom_v, odom_w = odometry_readings(config, speed, turn, rng_odom)
    odom = integrate((0.0, 0.0, 0.0), odom_v, odom_w, period_ns / 1e9)
    scan_rel_ns = np.arange(0, end_rel_ns + 1, scan_period_ns, dtype=np.int64)
    scans = _observe(config, EPOCH_NS + scan_rel_ns, _scan_poses(period_ns, scan_rel_ns, speed, turn, truth),
                     landmarks, rng_sensor)

    truth_out = np.column_stack([truth[:, :2], wrap_angle(truth[:, 2])]).tolist()
    odom_out = np.column_stack([odom[:, :2], wrap_angle(odom[:, 2])]).tolist()
    total = n_steps + 1
    every = max(1, total // 200)
    counts = {"scans": 0, "observations": 0}
    observed = np.zeros(len(landmarks), dtype=bool)
    pending: RangeBearingScan | None = next(scans, None)
    with Recorder(out, source={"simulator": SIMULATOR}, seed=seed, parameters=dataclasses.asdict(config),
                  robot={"kinematics": "unicycle", "sensor": "range-bearing with true landmark ids"},
                  sensor_model=sensor_model(config)) as rec:
        rec.write(TOPIC_GROUND_TRUTH_LANDMARKS, LandmarkMap(EPOCH_NS, np.arange(len(landmarks)), landmarks))
        for k in range(total):
            stamp = EPOCH_NS + k * period_ns
            msgs: list[tuple[str, Message]] = [(TOPIC_GROUND_TRUTH_POSE, GroundTruthPose(stamp, *truth_out[k])),
                                               (TOPIC_ODOM, OdometryPose(stamp, *odom_out[k]))]
            next_stamp = stamp + period_ns if k + 1 < total else stamp + 1
            while pending is not None and pending.stamp_ns < next_stamp:
                msgs.append((TOPIC_RANGE_BEARING, pending))
                counts["scans"] += 1
                counts["observations"] += len(pending)
                observed[pending.landmark_ids] = True
                pending = next(scans, None)
            for topic, msg in msgs:
                rec.write(topic, msg)
            if progress is not None and ((k + 1) % every == 0 or k + 1 == total):
                progress(k + 1, total)
        messages = rec.message_count
    steps = np.diff(truth[:, :2], axis=0)
    return SimSummary(path=Path(out), messages=messages, poses=total, scans=counts["scans"],
                      observations=counts["observations"], landmarks=len(landmarks),
                      landmarks_observed=int(observed.sum()), area_m=config.side_m, start_ns=EPOCH_NS,
                      end_ns=EPOCH_NS + end_rel_ns, path_length_m=float(np.hypot(steps[:, 0], steps[:, 1]).sum()))
