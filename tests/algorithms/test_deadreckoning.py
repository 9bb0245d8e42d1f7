"""Dead reckoning: the float fast path equals the SE(2) formula it implements."""

from __future__ import annotations

import numpy as np
import pytest

from slamreplay.algorithms.common import se2
from slamreplay.algorithms.deadreckoning import DeadReckoning


def test_matches_se2_composition() -> None:
    """x_k = start + (-o_0 + o_k) for random poses, headings wrapped to [-pi, pi)."""
    rng = np.random.default_rng(4)
    start = np.array([3.0, -2.0, 2.5])
    dr = DeadReckoning(start)
    odom = rng.normal(size=(500, 3)) * [20.0, 20.0, 6.0]
    for o in odom:
        got = dr.step(o)
        np.testing.assert_allclose(got, se2.compose(start, se2.between(odom[0], o)), atol=1e-12)
        assert -np.pi <= got[2] < np.pi
    np.testing.assert_allclose(dr.step(odom[0]), start, atol=1e-12)


def test_bad_pose_raises() -> None:
    """A pose that is not (3,) is a ValueError naming the argument."""
    with pytest.raises(ValueError, match="odom_pose must be a"):
        DeadReckoning(np.zeros(3)).step([1.0, 2.0])
    with pytest.raises(ValueError, match="start_pose must be"):
        DeadReckoning([0.0, np.nan, 0.0])
