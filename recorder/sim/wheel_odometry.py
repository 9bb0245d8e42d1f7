"""Wheel odometry of a differential-drive robot with systematic and random drift.

Systematic errors follow Borenstein's UMBmark model [1]_: unequal wheel diameters (the right
wheel's travel read ``1 + e_d/2`` times, the left one's ``1 - e_d/2`` times: a heading bias of
about ``e_d / B`` rad per metre on a straight run, counter-clockwise when ``e_d > 0``), an
uncertain wheel base (the odometry divides by ``B (1 + e_b)``: turns under-read when ``e_b > 0``)
and a common scale error of both wheels. Random errors have variances proportional to the
distance travelled and the angle turned, so the drift does not depend on how finely the motion
is cut into steps.

References
----------
.. [1] J. Borenstein, L. Feng, "Measurement and correction of systematic odometry errors in
   mobile robots", IEEE Trans. Robotics and Automation 12(6), 1996.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike, NDArray

from slamreplay.recorder.sim.corridor_config import CorridorConfig

F64 = NDArray[np.float64]


class WheelOdometry:
    """Turns true body-frame motion increments into drifting odometry increments.

    Parameters
    ----------
    config : the ``odom_*`` and ``wheel_base_m`` fields are used.
    rng : the odometry's own random stream (one draw of two normals per :meth:`step`).
    start : the initial odometry pose ``[x_m, y_m, yaw_rad]`` in the ``odom`` frame.

    Examples
    --------
    >>> odo = WheelOdometry(CorridorConfig(), np.random.default_rng(0))  # doctest: +SKIP
    >>> inc = odo.step(arc_step(0.0, 0.4, 0.0, 0.05))  # 2 cm straight ahead  # doctest: +SKIP
    >>> odo.pose  # cumulative odometry pose  # doctest: +SKIP
    """

    def __init__(self, config: CorridorConfig, rng: np.random.Generator, start: ArrayLike = (0.0, 0.0, 0.0)) -> None:
        self.config = config
        self._rng = rng
        self._pose = np.array(start, dtype=np.float64).reshape(3)

    @property
    def pose(self) -> F64:
        """Cumulative odometry pose ``[x_m, y_m, yaw_rad]`` (yaw unwrapped), a copy."""
        return self._pose.copy()

    def step(self, true_increment: ArrayLike) -> F64:
        """Measure one motion and add it to :attr:`pose`.

        Parameters
        ----------
        true_increment : (3,) ``[dx_m, dy_m, dyaw_rad]``, the true motion in the body frame of
            the previous pose (for instance ``arc_step(0.0, v, w, dt)``).

        Returns
        -------
        (3,) float64 : the odometry increment, in the body frame of the previous odometry pose.
            With every ``odom_*`` parameter 0 it equals ``true_increment`` exactly.
        """
        dx, dy, dth = (float(v) for v in np.asarray(true_increment, dtype=np.float64).reshape(3))
        if not all(math.isfinite(v) for v in (dx, dy, dth)):
            raise ValueError(f"true_increment must be finite, got {(dx, dy, dth)}")
        if abs(dth) >= math.pi:
            raise ValueError(f"true_increment turns {dth:.3f} rad: split motions into steps turning less than pi")
        cfg = self.config
        chord = math.hypot(dx, dy)
        arc = math.copysign(chord / float(np.sinc(dth / (2.0 * math.pi))), dx if dx != 0.0 else 1.0)
        # Wheel travels s +- th B/2, read with the systematic errors, folded back to (s, th).
        k = 1.0 + cfg.odom_scale_error
        e_d, base = cfg.odom_wheel_ratio_error, cfg.wheel_base_m
        arc_m = k * (arc + e_d * dth * base / 4.0)
        dth_m = k * (dth + e_d * arc / base) / (1.0 + cfg.odom_wheelbase_error)
        n = self._rng.standard_normal(2)
        arc_m += cfg.odom_sigma_m * math.sqrt(abs(arc)) * float(n[0])
        dth_m += math.sqrt(cfg.odom_sigma_rad**2 * abs(dth) + cfg.odom_sigma_rad_per_m**2 * abs(arc)) * float(n[1])
        if chord > 1e-12:
            # Scale the chord and turn it by half the heading error: exact when there is no error.
            ratio, half = arc_m / arc, 0.5 * (dth_m - dth)
            c, s = math.cos(half), math.sin(half)
            out = np.array([ratio * (c * dx - s * dy), ratio * (s * dx + c * dy), dth_m])
        else:
            out = arc_m * float(np.sinc(dth_m / (2.0 * math.pi))) * np.array([math.cos(dth_m / 2), math.sin(dth_m / 2),
                                                                               0.0])
            out[2] = dth_m
        c, s = math.cos(self._pose[2]), math.sin(self._pose[2])
        self._pose = self._pose + np.array([c * out[0] - s * out[1], s * out[0] + c * out[1], out[2]])
        return out
