"""D-SLAM building blocks with known answers: recasting (eqs. 2-4, 8), eq. (9), eq. (10), recovery, localization."""

from __future__ import annotations

import numpy as np
import pytest
from numpy.typing import NDArray

from slamreplay.algorithms.common import se2
from slamreplay.algorithms.common.rangebearing import noise, predict
from slamreplay.algorithms.dslam import DSlam, DSlamConfig, ScanStatus
from slamreplay.algorithms.dslam.covariance import CovarianceCache
from slamreplay.algorithms.dslam.information import InformationMatrix, dofs
from slamreplay.algorithms.dslam.localization import PoseStatus, measurement_pose
from slamreplay.algorithms.dslam.mapping import choose_anchors, recast_increment
from slamreplay.algorithms.dslam.recast import init_features, map_invariants, recast, robot_invariants
from slamreplay.algorithms.dslam.recovery import Recovery, direct, invert_blocks, pcg

F64 = NDArray[np.float64]
POINTS = np.array([[2.0, 1.0], [3.5, -1.0], [1.0, 3.0], [4.0, 2.5], [-1.0, 2.0]])


def numeric_jacobian(f, x: F64, eps: float = 1e-6) -> F64:  # type: ignore[no-untyped-def]
    """Central differences of f at x (angles in f's output are assumed not to wrap)."""
    cols = []
    for k in range(len(x)):
        d = np.zeros_like(x)
        d[k] = eps
        cols.append((f(x + d) - f(x - d)) / (2 * eps))
    return np.stack(cols, -1)


def test_map_invariants_values_jacobian_and_invariance() -> None:
    """Eq. (8): d_12, alpha_312, d_13 ... by hand; Jacobian = finite differences; rigid motions change nothing."""
    h, jac = map_invariants(POINTS)
    v = POINTS - POINTS[0]
    assert h[0] == pytest.approx(np.hypot(*v[1]))
    assert h[1] == pytest.approx(se2.wrap_angle(np.arctan2(v[2, 1], v[2, 0]) - np.arctan2(v[1, 1], v[1, 0])))
    assert h[2] == pytest.approx(np.hypot(*v[2]))
    assert h.shape == (7,) and jac.shape == (7, 10)
    np.testing.assert_allclose(jac, numeric_jacobian(lambda p: map_invariants(p.reshape(-1, 2))[0], POINTS.ravel()),
                               atol=1e-8)
    moved = se2.transform_points(np.array([3.0, -7.0, 2.2]), POINTS)
    np.testing.assert_allclose(map_invariants(moved)[0], h, atol=1e-12)


def test_robot_invariants_locate_the_robot() -> None:
    """Eq. (3): from z_rob and the anchors' map positions the robot pose follows exactly."""
    pose = np.array([1.5, -0.5, 0.8])
    world = se2.transform_points(pose, POINTS)  # the features in the map frame
    z_rob, jac = robot_invariants(POINTS)
    np.testing.assert_allclose(jac, numeric_jacobian(lambda p: robot_invariants(p.reshape(-1, 2))[0],
                                                     POINTS.ravel()), atol=1e-8)
    alpha_12 = np.arctan2(*(world[1] - world[0])[::-1])
    robot = world[0] + z_rob[1] * np.array([np.cos(alpha_12 + z_rob[0]), np.sin(alpha_12 + z_rob[0])])
    np.testing.assert_allclose(robot, pose[:2], atol=1e-12)
    assert se2.wrap_angle(alpha_12 + z_rob[2]) == pytest.approx(pose[2])


def test_recast_jacobian_matches_finite_differences() -> None:
    """dz_new/dz_old of eqs. (3)-(4) against central differences; R_new = J R_old J^T is full."""
    r = np.hypot(POINTS[:, 0], POINTS[:, 1])
    b = np.arctan2(POINTS[:, 1], POINTS[:, 0])
    rc = recast(r, b, noise(5, 0.05, 0.02))

    def z_new(z: F64) -> F64:
        out = recast(z[0::2], z[1::2], noise(5, 0.05, 0.02))
        return np.concatenate([out.z_rob, out.z_map])

    z_old = np.stack([r, b], -1).ravel()
    np.testing.assert_allclose(rc.jacobian, numeric_jacobian(z_new, z_old), atol=1e-7)
    r_old = np.diag(np.tile([0.05**2, 0.02**2], 5))
    np.testing.assert_allclose(rc.r_new, rc.jacobian @ r_old @ rc.jacobian.T, atol=1e-15)
    off = rc.r_map - np.diag(np.diag(rc.r_map))
    assert np.abs(off).max() > 1e-4 and np.abs(rc.r_new[:3, 3:]).max() > 1e-4  # correlated, not diagonal
    np.testing.assert_allclose(rc.z_map, map_invariants(POINTS)[0], atol=1e-12)


