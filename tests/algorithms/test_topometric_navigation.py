"""Navigation mode of the topo-metric map (paper section IV): Dijkstra, Fig. 3, path following."""

from __future__ import annotations

import math

import numpy as np
import pytest

from slamreplay.algorithms.common import se2
from slamreplay.algorithms.topometric.guidance import (
    GuidanceConfig,
    NavGraph,
    Navigator,
    QualitativePose,
    RouteConfig,
    VisualMatch,
    heading_deviation_rad,
    plan_route,
)
from slamreplay.algorithms.topometric.pathfollow import FollowerConfig, PathFollower, discretize, distance_to_polyline

EAST, NORTH, WEST = 0.0, 0.5 * math.pi, math.pi


def loop_graph() -> NavGraph:
    """Corridor A (0..4) recorded eastwards along y=0, corridor B (5..9) westwards along y=2, joined at the ends."""
    a = [(x, 0.0, EAST) for x in range(5)]
    b = [(4.0 - x, 2.0, WEST) for x in range(5)]
    edges = [(k, k + 1) for k in range(9)] + [(9, 0)]
    return NavGraph(np.array(a + b, float), np.array(edges))


def test_dijkstra_shortest_path_on_a_small_graph() -> None:
    """Without orientation costs Dijkstra returns the metric shortest path."""
    cfg = RouteConfig(turn_cost_m_per_rad=0.0, against_map_factor=1.0)
    route = plan_route(loop_graph(), 1, 8, cfg=cfg)
    assert route is not None
    assert route.nodes == (1, 0, 9, 8)
    assert route.length_m == pytest.approx(4.0)


def test_dijkstra_does_not_reverse_against_the_recorded_headings() -> None:
    """From the corridor's end back to its start the route goes round the loop, not backwards through it."""
    g = loop_graph()
    route = plan_route(g, 4, 0)
    assert route is not None
    assert route.nodes == (4, 5, 6, 7, 8, 9, 0)
    # Orientation off: straight back through the corridor.
    flat = plan_route(g, 4, 0, cfg=RouteConfig(turn_cost_m_per_rad=0.0, against_map_factor=1.0))
    assert flat is not None and flat.nodes == (4, 3, 2, 1, 0)
    # When there is no other way, reversing is allowed.
    line = NavGraph(g.poses[:5], np.array([(k, k + 1) for k in range(4)]))
    back = plan_route(line, 4, 0)
    assert back is not None and back.nodes == (4, 3, 2, 1, 0)


def test_dijkstra_counts_the_turn_from_the_start_heading() -> None:
    """Two equally long ways: the one ahead of the robot wins."""
    poses = np.array([(0, 0, EAST), (1, 0, EAST), (-1, 0, WEST), (0, 1, NORTH)], float)
    g = NavGraph(poses, np.array([(0, 1), (1, 3), (0, 2), (2, 3)]))
    east = plan_route(g, 0, 3, start_yaw=EAST)
    west = plan_route(g, 0, 3, start_yaw=WEST)
    assert east is not None and east.nodes == (0, 1, 3)
    assert west is not None and west.nodes == (0, 2, 3)


def test_dijkstra_bad_input_and_unreachable() -> None:
    """A node outside the map raises; a disconnected goal gives None."""
    g = NavGraph(np.array([(0, 0, 0), (1, 0, 0), (5, 5, 0)], float), np.array([(0, 1)]))
    with pytest.raises(ValueError, match="goal node 7"):
        plan_route(g, 0, 7)
    assert plan_route(g, 0, 2) is None
    assert plan_route(g, 1, 1) is not None
    with pytest.raises(ValueError, match="cannot be reached"):
        Navigator(g, 0, 2, None)


def test_heading_from_x_translation_reproduces_fig3() -> None:
    """Fig. 3: 33 px of x-translation in a 320 px image give 4.73 deg; the linear rule at 46 deg gives 4.74."""
    hfov = math.radians(46.0)
    linear = math.degrees(heading_deviation_rad(33.0, 320, hfov))
    pinhole = math.degrees(heading_deviation_rad(33.0, 320, hfov, rule="pinhole"))
    assert linear == pytest.approx(4.73, abs=0.015)
    assert pinhole == pytest.approx(5.00, abs=0.01)  # the pinhole rule does not give the paper's number
    implied_linear = 4.73 * 320 / 33  # hfov that makes the linear rule exact
    assert implied_linear == pytest.approx(45.87, abs=0.01)
    implied_pinhole = 2 * math.degrees(math.atan(160 / (33 / math.tan(math.radians(4.73)))))
    assert implied_pinhole == pytest.approx(43.7, abs=0.05)
    assert heading_deviation_rad(-33.0, 320, hfov) == pytest.approx(-math.radians(linear))
    with pytest.raises(ValueError, match="width_px"):
        heading_deviation_rad(1.0, 0, hfov)


