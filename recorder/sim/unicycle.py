"""Planar unicycle kinematics for the simulators (recorder/ does not import algorithms/)."""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike, NDArray

F64 = NDArray[np.float64]


def wrap_angle(theta: ArrayLike) -> F64:
    """Wrap angles to [-pi, pi).

    The same function as ``slamreplay.algorithms.common.se2.wrap_angle``, written twice on purpose: recorder and
    algorithms never import each other (docs/design.md, Layers); tests/test_layers.py checks that the two agree.
    """
    t = np.asarray(theta, dtype=np.float64)
    w = (t + np.pi) % (2.0 * np.pi) - np.pi
    # just below -pi, the modulo rounds up to 2 pi and gives +pi: fold it back into the half-open range
    return np.where(w >= np.pi, w - 2.0 * np.pi, w)


def arc_step(yaw_rad: ArrayLike, speed_mps: ArrayLike, turn_radps: ArrayLike, dt_s: ArrayLike) -> F64:
    """Displacement ``(..., 3)`` = ``[dx, dy, dyaw]`` in the parent frame of an exact arc.

    Constant forward speed and turn rate for ``dt_s`` from heading ``yaw_rad``: the chord has
    length ``v dt sinc(w dt / 2)`` and points along the mid-arc heading, which stays exact
    (no division) as the turn rate goes to zero.
    """
    yaw = np.asarray(yaw_rad, dtype=np.float64)
    dt = np.asarray(dt_s, dtype=np.float64)
    dyaw = np.asarray(turn_radps, dtype=np.float64) * dt
    chord = np.asarray(speed_mps, dtype=np.float64) * dt * np.sinc(dyaw / (2.0 * np.pi))
    mid = yaw + 0.5 * dyaw
    return np.stack(np.broadcast_arrays(chord * np.cos(mid), chord * np.sin(mid), dyaw), -1)


def integrate(start: ArrayLike, speed_mps: ArrayLike, turn_radps: ArrayLike, dt_s: float) -> F64:
    """Poses ``(n + 1, 3)`` (unwrapped yaw) from ``start`` under n constant-velocity arcs of ``dt_s``.

    ``speed_mps`` and ``turn_radps`` are (n,): the velocities held over each step.
    """
    p0 = np.asarray(start, dtype=np.float64)
    v = np.asarray(speed_mps, dtype=np.float64)
    w = np.asarray(turn_radps, dtype=np.float64)
    yaw = p0[2] + np.concatenate([[0.0], np.cumsum(w * dt_s)])
    d = arc_step(yaw[:-1], v, w, dt_s)
    poses = np.empty((len(v) + 1, 3))
    poses[0] = p0
    poses[1:, 0] = p0[0] + np.cumsum(d[:, 0])
    poses[1:, 1] = p0[1] + np.cumsum(d[:, 1])
    poses[:, 2] = yaw
    return poses


def between(a: ArrayLike, b: ArrayLike) -> F64:
    """``b`` in the body frame of ``a``: ``[dx, dy, dyaw]``; the yaw difference is not wrapped (callers with
    wrapped poses wrap it)."""
    pa, pb = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    c, s = math.cos(pa[2]), math.sin(pa[2])
    d = pb[:2] - pa[:2]
    return np.array([c * d[0] + s * d[1], -s * d[0] + c * d[1], pb[2] - pa[2]])


def compose(a: ArrayLike, b: ArrayLike) -> F64:
    """Pose ``a`` followed by the body-frame motion ``b``: ``[x, y, yaw]`` (yaw not wrapped)."""
    pa, pb = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    c, s = math.cos(pa[2]), math.sin(pa[2])
    return np.array([pa[0] + c * pb[0] - s * pb[1], pa[1] + s * pb[0] + c * pb[1], pa[2] + pb[2]])
