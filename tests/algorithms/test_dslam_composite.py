"""Composite scans (algorithms/dslam/composite.py): the window's algebra, and D-SLAM with a sparse sensor."""

from __future__ import annotations

import numpy as np
import pytest
from numpy.typing import NDArray

from slamreplay.algorithms.common import se2
from slamreplay.algorithms.common.motion import OdometryNoise
from slamreplay.algorithms.common.rangebearing import to_points
from slamreplay.algorithms.dslam import DSlam, DSlamConfig, ScanStatus
from slamreplay.algorithms.dslam.composite import CompositeScan, _move

F64 = NDArray[np.float64]
GATE = 18.42  # chi-square 0.9999, 2 dof


def window() -> CompositeScan:
    return CompositeScan(max_scans=100, max_distance_m=10.0, max_heading_sigma_rad=10.0)


def reading_cov(sr: float, sb: float, k: int = 1) -> F64:
    return np.tile(np.diag([sr**2, sb**2]), (k, 1, 1))


def test_a_composite_of_one_scan_is_that_scan() -> None:
    w = window()
    r, b = np.array([2.0, 5.0]), np.array([0.3, -1.2])
    w.add([1, 2], r, b, reading_cov(0.1, 0.02, 2), scan=0)
    comp = w.take(1, GATE)
    np.testing.assert_allclose(comp.ranges, r)
    np.testing.assert_allclose(comp.bearings, b)
    np.testing.assert_allclose(comp.cov, np.diag([0.01, 0.0004, 0.01, 0.0004]), atol=1e-15)
    assert comp.keys.tolist() == [1, 2] and len(w) == 0


def test_moving_readings_known_answer_and_covariance_against_monte_carlo() -> None:
    """Readings brought over a link land where the geometry says; C' matches sampled link and reading noise."""
    points = np.array([[2.0, 0.0], [3.0 * np.cos(0.5), 3.0 * np.sin(0.5)]])
    c0 = np.diag([0.05, 0.02, 0.03, 0.04]) ** 2
    u, q = np.array([1.0, 0.2, np.pi / 2]), np.diag([0.02, 0.01, 0.03]) ** 2
    moved, cov = _move(points, c0, u, q)
    np.testing.assert_allclose(moved, se2.transform_points(se2.inverse(u), points), atol=1e-12)
    rng = np.random.default_rng(3)
    z = rng.multivariate_normal(points.reshape(-1), c0, 200_000).reshape(-1, 2, 2)
    us = rng.multivariate_normal(u, q, len(z))
    c, s = np.cos(us[:, 2]), np.sin(us[:, 2])
    d = z - us[:, None, :2]
    sampled = np.stack([c[:, None] * d[..., 0] + s[:, None] * d[..., 1],
                        -s[:, None] * d[..., 0] + c[:, None] * d[..., 1]], -1).reshape(len(z), -1)
    np.testing.assert_allclose(cov, np.cov(sampled.T), atol=3e-5)  # linearised vs sampled (small noise)
    assert abs(cov[0, 2]) > 1e-4  # the shared link correlates the two readings


def test_odometry_links_compose_and_standing_still_adds_nothing() -> None:
    """Two scans with increments between them: the older reading arrives in the newer frame; no motion, no noise."""
    w = window()
    w.add([1], np.array([2.0]), np.array([0.0]), reading_cov(0.1, 0.02), scan=0)
    for _ in range(4):
        w.move(np.array([0.25, 0.0, 0.0]), np.diag([1e-4, 1e-4, 1e-4]))
    w.move(np.zeros(3), np.eye(3))  # standing still: ignored
    w.add([2], np.array([1.0]), np.array([np.pi / 2]), reading_cov(0.1, 0.02), scan=1)
    comp = w.take(2, GATE)
    np.testing.assert_allclose(comp.ranges, [1.0, 1.0], atol=1e-12)
    np.testing.assert_allclose(comp.bearings, [0.0, np.pi / 2], atol=1e-12)
    assert comp.cov[0, 0] == pytest.approx(0.01 + 4e-4, rel=1e-9)  # range 0.1^2 plus 4 increments' 1e-4 along x
    w.add([1], np.array([2.0]), np.array([0.0]), reading_cov(0.1, 0.02), scan=2)
    w.move(np.zeros(3), np.eye(3))
    w.add([2], np.array([1.0]), np.array([0.4]), reading_cov(0.1, 0.02), scan=3)
    np.testing.assert_allclose(w.take(2, GATE).cov, np.diag([0.01, 0.0004, 0.01, 0.0004]), atol=1e-15)