def test_qualitative_pose_between_and_at_loop_closures() -> None:
    """Node position with corrected heading at a closure, then odometry composed since it."""
    q = QualitativePose([0.0, 0.0, 0.0], [10.0, 10.0, 1.0])
    moved = se2.compose([10.0, 10.0, 1.0], [1.0, 0.0, 0.0])
    np.testing.assert_allclose(q.predict(moved), [1.0, 0.0, 0.0], atol=1e-12)
    q.correct([2.0, 3.0, 0.5], 0.1, moved)
    np.testing.assert_allclose(q.pose, [2.0, 3.0, 0.6])
    later = se2.compose(moved, [0.5, 0.0, 0.0])
    np.testing.assert_allclose(q.predict(later), [2.0 + 0.5 * math.cos(0.6), 3.0 + 0.5 * math.sin(0.6), 0.6])


def test_discretize_every_centimetre() -> None:
    """Consecutive points are 1 cm apart along the path, corners included; ends are kept."""
    pts = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 0.505]])
    path = discretize(pts, 0.01)
    steps = np.hypot(*np.diff(path, axis=0).T)
    np.testing.assert_allclose(path[0], pts[0])
    np.testing.assert_allclose(path[-1], pts[-1])
    assert len(path) == 152  # 150 intervals of 1 cm, then 0.5 cm
    arc = np.concatenate([[0.0], np.cumsum(steps)])
    np.testing.assert_allclose(arc[:-1], np.arange(151) * 0.01, atol=1e-9)
    assert np.all(steps <= 0.01 + 1e-12)
    assert len(discretize([[1.0, 1.0], [1.0, 1.0]])) == 1


def test_local_path_and_target_selection() -> None:
    """The local path joins the global path 40 cm ahead; the target is the first point beyond 20 cm."""
    path = discretize([[0.0, 0.0], [5.0, 0.0]])
    f = PathFollower(path)
    local = f.replan([0.0, 0.3, 0.0])
    np.testing.assert_allclose(local[0], [0.0, 0.3])
    join = np.flatnonzero(np.isclose(local[:, 1], 0.0))[0]
    np.testing.assert_allclose(local[join], [0.4, 0.0], atol=1e-9)
    np.testing.assert_allclose(local[join + 1:], path[41:])
    cmd = f.command([0.0, 0.3, 0.0], 0.1)
    assert cmd.target is not None
    assert math.hypot(*(cmd.target - [0.0, 0.3])) == pytest.approx(0.2, abs=0.011)
    assert cmd.heading_error_rad < 0 and cmd.angular_radps < 0  # towards the path, on the right
    assert cmd.linear_mps == FollowerConfig().linear_speed_mps
    # Behind the robot at 90 deg off: turn on the spot.
    f2 = PathFollower(path)
    f2.replan([0.0, 0.0, 0.5 * math.pi])
    assert f2.command([0.0, 0.0, 0.5 * math.pi], 0.1).linear_mps == 0.0


def drive(follower: PathFollower, pose: np.ndarray, steps: int, dt: float = 0.1) -> list[np.ndarray]:
    """A perfectly localized unicycle under the follower's commands, replanning every 10 steps."""
    out = [pose]
    for k in range(steps):
        if k % 10 == 0:
            follower.replan(pose)
        cmd = follower.command(pose, dt)
        if cmd.reached:
            break
        pose = se2.compose(pose, [cmd.linear_mps * dt, 0.0, cmd.angular_radps * dt])
        out.append(pose)
    return out


def test_pid_converges_to_a_straight_line_from_an_offset() -> None:
    """Starting 30 cm beside the line, the robot joins it and stops at the end within tolerance."""
    path = discretize([[0.0, 0.0], [6.0, 0.0]])
    f = PathFollower(path)
    poses = np.array(drive(f, np.array([0.0, 0.3, 0.2]), 400))
    assert f.reached
    after = poses[poses[:, 0] > 2.0]
    assert np.max(np.abs(after[:, 1])) < 0.02
    assert math.hypot(*(poses[-1, :2] - path[-1])) <= FollowerConfig().goal_tolerance_m + 0.03
    assert distance_to_polyline([[1.0, 0.5], [7.0, 0.0]], path).tolist() == pytest.approx([0.5, 1.0])


def corridor_map(n: int = 41, spacing: float = 0.5) -> NavGraph:
    """An L-shaped mapped route: 10 m east then 10 m north, a node every 50 cm."""
    pts = []
    for k in range(n):
        s = k * spacing
        pts.append((s, 0.0, EAST) if s <= 10.0 else (10.0, s - 10.0, NORTH))
    return NavGraph(np.array(pts), np.array([(k, k + 1) for k in range(n - 1)]))