def test_recast_rejects_bad_input() -> None:
    """One feature or a zero sigma cannot be recast."""
    with pytest.raises(ValueError, match="m >= 2"):
        recast(np.array([1.0]), np.array([0.0]), noise(1, 0.1, 0.1))
    with pytest.raises(ValueError, match="r_old must be a positive definite"):
        recast(np.array([1.0, 2.0]), np.array([0.0, 1.0]), noise(2, 0.0, 0.1))


def test_eq9_initialisation_is_exact_and_its_jacobians_match() -> None:
    """Eq. (9) with exact anchors and exact z_map puts new features where they are."""
    world = se2.transform_points(np.array([4.0, 1.0, -1.1]), POINTS)
    z_map, _ = map_invariants(world)
    alpha, dist = z_map[1::2], z_map[2::2]
    pos, j_x, j_z = init_features(world[0], world[1], alpha, dist)
    np.testing.assert_allclose(pos, world[2:], atol=1e-12)
    jx_num = numeric_jacobian(lambda a: init_features(a[:2], a[2:], alpha, dist)[0].ravel(), world[:2].ravel())
    np.testing.assert_allclose(np.concatenate(list(j_x)), jx_num, atol=1e-7)
    jz_num = numeric_jacobian(lambda z: init_features(world[0], world[1], z[:1], z[1:])[0].ravel(),
                              np.array([alpha[0], dist[0]]))
    np.testing.assert_allclose(j_z[0], jz_num, atol=1e-7)


def test_eq10_update_is_exactly_sparse() -> None:
    """Two scans sharing feature 2 link {0,1,2} and {2,3}; features 0 and 3 stay unlinked; i matches eq. (10)."""
    info = InformationMatrix()
    info.add_features(4)
    x = np.array([[0.0, 0.0], [3.0, 0.0], [1.0, 2.0], [3.0, 3.0]])
    for scan in ([0, 1, 2], [2, 3]):
        rel = x[scan] - [0.5, -1]
        rc = recast(np.hypot(*rel.T), np.arctan2(rel[:, 1], rel[:, 0]), noise(len(scan), 0.05, 0.02))
        d_matrix, d_vector = recast_increment(x[scan], rc)
        _, jac = map_invariants(x[scan])
        w = np.linalg.inv(rc.r_map)
        np.testing.assert_allclose(d_matrix, jac.T @ w @ jac, rtol=1e-10)
        innovation = rc.z_map - map_invariants(x[scan])[0]
        np.testing.assert_allclose(d_vector, jac.T @ w @ (innovation + jac @ x[scan].ravel()), rtol=1e-9, atol=1e-6)
        info.add(np.array(scan), d_matrix, d_vector)
    dense = info.csc().toarray()
    assert np.all(dense[np.ix_(dofs([0]), dofs([3]))] == 0.0)
    assert sorted(map(tuple, info.links().tolist())) == [(0, 1), (0, 2), (1, 2), (2, 3)]
    assert info.nnz_blocks == 4 + 2 * 4 and info.neighbours[2] == {0, 1, 3}
    np.testing.assert_allclose(dense, dense.T, atol=1e-9)
    img = info.sparsity_image()
    assert img.shape == (4, 4) and img[0, 3] == 0 and img[2, 3] == 255
    with pytest.raises(ValueError, match="distinct indices"):
        info.add(np.array([0, 0]), np.zeros((4, 4)), np.zeros(4))


def random_information(n: int, seed: int) -> tuple[InformationMatrix, F64]:
    """A sparse SPD block matrix linking each feature to its grid neighbours, and a vector."""
    rng = np.random.default_rng(seed)
    info = InformationMatrix()
    info.add_features(n)
    side = int(np.ceil(np.sqrt(n)))
    for f in range(n):
        group = [g for g in (f, f + 1, f + side) if g < n and (g != f + 1 or (f + 1) % side)]
        a = rng.normal(size=(2 * len(group) + 1, 2 * len(group)))
        info.add(np.array(group), a.T @ a + 0.5 * np.eye(2 * len(group)), rng.normal(size=2 * len(group)))
    return info, np.array(info.vector)


