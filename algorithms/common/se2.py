"""SE(2): planar rigid motions as ``[x, y, theta]`` arrays, vectorized over leading axes.

A pose ``p = [x, y, theta]`` is the transform taking points from the body frame into the
parent frame: ``p_parent = R(theta) @ p_body + [x, y]``. Every function accepts a single
pose of shape (3,) or a stack of shape (..., 3) and broadcasts.
"""

from __future__ import annotations

from typing import cast

import numpy as np
from numpy.typing import ArrayLike, NDArray

F64 = NDArray[np.float64]


def wrap_angle(theta: ArrayLike) -> F64:
    """Wrap angles to [-pi, pi)."""
    t = np.asarray(theta, dtype=np.float64)
    w = (t + np.pi) % (2.0 * np.pi) - np.pi
    # just below -pi, the modulo rounds up to 2 pi and gives +pi: fold it back into the half-open range
    return np.where(w >= np.pi, w - 2.0 * np.pi, w)


def rot(theta: ArrayLike) -> F64:
    """Rotation matrices R(theta), shape (..., 2, 2)."""
    t = np.asarray(theta, dtype=np.float64)
    c, s = np.cos(t), np.sin(t)
    return np.stack([np.stack([c, -s], -1), np.stack([s, c], -1)], -2)


def compose(a: ArrayLike, b: ArrayLike) -> F64:
    """a ⊕ b: the pose b (expressed in frame a) expressed in a's parent frame."""
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    c, s = np.cos(a[..., 2]), np.sin(a[..., 2])
    x = a[..., 0] + c * b[..., 0] - s * b[..., 1]
    y = a[..., 1] + s * b[..., 0] + c * b[..., 1]
    return np.stack([x, y, wrap_angle(a[..., 2] + b[..., 2])], -1)


def inverse(a: ArrayLike) -> F64:
    """⊖a: the inverse transform, so that compose(a, inverse(a)) is the identity."""
    a = np.asarray(a, dtype=np.float64)
    c, s = np.cos(a[..., 2]), np.sin(a[..., 2])
    x = -c * a[..., 0] - s * a[..., 1]
    y = s * a[..., 0] - c * a[..., 1]
    return np.stack([x, y, wrap_angle(-a[..., 2])], -1)


def between(a: ArrayLike, b: ArrayLike) -> F64:
    """⊖a ⊕ b: the pose of b expressed in the frame of a (a relative motion)."""
    return compose(inverse(a), b)


def transform_points(pose: ArrayLike, points: ArrayLike) -> F64:
    """Map points (..., n, 2) from the body frame of ``pose`` (..., 3) into its parent frame."""
    p = np.asarray(pose, dtype=np.float64)
    pts = np.asarray(points, dtype=np.float64)
    return cast(F64, np.einsum("...ij,...nj->...ni", rot(p[..., 2]), pts) + p[..., None, :2])


def to_matrix(a: ArrayLike) -> F64:
    """Homogeneous 3x3 matrices, shape (..., 3, 3)."""
    a = np.asarray(a, dtype=np.float64)
    m = np.zeros(a.shape[:-1] + (3, 3))
    m[..., :2, :2] = rot(a[..., 2])
    m[..., :2, 2] = a[..., :2]
    m[..., 2, 2] = 1.0
    return m


def from_matrix(m: ArrayLike) -> F64:
    """Inverse of :func:`to_matrix`: (..., 3, 3) -> (..., 3)."""
    m = np.asarray(m, dtype=np.float64)
    return np.stack([m[..., 0, 2], m[..., 1, 2], np.arctan2(m[..., 1, 0], m[..., 0, 0])], -1)


def interpolate(t_query: ArrayLike, t: ArrayLike, poses: ArrayLike) -> F64:
    """Linearly interpolate poses (n, 3) sampled at increasing times t (n,) at t_query (m,).

    Positions interpolate linearly; headings along the shorter arc. Queries outside
    [t[0], t[-1]] are clamped to the end poses.
    """
    tq = np.asarray(t_query, dtype=np.float64)
    tt = np.asarray(t, dtype=np.float64)
    p = np.asarray(poses, dtype=np.float64)
    yaw = np.unwrap(p[:, 2])
    return np.stack(
        [np.interp(tq, tt, p[:, 0]), np.interp(tq, tt, p[:, 1]), wrap_angle(np.interp(tq, tt, yaw))], -1
    )
