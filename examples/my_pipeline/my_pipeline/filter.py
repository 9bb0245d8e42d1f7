"""A constant-velocity Kalman filter over wheel odometry: pure numpy, no slamreplay imports.

State ``[x, y, theta, v, omega]``: the planar pose in the world frame, and the forward speed and
turn rate held over the odometry interval that ends at the current sample. The speed and turn
rate follow the white-noise-acceleration model (Bar-Shalom, Li, Kirubarajan, *Estimation with
Applications to Tracking and Navigation*, 2001, section 6.2.2: the discretised continuous
white-noise model, process noise ``q dt`` on a velocity held over ``dt``); odometry measures the
mean speed and turn rate of each interval; the pose moves along the exact arc of constant
``(v, omega)``. Because the pose is never measured, the speed and turn rate are estimated
independently of it and the pose covariance grows: an estimator of motion, not a SLAM system.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

F64 = NDArray[np.float64]


def sinc_half(a: float) -> tuple[float, float]:
    """``sin(a) / a`` and its derivative in ``a``, accurate near 0 (series below 1e-4)."""
    if abs(a) < 1e-4:
        return 1.0 - a * a / 6.0, -a / 3.0
    s, c = math.sin(a), math.cos(a)
    return s / a, (a * c - s) / (a * a)


def arc_increment(v: float, omega: float, dt: float) -> tuple[float, float, float]:
    """Body-frame displacement ``(dx, dy, dtheta)`` of ``dt`` seconds at constant ``(v, omega)``."""
    half = 0.5 * omega * dt
    k, _ = sinc_half(half)
    chord = v * dt * k
    return chord * math.cos(half), chord * math.sin(half), omega * dt


def mean_velocity(dx: float, dy: float, dtheta: float, dt: float) -> tuple[float, float]:
    """Speed and turn rate of the constant-velocity arc that moves ``(dx, dy, dtheta)`` in ``dt``: the
    inverse of :func:`arc_increment` (signed speed: negative when driving backwards)."""
    if not dt > 0:
        raise ValueError(f"dt must be > 0, got {dt}")
    k, _ = sinc_half(0.5 * dtheta)
    chord = math.hypot(dx, dy)
    sign = -1.0 if dx < 0 else 1.0
    return sign * chord / (k * dt), dtheta / dt


@dataclass(frozen=True, slots=True)
class CvNoise:
    """Noise of the filter; all finite and > 0 (floors may be 0)."""

    accel_sigma: float  # m/s^2/sqrt(Hz): white acceleration density (q = sigma^2)
    yaw_accel_sigma: float  # rad/s^2/sqrt(Hz)
    translation_sigma_per_sqrt_m: float  # odometry: m per sqrt(m) travelled
    heading_sigma_per_sqrt_m: float  # rad per sqrt(m) travelled
    heading_sigma_per_sqrt_rad: float  # rad per sqrt(rad) turned
    speed_sigma_floor: float  # m/s: the measurement noise never falls below this (a robot standing still)
    yaw_rate_sigma_floor: float  # rad/s

    def measurement_covariance(self, distance_m: float, turned_rad: float, dt: float) -> F64:
        """R (2, 2) of a mean speed and turn rate over ``dt`` that moved ``distance_m`` and turned ``turned_rad``
        (the odometry noise model of slamreplay's OdometryNoise, divided by ``dt``)."""
        var_t = self.translation_sigma_per_sqrt_m ** 2 * distance_m
        var_h = self.heading_sigma_per_sqrt_m ** 2 * distance_m + self.heading_sigma_per_sqrt_rad ** 2 * abs(turned_rad)
        return np.diag([var_t / dt**2 + self.speed_sigma_floor**2, var_h / dt**2 + self.yaw_rate_sigma_floor**2])


@dataclass(frozen=True, slots=True)
class CvStep:
    """The state after one odometry sample, and the innovation that sample brought."""

    mean: F64  # (5,)
    cov: F64  # (5, 5)
    innovation: F64  # (2,) measured minus predicted (v, omega)
    nis: float  # normalised innovation squared: chi-square with 2 degrees of freedom when the noise is right


class ConstantVelocityFilter:
    """The filter's state and its step; inputs are never mutated."""

    def __init__(self, start_pose: F64, noise: CvNoise, init_speed_sigma: float = 1.0,
                 init_yaw_rate_sigma: float = 1.0) -> None:
        start = np.asarray(start_pose, np.float64)
        if start.shape != (3,) or not np.all(np.isfinite(start)):
            raise ValueError(f"start_pose must be a finite (3,) [x, y, theta], got {start_pose!r}")
        self.noise = noise
        self.mean = np.array([*start, 0.0, 0.0])
        self.cov = np.diag([0.0, 0.0, 0.0, init_speed_sigma**2, init_yaw_rate_sigma**2])

    def step(self, increment: F64, dt: float) -> CvStep:
        """Fold in one odometry increment ``(dx, dy, dtheta)`` (body frame) that took ``dt`` seconds.

        1. Speed and turn rate: random-walk prediction ``P += diag(q_v, q_w) dt``, then the Kalman
           update with their measured means over the interval.
        2. Pose: moved along the arc of the updated ``(v, omega)``, covariance through its Jacobian.
        """
        u = np.asarray(increment, np.float64)
        if u.shape != (3,) or not np.all(np.isfinite(u)):
            raise ValueError(f"increment must be a finite (3,) [dx, dy, dtheta], got {increment!r}")
        if not (math.isfinite(dt) and dt > 0):
            raise ValueError(f"dt must be finite and > 0, got {dt}")
        n = self.noise
        mean, cov = self.mean.copy(), self.cov.copy()
        cov[3, 3] += n.accel_sigma**2 * dt
        cov[4, 4] += n.yaw_accel_sigma**2 * dt
        z = np.array(mean_velocity(float(u[0]), float(u[1]), float(u[2]), dt), dtype=np.float64)
        # The noise of odometry grows with the distance travelled and the angle turned: taken from the predicted
        # (v, omega), not from the measurement itself, which would weigh fast samples less and bias the speed low.
        R = n.measurement_covariance(abs(mean[3]) * dt, abs(mean[4]) * dt, dt)
        H = np.zeros((2, 5))
        H[0, 3] = H[1, 4] = 1.0
        innovation = z - mean[3:]
        S = H @ cov @ H.T + R
        K = cov @ H.T @ np.linalg.inv(S)
        mean = mean + K @ innovation
        IKH = np.eye(5) - K @ H
        cov = IKH @ cov @ IKH.T + K @ R @ K.T  # Joseph form: stays symmetric positive semi-definite
        nis = float(innovation @ np.linalg.solve(S, innovation))

        x, y, th, v, w = mean
        half = 0.5 * w * dt
        k, dk = sinc_half(half)
        c, s = math.cos(th + half), math.sin(th + half)
        chord = v * dt * k
        F = np.eye(5)
        F[0, 2], F[1, 2] = -chord * s, chord * c
        F[0, 3], F[1, 3] = dt * k * c, dt * k * s
        dchord_dw = v * dt * dk * 0.5 * dt
        F[0, 4] = dchord_dw * c - chord * s * 0.5 * dt
        F[1, 4] = dchord_dw * s + chord * c * 0.5 * dt
        F[2, 4] = dt
        mean = np.array([x + chord * c, y + chord * s, math.remainder(th + w * dt, math.tau), v, w])
        cov = F @ cov @ F.T
        self.mean, self.cov = mean, 0.5 * (cov + cov.T)
        return CvStep(self.mean.copy(), self.cov.copy(), innovation, nis)