def test_recovery_matches_a_direct_solve() -> None:
    """PCG, the local solve and the covariance columns all agree with dense linear algebra."""
    info, b = random_information(60, 1)
    dense = info.csc().toarray()
    exact = np.linalg.solve(dense, b)
    inv_blocks = invert_blocks(info.diagonal_blocks())
    res = pcg(info, b, np.zeros_like(b), inv_blocks, 1e-10, 500)
    assert res.converged and 0 < res.iterations < 500
    np.testing.assert_allclose(res.x, exact, atol=1e-8)
    np.testing.assert_allclose(direct(info, b), exact, atol=1e-10)
    rec = Recovery(info, "local", 1e-10, 1e-6, 3, 500, 1000)
    rec.grow(np.zeros((60, 2)))
    rec.set_state(np.zeros(120))  # residual b
    report = rec.solve(list(range(60)), loop_closure=False)
    assert report.method in ("local", "pcg")
    np.testing.assert_allclose(rec.x, exact, atol=1e-6)
    cache = CovarianceCache()
    cache.refresh(info, inv_blocks, [3, 17, 40], 0, 1e-10, 500)
    np.testing.assert_allclose(cache.block([3, 17, 40]), np.linalg.inv(dense)[np.ix_(dofs([3, 17, 40]),
                                                                                    dofs([3, 17, 40]))], atol=1e-9)


def test_stale_covariance_is_conservative() -> None:
    """Adding information (eq. 10) only shrinks I^-1: an older block bounds the new one from above."""
    info, _ = random_information(30, 2)
    cache = CovarianceCache()
    feats = [4, 5, 10]
    cache.refresh(info, invert_blocks(info.diagonal_blocks()), feats, 0, 1e-12, 500)
    old = cache.block(feats)
    rng = np.random.default_rng(3)
    a = rng.normal(size=(3, 6))
    info.add(np.array(feats), a.T @ a, np.zeros(6))
    cache.refresh(info, invert_blocks(info.diagonal_blocks()), feats, 1, 1e-12, 500)
    assert np.linalg.eigvalsh(old - cache.block(feats)).min() >= -1e-10


def test_measurement_pose_known_answer_and_statuses() -> None:
    """Noise-free z_loc gives the pose exactly; one feature is too few; a wrong association is inconsistent."""
    pose = np.array([2.0, -1.0, 0.6])
    z, _, _ = predict(pose, POINTS)
    cov = 1e-4 * np.eye(10)
    est = measurement_pose(z[:, 0], z[:, 1], noise(5, 0.05, 0.01), POINTS, cov)
    assert est.status is PoseStatus.OK and est.chi2 < 1e-12
    np.testing.assert_allclose(est.pose, pose, atol=1e-9)
    assert np.all(np.linalg.eigvalsh(est.cov) > 0)
    assert measurement_pose(z[:1, 0], z[:1, 1], noise(1, 0.05, 0.01), POINTS[:1], cov[:2, :2]).status \
        is PoseStatus.TOO_FEW_FEATURES
    swapped = POINTS[[1, 0, 2, 3, 4]]
    assert measurement_pose(z[:, 0], z[:, 1], noise(5, 0.05, 0.01), swapped, cov).status is PoseStatus.INCONSISTENT


def test_anchor_rule_prefers_a_long_well_known_baseline() -> None:
    """The pair minimising (tr P_a + tr P_b) / d_ab^2 wins; f_1 is the better known of the two."""
    points = np.array([[0.0, 0.0], [0.5, 0.0], [4.0, 0.0]])
    assert choose_anchors(points, np.array([0.02, 0.01, 0.02])) == (1, 2)
    assert choose_anchors(points, np.array([0.02, 0.01, 10.0])) == (1, 0)
    with pytest.raises(ValueError, match="at least two"):
        choose_anchors(points[:1], np.array([1.0]))


