"""SE(2) invariants (Hypothesis): inverses, associativity, matrix round trips, interpolation ends."""

from __future__ import annotations

import numpy as np
from hypothesis import given
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from slamreplay.algorithms.common import se2

coords = st.floats(-100, 100, allow_nan=False)
poses = st.tuples(coords, coords, st.floats(-np.pi, np.pi - 1e-9)).map(np.array)


def close(a: np.ndarray, b: np.ndarray, tol: float = 1e-9) -> bool:
    d = np.asarray(a) - np.asarray(b)
    d[..., 2] = se2.wrap_angle(d[..., 2])
    return bool(np.all(np.abs(d) < tol))


@given(poses, poses)
def test_between_inverts_compose(a: np.ndarray, b: np.ndarray) -> None:
    """between(a, a ⊕ b) == b and a ⊕ ⊖a == identity."""
    assert close(se2.between(a, se2.compose(a, b)), b, 1e-7)
    assert close(se2.compose(a, se2.inverse(a)), np.zeros(3), 1e-7)


@given(poses, poses, poses)
def test_compose_is_associative_and_matches_matrices(a: np.ndarray, b: np.ndarray, c: np.ndarray) -> None:
    """(a ⊕ b) ⊕ c == a ⊕ (b ⊕ c), and composition is the product of homogeneous matrices."""
    assert close(se2.compose(se2.compose(a, b), c), se2.compose(a, se2.compose(b, c)), 1e-6)
    assert close(se2.from_matrix(se2.to_matrix(a) @ se2.to_matrix(b)), se2.compose(a, b), 1e-6)


@given(poses, arrays(np.float64, (5, 2), elements=coords))
def test_transform_points_matches_compose(p: np.ndarray, pts: np.ndarray) -> None:
    """Transforming a point equals composing a pose with zero heading."""
    as_poses = np.column_stack([pts, np.zeros(5)])
    assert np.allclose(se2.transform_points(p, pts), se2.compose(p, as_poses)[:, :2], atol=1e-7)


def test_wrap_and_interpolate() -> None:
    """Angles wrap to [-pi, pi); interpolation takes the short arc and clamps at the ends."""
    assert np.allclose(se2.wrap_angle([3 * np.pi, -np.pi, 0.5]), [-np.pi, -np.pi, 0.5])
    t = [0.0, 1.0]
    poses_ = np.array([[0, 0, np.pi - 0.1], [2, 0, -np.pi + 0.1]])
    mid = se2.interpolate([0.5, -1.0, 2.0], t, poses_)
    assert np.allclose(mid[0, :2], [1, 0]) and abs(abs(mid[0, 2]) - np.pi) < 1e-9
    assert np.allclose(mid[1], poses_[0]) and np.allclose(mid[2], poses_[1])