def test_two_readings_fuse_to_the_information_weighted_mean() -> None:
    """Independent readings of one landmark from one pose: (P1^-1 + P2^-1)^-1 and the weighted mean."""
    w = window()
    w.add([5], np.array([4.0]), np.array([0.10]), reading_cov(0.2, 0.01), scan=0)
    w.add([5], np.array([4.1]), np.array([0.105]), reading_cov(0.05, 0.03), scan=1)
    p, jac = to_points(np.array([4.0, 4.1]), np.array([0.10, 0.105]))
    c1 = jac[0] @ reading_cov(0.2, 0.01)[0] @ jac[0].T
    c2 = jac[1] @ reading_cov(0.05, 0.03)[0] @ jac[1].T
    info = np.linalg.inv(c1) + np.linalg.inv(c2)
    fused = np.linalg.solve(info, np.linalg.solve(c1, p[0]) + np.linalg.solve(c2, p[1]))
    comp = w.take(2, GATE)
    assert comp.keys.tolist() == [5] and comp.readings == 2 and comp.rejected == 0
    np.testing.assert_allclose([comp.ranges[0] * np.cos(comp.bearings[0]), comp.ranges[0] * np.sin(comp.bearings[0])],
                               fused, rtol=1e-9)
    _, polar_cov = comp.ranges, comp.cov
    j = np.array([[fused[0], fused[1]] / np.hypot(*fused), [-fused[1], fused[0]] / np.sum(fused**2)])
    np.testing.assert_allclose(polar_cov, j @ np.linalg.inv(info) @ j.T, rtol=1e-9)


def test_a_reading_that_disagrees_is_dropped_from_the_fusion() -> None:
    w = window()
    for scan, bearing in enumerate((0.1, 0.1005, 2.9, 0.0995)):
        w.add([5, 6], np.array([4.0, 2.0]), np.array([bearing, -0.4]), reading_cov(0.1, 0.01, 2), scan=scan)
    comp = w.take(4, GATE)
    assert comp.rejected == 1 and comp.readings == 8
    assert comp.bearings[0] == pytest.approx(0.1, abs=1e-3)


def test_split_rule_keeps_a_bridge_of_two_mapped_landmarks() -> None:
    """Cut at the latest scan leaving two landmarks that will be mapped; none when that is impossible."""
    w = window()
    one = reading_cov(0.1, 0.02)
    for scan, keys in enumerate(([1, 2], [2], [2, 3], [3, 4], [3, 4])):
        w.add(keys, np.full(len(keys), 2.0), np.zeros(len(keys)), np.repeat(one, len(keys), 0), scan)
    assert w.split({1, 2}) == 4  # scans 0-3 map 3 and 4 on anchors 1, 2; scan 4 keeps 3 and 4 as the bridge
    assert w.split({1}) == 0  # one anchor: nothing can be mapped
    chain = window()
    for scan, keys in enumerate(([1, 2], [2, 3], [3, 4])):
        chain.add(keys, np.full(2, 2.0), np.zeros(2), np.repeat(one, 2, 0), scan)
    assert chain.split({1, 2}) == 0  # a strict chain: no cut leaves both parts two anchors


