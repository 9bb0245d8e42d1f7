"""The pole extractor and the tf tree: known answers."""

from __future__ import annotations

import math

import numpy as np
import pytest

from slamreplay.recorder.errors import RecorderError
from slamreplay.recorder.importers.poles import PoleConfig, extract_poles
from slamreplay.recorder.importers.tf_tree import TfTree


def _scan(poles: list[tuple[float, float, float]], walls: float | None = None, noise: float = 0.0,
          inc: float = math.pi / 720) -> tuple[np.ndarray, float, float]:
    a = -math.pi / 2 + inc * np.arange(721)
    r = np.full(len(a), np.inf) if walls is None else walls / np.maximum(np.cos(a), 1e-3)
    for px, py, rad in poles:
        b = np.cos(a) * px + np.sin(a) * py
        disc = b * b - (px * px + py * py - rad * rad)
        t = b - np.sqrt(np.maximum(disc, 0))
        r = np.where((disc >= 0) & (t > 0) & (t < r), t, r)
    r = r + np.random.default_rng(0).normal(0, noise, len(r)) if noise else r
    return r, -math.pi / 2, inc


@pytest.mark.parametrize("fit", [True, False])
def test_poles_found_at_their_centres(fit: bool) -> None:
    """Three poles in free space: centres within 2 cm (fit) or 6 cm (width estimate), radii close, sigmas > floor."""
    truth = [(5.0, 1.0, 0.2), (10.0, -3.0, 0.15), (3.0, 4.0, 0.3)]
    p = extract_poles(*_scan(truth, noise=0.005), PoleConfig(circle_fit=fit))
    assert len(p) == 3
    xy = np.column_stack([p.ranges_m * np.cos(p.bearings_rad), p.ranges_m * np.sin(p.bearings_rad)])
    for x, y, rad in truth:
        k = int(np.argmin(np.hypot(xy[:, 0] - x, xy[:, 1] - y)))
        assert math.hypot(xy[k, 0] - x, xy[k, 1] - y) < (0.02 if fit else 0.06)
        assert abs(p.radii_m[k] - rad) < 0.05
    assert np.all(p.range_sigmas_m >= 0.05) and np.all(p.bearing_sigmas_rad >= 0.01)


def test_wall_and_wide_objects_are_not_poles() -> None:
    """A wall is one wide segment, a pole against it is not isolated unless well in front of it."""
    assert len(extract_poles(*_scan([], walls=8.0), PoleConfig())) == 0
    assert len(extract_poles(*_scan([(7.9, 0.0, 0.2)], walls=8.0), PoleConfig())) == 0  # touching the wall
    assert len(extract_poles(*_scan([(5.0, 0.0, 0.2)], walls=8.0), PoleConfig())) == 1
    assert len(extract_poles(*_scan([(5.0, 0.0, 1.5)]), PoleConfig())) == 0  # 3 m wide: not a trunk


def test_pole_config_rejects_nonsense() -> None:
    """Bad settings name the key."""
    with pytest.raises(ValueError, match="jump_m"):
        PoleConfig(jump_m=0)
    with pytest.raises(ValueError, match="min_diameter_m must be < max_diameter_m"):
        PoleConfig(min_diameter_m=2.0, max_diameter_m=1.0)


def _q(yaw: float) -> tuple[float, float, float, float]:
    return (0.0, 0.0, math.sin(yaw / 2), math.cos(yaw / 2))


def test_tf_composition_and_interpolation() -> None:
    """map->odom (static) and odom->base (moving): poses composed, interpolated between samples, not extrapolated."""
    tree = TfTree()
    tree.add("map", "odom", 0, (1.0, 2.0, 0.0), _q(math.pi / 2), static=True)
    tree.add("odom", "base_link", 10, (0.0, 0.0, 0.0), _q(0.0), static=False)
    tree.add("odom", "base_link", 30, (2.0, 0.0, 0.0), _q(0.2), static=False)
    tree.add("base_link", "laser", 0, (0.5, 0.0, 0.0), _q(0.0), static=True)
    stamps, poses = tree.planar_poses("map", "base_link")
    assert stamps.tolist() == [10, 30]
    np.testing.assert_allclose(poses[1], [1.0, 4.0, math.pi / 2 + 0.2], atol=1e-12)
    tree.add("map", "odom", 20, (1.0, 2.0, 0.0), _q(math.pi / 2), static=True)
    stamps, poses = tree.planar_poses("odom", "laser")
    np.testing.assert_allclose(poses[0], [0.5, 0.0, 0.0], atol=1e-12)
    assert tree.static_planar("base_link", "laser") == pytest.approx((0.5, 0.0, 0.0))
    mid = TfTree()
    mid.add("odom", "base_link", 0, (0.0, 0.0, 0.0), _q(0.0), static=False)
    mid.add("odom", "base_link", 10, (2.0, 0.0, 0.0), _q(0.4), static=False)
    mid.add("map", "odom", 5, (0.0, 0.0, 0.0), _q(0.0), static=False)
    mid.add("map", "odom", 10, (0.0, 0.0, 0.0), _q(0.0), static=False)
    stamps, poses = mid.planar_poses("map", "base_link")
    assert stamps.tolist() == [5, 10]  # only where both moving edges have samples
    np.testing.assert_allclose(poses[0], [1.0, 0.0, 0.2], atol=1e-12)


def test_tf_errors_name_the_frames() -> None:
    """Missing frame, disconnected trees and static-only links each say what is wrong."""
    tree = TfTree()
    tree.add("odom", "base_link", 1, (0.0, 0.0, 0.0), _q(0.0), static=False)
    tree.add("world", "marker", 1, (0.0, 0.0, 0.0), _q(0.0), static=True)
    with pytest.raises(RecorderError, match=r"no frame 'map' \(frames: base_link, marker, odom, world\)"):
        tree.check_frame("map", "--ground-truth-frame")
    with pytest.raises(RecorderError, match="not connected"):
        tree.planar_poses("world", "base_link")
    with pytest.raises(RecorderError, match="only static"):
        tree.planar_poses("world", "marker")