def closed_loop(visual: bool, seed: int = 3) -> tuple[np.ndarray, Navigator]:
    """Drive the L with odometry that drifts in heading; a perfect camera matches the nearest node.

    The paper's rule (position = the matched node's): exact with a matcher that picks the nearest node.
    """
    g = corridor_map()
    truth = g.poses[0].copy()
    width, hfov = 320, math.radians(46.0)

    def localizer(pixels: np.ndarray, motion: np.ndarray | None) -> VisualMatch | None:
        k = int(np.argmin(np.hypot(*(g.poses[:, :2] - truth[:2]).T)))
        dyaw = float(se2.wrap_angle(truth[2] - g.poses[k, 2]))
        return VisualMatch(k, dyaw * width / hfov)  # the linear rule, inverted

    rng = np.random.default_rng(seed)
    nav = Navigator(g, 0, len(g.poses) - 1, localizer, GuidanceConfig(visual_correction=visual, keep_along_m=0.0))
    odom = np.zeros(3)
    dt = 0.1
    image = np.zeros((240, width), np.uint8)
    trail = [truth.copy()]
    for _ in range(2000):
        nav.on_odometry(odom)
        if nav.image_due():
            nav.on_image(image)
        cmd = nav.control(dt)
        if cmd.reached:
            break
        inc = np.array([cmd.linear_mps * dt, 0.0, cmd.angular_radps * dt])
        truth = se2.compose(truth, inc)
        # Wheel odometry: 2 % scale error and a heading bias of 3 deg per metre, plus noise.
        noisy = inc * [1.02, 1.0, 1.0] + [0.0, 0.0, math.radians(3.0) * inc[0]] + rng.normal(0, [1e-4, 1e-4, 1e-4])
        odom = se2.compose(odom, noisy)
        trail.append(truth.copy())
    return np.array(trail), nav


def test_vision_keeps_a_drifting_robot_on_the_path_and_odometry_alone_does_not() -> None:
    """Fig. 4's point on a synthetic map: corrected the robot stays within 15 cm of the path, uncorrected > 1 m."""
    on, nav_on = closed_loop(True)
    off, nav_off = closed_loop(False)
    path = nav_on.global_path
    xt_on = distance_to_polyline(on[:, :2], path)
    xt_off = distance_to_polyline(off[:, :2], path)
    assert nav_on.reached and nav_on.corrections > 30
    assert xt_on.max() < 0.15 and xt_on.mean() < 0.05
    assert nav_off.corrections == 0 and nav_off.matches > 0
    assert xt_off.max() > 1.0


def test_correct_resets_the_position_to_the_node_with_the_papers_rule() -> None:
    """keep_along_m 0 (the paper, the default): the position becomes the node's, whatever the estimate was; the
    heading the node's plus the deviation. keep_along_m 1: the offset along the node's heading stays, clamped."""
    assert GuidanceConfig().keep_along_m == 0.0
    node = [2.0, 3.0, NORTH]
    for estimate in ([2.4, 3.7, 0.2], [1.0, 1.0, -2.0]):
        q = QualitativePose(estimate, [0.0, 0.0, 0.0])
        np.testing.assert_allclose(q.correct(node, 0.1, [5.0, 0.0, 0.0], keep_along_m=0.0),
                                   [2.0, 3.0, NORTH + 0.1], atol=1e-12)
        np.testing.assert_allclose(q.anchor_odom, [5.0, 0.0, 0.0])
    q = QualitativePose([2.4, 3.7, 0.2], [0.0, 0.0, 0.0])  # 0.7 m along the node's heading (north), 0.4 m across
    np.testing.assert_allclose(q.correct(node, 0.0, [0.0, 0.0, 0.0], keep_along_m=1.0), [2.0, 3.7, NORTH],
                               atol=1e-12)
    q = QualitativePose([2.0, 1.0, 0.0], [0.0, 0.0, 0.0])  # 2 m behind: clamped to 1 m
    np.testing.assert_allclose(q.correct(node, 0.0, [0.0, 0.0, 0.0], keep_along_m=1.0)[:2], [2.0, 2.0],
                               atol=1e-12)


@pytest.mark.parametrize("value", [-0.5, math.inf, math.nan])
def test_guidance_rejects_a_bad_keep_along(value: float) -> None:
    """keep_along_m must be finite and >= 0."""
    with pytest.raises(ValueError, match=r"keep_along_m must be finite and >= 0"):
        GuidanceConfig(keep_along_m=value)