def test_filter_bad_input_and_statuses() -> None:
    """NaN and missing ids raise; an empty scan, phase I and a one-landmark scan get their statuses."""
    slam = DSlam(DSlamConfig())
    with pytest.raises(ValueError, match="ranges contains NaN"):
        slam.observe([1.0, np.nan], [0.0, 0.1], [0, 1])
    with pytest.raises(ValueError, match="ids are required"):
        slam.observe([1.0], [0.0])
    with pytest.raises(ValueError, match="ids must all be >= 0"):
        slam.observe([1.0], [0.0], [-1])
    with pytest.raises(ValueError, match="odometry increment"):
        slam.predict([0.1, np.inf, 0.0])
    with pytest.raises(ValueError, match="range_sigma must be finite"):
        slam.observe([1.0], [0.0], [0], range_sigma=-1.0)
    assert slam.observe([], [], []).status is ScanStatus.EMPTY
    z, _, _ = predict(np.zeros(3), POINTS[:3])
    first = slam.observe(z[:, 0], z[:, 1], [0, 1, 2], 0.05, 0.01)
    assert first.status is ScanStatus.PHASE_I and first.new_features == (0, 1, 2)
    np.testing.assert_allclose(slam.estimates(), POINTS[:3], atol=1e-9)
    slam.predict([0.5, 0.0, 0.0])
    z, _, _ = predict(np.array([0.5, 0.0, 0.0]), POINTS)
    one = slam.observe(z[:1, 0], z[:1, 1], [0], 0.05, 0.01)
    assert one.status is ScanStatus.LOCALIZATION_ONLY and one.measurement is None and "localization only" in one.note
    both = slam.observe(z[:, 0], z[:, 1], [0, 1, 2, 3, 4], 0.05, 0.01)
    assert both.status is ScanStatus.MAPPED and both.anchors is not None and len(both.new_features) == 2
    np.testing.assert_allclose(slam.estimates(), POINTS, atol=1e-6)
    np.testing.assert_allclose(both.pose, [0.5, 0.0, 0.0], atol=1e-6)


def _recast_factor(info: InformationMatrix, feats: list[int], seed: int) -> tuple[F64, F64, F64]:
    """A recast-shaped factor on ``feats`` (eq. 8's Jacobian at random points, a full SPD R_map), added to ``info``."""
    rng = np.random.default_rng(seed)
    pts = rng.uniform(-4, 4, size=(len(feats), 2))
    _, jac = map_invariants(pts)
    a = rng.normal(size=(len(jac), len(jac)))
    r_map = 0.01 * (a @ a.T / len(jac) + np.eye(len(jac)))
    d_matrix = jac.T @ np.linalg.solve(r_map, jac)
    info.add(np.array(feats), 0.5 * (d_matrix + d_matrix.T), np.zeros(2 * len(feats)))
    return pts, jac, r_map


def test_vicinity_covariance_form_of_eq10_is_exact() -> None:
    """Kalman form of eq. (10) on V, and eq. (9) joins of new features: equal to blocks of the new I^-1."""
    info, _ = random_information(30, 4)
    v = [3, 4, 5, 9, 10, 11, 16]
    cache = CovarianceCache()
    cache.replace(v, np.linalg.inv(info.csc().toarray())[np.ix_(dofs(v), dofs(v))])
    _, jac, r_map = _recast_factor(info, [4, 10, 5, 16], 5)  # anchors 4 and 10 first
    cache.recast_update([4, 10, 5, 16], [], jac, r_map)
    exact = np.linalg.inv(info.csc().toarray())
    np.testing.assert_allclose(cache.block(v), exact[np.ix_(dofs(v), dofs(v))], atol=1e-10)
    new = info.add_features(2).tolist()  # no information yet: eq. (9) places them from the anchors
    _, jac, r_map = _recast_factor(info, [10, 9, 3] + new, 6)
    cache.recast_update([10, 9, 3], new, jac, r_map)
    exact = np.linalg.inv(info.csc().toarray())
    joint = v + new
    np.testing.assert_allclose(cache.block(joint), exact[np.ix_(dofs(joint), dofs(joint))], atol=1e-10)
    cache.drop([3, 16])
    assert not cache.has([3]) and cache.known([3, 16])
    np.testing.assert_allclose(cache.marginals([3, 4]), [exact[np.ix_(dofs([f]), dofs([f]))] for f in (3, 4)],
                               atol=1e-10)


def test_a_mapped_feature_joining_the_vicinity_gets_an_upper_bound() -> None:
    """A mapped feature outside V joins through eq. (9) without its own history: never below the exact block."""
    info, _ = random_information(30, 7)
    v = [12, 13, 18, 19]
    cache = CovarianceCache()
    cache.replace(v, np.linalg.inv(info.csc().toarray())[np.ix_(dofs(v), dofs(v))])
    _, jac, r_map = _recast_factor(info, [13, 18, 12, 25, 7], 8)  # 25 and 7 are mapped but not in V
    cache.recast_update([13, 18, 12], [25, 7], jac, r_map)
    joint = v + [25, 7]
    exact = np.linalg.inv(info.csc().toarray())[np.ix_(dofs(joint), dofs(joint))]
    bound = cache.block(joint)
    assert np.linalg.eigvalsh(bound - exact).min() >= -1e-10
    assert np.linalg.eigvalsh(bound - exact).max() > 1e-6  # and it is a bound, not the exact block