def test_scans_beyond_the_window_expire() -> None:
    w = CompositeScan(max_scans=5, max_distance_m=1.0, max_heading_sigma_rad=10.0)
    w.add([1], np.array([2.0]), np.array([0.0]), reading_cov(0.1, 0.02), scan=0)
    w.move(np.array([0.6, 0.0, 0.0]), np.eye(3) * 1e-6)
    w.add([2], np.array([2.0]), np.array([0.5]), reading_cov(0.1, 0.02), scan=1)
    assert not w.expired(1)
    w.move(np.array([0.6, 0.0, 0.0]), np.eye(3) * 1e-6)
    assert w.expired(2)  # 1.2 m since scan 0
    w.drop_oldest()
    assert not w.expired(2) and w.expired(6) and w.keys() == {2}


# -- D-SLAM with a sensor that sees about one landmark at a time

START = np.array([0.0, 0.0, 0.0])
NOISE = OdometryNoise(0.03, 0.03, 0.05)
SIGMA_R, SIGMA_B = 0.05, np.radians(1.0)


def sparse_world(seed: int, steps: int = 900) -> tuple[F64, list[tuple[F64, F64, F64, F64, NDArray[np.int64]]]]:
    """Pairs of landmarks 1 m left and right of a 12 m x 8 m loop, every 2.5 m; a 60-degree, 3.5 m sensor sees one pair
    at most, with stretches between pairs where it sees nothing (MRCLAM-like: the one-scan rule maps no pair after
    the first).

    The robot stands still 10 steps (phase I, seeing the first two landmarks) and then drives
    the loop twice at 0.2 m/s (0.2 s steps).
    """
    rng = np.random.default_rng(seed)
    corners = [np.array(c) for c in ([12.0, 0.0], [12.0, 8.0], [0.0, 8.0], [0.0, 0.0])]
    landmarks = [[2.5, 0.7], [2.9, -0.6]]  # seen from the start (phase I)
    for (a, b) in zip([corners[-1], *corners[:-1]], corners, strict=True):  # a pair across each leg every 2.5 m
        along, normal = (b - a) / np.hypot(*(b - a)), np.array([-(b - a)[1], (b - a)[0]]) / np.hypot(*(b - a))
        for s in np.arange(1.5, np.hypot(*(b - a)) - 1.0, 2.5):
            landmarks += [list(a + s * along + normal), list(a + s * along - normal)]
    lm = np.array(landmarks)
    pose, out = START.copy(), []
    target = 0
    for k in range(steps):
        u = np.zeros(3)
        if k >= 10:
            goal = corners[target]
            if np.hypot(*(goal - pose[:2])) < 0.3:
                target = (target + 1) % 4
                goal = corners[target]
            turn = se2.wrap_angle(np.arctan2(goal[1] - pose[1], goal[0] - pose[0]) - pose[2])
            u = np.array([0.04, 0.0, float(np.clip(turn, -0.12, 0.12))])
        pose = se2.compose(pose, u)
        odo = u + (rng.normal(0, [0.004, 0.001, 0.004]) if k >= 10 else 0.0)
        rel = se2.transform_points(se2.inverse(pose), lm)
        r, b = np.hypot(rel[:, 0], rel[:, 1]), np.arctan2(rel[:, 1], rel[:, 0])
        ids = np.flatnonzero((r < 3.5) & (np.abs(b) < np.radians(30)))
        out.append((odo, pose.copy(), r[ids] + rng.normal(0, SIGMA_R, len(ids)),
                    b[ids] + rng.normal(0, SIGMA_B, len(ids)), ids))
    return lm, out


def run_sparse(seed: int, composite: int) -> tuple[DSlam, list[ScanStatus], F64]:
    landmarks, steps = sparse_world(seed)
    slam = DSlam(DSlamConfig(odometry_noise=NOISE, composite_max_scans=composite, composite_max_distance_m=6.0))
    statuses = []
    for odo, _, r, b, ids in steps:
        slam.predict(odo)
        statuses.append(slam.observe(r, b, ids, SIGMA_R, SIGMA_B).status)
    slam.finalize()
    return slam, statuses, landmarks


def test_composite_scans_map_what_single_scans_cannot() -> None:
    """One-scan rule: few landmarks mapped; composite scans: every landmark seen, accurate and not overconfident."""
    seen = {int(i) for *_, ids in sparse_world(1)[1] for i in ids}
    plain, _, _ = run_sparse(1, 0)
    slam, statuses, landmarks = run_sparse(1, 400)
    assert plain.n < len(seen) // 2
    assert slam.n == len(seen) and ScanStatus.MAPPED in statuses
    est, cov = slam.estimates(), slam.marginal_covariances()
    err = est - landmarks[np.asarray(slam.feature_ids)]
    rmse = float(np.sqrt(np.mean(np.sum(err**2, 1))))
    nees = float(np.mean(np.einsum("ni,nij,nj->n", err, np.linalg.inv(cov), err)))
    assert rmse < 0.8 and nees <= 2.0, (rmse, nees)  # 0.55 m, 1.06: consistent; bridges of up to 6 m of odometry


def test_composite_runs_are_deterministic_and_unknown_ids_ignore_the_window() -> None:
    a, sa, _ = run_sparse(2, 400)
    b, sb, _ = run_sparse(2, 400)
    assert sa == sb
    np.testing.assert_array_equal(a.estimates(), b.estimates())
    assert DSlam(DSlamConfig(association="unknown", composite_max_scans=10)).window is None


@pytest.mark.parametrize("field", ["composite_max_distance_m", "composite_max_heading_sigma_rad"])
def test_composite_config_is_checked(field: str) -> None:
    with pytest.raises(ValueError, match=field):
        DSlamConfig(**{field: 0.0})  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="composite_max_scans"):
        DSlamConfig(composite_max_scans=-1)


def test_a_misread_id_does_not_start_a_feature() -> None:
    """Known ids with the outlier gate: a reading of an unmapped id far from its earlier readings is not used."""
    from slamreplay.algorithms.common.association import AssociationConfig

    slam = DSlam(DSlamConfig(odometry_noise=NOISE, association_params=AssociationConfig(outlier_probability=0.9999)))
    anchors_r, anchors_b = np.array([2.0, 2.5]), np.array([0.4, -0.3])
    for _ in range(3):  # phase I: two features
        slam.observe(anchors_r, anchors_b, [0, 1], SIGMA_R, SIGMA_B)
    slam.predict(np.array([0.05, 0.0, 0.0]))
    for _ in range(3):  # landmark 5 alone, not mapped yet (fewer than two mapped features)
        res = slam.observe([4.0], [0.0], [5], SIGMA_R, SIGMA_B)
        assert res.status is ScanStatus.LOCALIZATION_ONLY
    rejected = slam.rejected
    res = slam.observe([*(anchors_r - 0.05), 3.5], [*anchors_b, 2.8], [0, 1, 5], SIGMA_R, SIGMA_B)  # "5" behind
    assert slam.rejected == rejected + 1 and 5 not in slam.feature_ids
    slam.observe([*(anchors_r - 0.05), 3.95], [*anchors_b, 0.0], [0, 1, 5], SIGMA_R, SIGMA_B)
    assert 5 in slam.feature_ids
    np.testing.assert_allclose(slam.estimates()[slam.feature_ids.index(5)], [4.0, 0.0], atol=0.15)


def test_scans_expire_when_the_odometry_heading_is_too_uncertain() -> None:
    w = CompositeScan(max_scans=100, max_distance_m=10.0, max_heading_sigma_rad=0.4)
    w.add([1], np.array([2.0]), np.array([0.0]), reading_cov(0.1, 0.02), scan=0)
    w.move(np.array([0.1, 0.0, 0.5]), np.diag([1e-4, 1e-4, 0.1]))
    assert not w.expired(1)  # heading sigma 0.32 rad
    w.move(np.array([0.1, 0.0, 0.5]), np.diag([1e-4, 1e-4, 0.1]))
    assert w.expired(1)  # 0.45 rad
