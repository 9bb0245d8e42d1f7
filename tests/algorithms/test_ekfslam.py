"""EKF-SLAM baseline: known-answer prediction/update/augmentation, bad input, the seeded world against D-SLAM."""

from __future__ import annotations

import numpy as np
import pytest
from test_dslam_sim import NOISE, SIGMA_B, SIGMA_R, landmark_world, run_dslam, score

from slamreplay.algorithms.common import se2
from slamreplay.algorithms.common.motion import OdometryNoise
from slamreplay.algorithms.ekfslam import EkfSlam, EkfSlamConfig


def run_ekf(seed: int, association: str = "known", n: int = 400):  # type: ignore[no-untyped-def]
    """EKF-SLAM over the same world as run_dslam."""
    landmarks, steps = landmark_world(seed, n)
    ekf = EkfSlam(EkfSlamConfig(odometry_noise=NOISE, association=association))  # type: ignore[arg-type]
    poses = []
    for s in steps:
        ekf.predict(s.increment)
        res = ekf.observe(s.ranges, s.bearings, s.ids, SIGMA_R, SIGMA_B)
        poses.append((res.pose, res.pose_cov))
    ids = ekf.feature_ids if association == "known" else [-1] * ekf.n
    return score(ekf.estimates(), ekf.marginal_covariances(), ids, landmarks, poses, steps), ekf


def test_prediction_known_answer() -> None:
    """1 m straight ahead: Var(x) = Var(y) = s_t^2, Var(theta) = s_h^2; the landmark block is untouched."""
    ekf = EkfSlam(EkfSlamConfig(odometry_noise=OdometryNoise(0.1, 0.2, 0.0)))
    ekf.observe([2.0], [0.5], [7], 0.1, 0.01)
    lm_cov = ekf.P[3:, 3:].copy()
    ekf.predict([1.0, 0.0, 0.0])
    np.testing.assert_allclose(ekf.pose, [1.0, 0.0, 0.0])
    np.testing.assert_allclose(ekf.pose_cov, np.diag([0.01, 0.01, 0.04]), atol=1e-15)
    np.testing.assert_allclose(ekf.P[3:, 3:], lm_cov)
    ekf.predict([1.0, 0.0, 0.0])  # now the heading uncertainty turns into lateral uncertainty
    assert ekf.pose_cov[1, 1] == pytest.approx(0.02 + 0.04, abs=1e-12)


def test_phase_one_augmentation_and_update() -> None:
    """At the exact origin a landmark's covariance is G R G^T; a second reading halves it (linear case)."""
    ekf = EkfSlam(EkfSlamConfig())
    ekf.observe([3.0], [0.0], [1], 0.1, 0.01)
    np.testing.assert_allclose(ekf.marginal_covariances()[0], np.diag([0.01, 0.0009]), atol=1e-15)
    res = ekf.observe([3.0], [0.0], [1], 0.1, 0.01)
    np.testing.assert_allclose(ekf.marginal_covariances()[0], np.diag([0.005, 0.00045]), atol=1e-12)
    assert res.features.tolist() == [0] and res.new_features == () and res.nis == pytest.approx(0.0)
    np.testing.assert_allclose(ekf.pose_cov, 0.0)


def test_bad_input_raises() -> None:
    """NaN ranges, missing ids in known mode, mismatched lengths and negative sigmas raise ValueError."""
    ekf = EkfSlam(EkfSlamConfig())
    with pytest.raises(ValueError, match="ranges contains NaN"):
        ekf.observe([np.nan], [0.0], [0])
    with pytest.raises(ValueError, match="ids are required"):
        ekf.observe([1.0], [0.0])
    with pytest.raises(ValueError, match="same length"):
        ekf.observe([1.0, 2.0], [0.0], [0, 1])
    with pytest.raises(ValueError, match="bearing_sigma must be finite"):
        ekf.observe([1.0], [0.0], [0], bearing_sigma=np.nan)
    with pytest.raises(ValueError, match="association must be"):
        EkfSlamConfig(association="guess")  # type: ignore[arg-type]


def test_ekf_and_dslam_on_the_same_world() -> None:
    """Same world, same noise: both consistent; D-SLAM's map within 1.5x of EKF-SLAM's RMSE, more conservative."""
    ekf, _ = run_ekf(1)
    dslam, _, _ = run_dslam(1)
    assert ekf.mapped == dslam.mapped and ekf.false == 0
    assert ekf.rmse < 0.1 and ekf.landmark_nees <= 3.0
    assert dslam.rmse <= 1.5 * ekf.rmse + 0.01


def test_unknown_ids() -> None:
    """Unknown ids: every landmark once, no false ones."""
    s, ekf = run_ekf(2, association="unknown")
    assert s.false == 0 and s.mapped >= 15 and s.rmse < 0.1
    assert np.all(ekf.tentative.hits < ekf.config.association_params.confirm_hits)  # confirmed ones joined the map


def test_fej_config_rejects_unknown_jacobians() -> None:
    """A misspelt linearisation rule is a ValueError naming the choices."""
    with pytest.raises(ValueError, match="jacobians must be 'standard' or 'first_estimates'"):
        EkfSlamConfig(jacobians="first")  # type: ignore[arg-type]


def test_fej_equals_standard_when_estimates_never_move() -> None:
    """Noise-free odometry and scans: every estimate is its first estimate, so FEJ and the standard EKF agree."""
    landmarks = np.array([[2.0, 1.0], [3.0, -1.0], [4.0, 0.5]])
    filters = [EkfSlam(EkfSlamConfig(jacobians=j)) for j in ("standard", "first_estimates")]  # type: ignore[arg-type]
    pose = np.zeros(3)
    for k in range(30):
        u = np.array([0.05, 0.0, 0.01]) if k >= 3 else np.zeros(3)
        pose = se2.compose(pose, u)
        rel = se2.transform_points(se2.inverse(pose), landmarks)
        r, b = np.hypot(rel[:, 0], rel[:, 1]), np.arctan2(rel[:, 1], rel[:, 0])
        for ekf in filters:
            ekf.predict(u)
            ekf.observe(r, b, [0, 1, 2], 0.05, 0.01)
    np.testing.assert_allclose(filters[0].x, filters[1].x, atol=1e-12)
    np.testing.assert_allclose(filters[0].P, filters[1].P, atol=1e-12)


def test_fej_prediction_jacobian_known_answer() -> None:
    """After an update moved the pose, FEJ's F uses p_{k+1|k} - p_{k|k-1}, the standard one p_{k+1|k} - p_{k|k}."""
    out = {}
    for rule in ("standard", "first_estimates"):
        ekf = EkfSlam(EkfSlamConfig(odometry_noise=OdometryNoise(0.1, 0.1, 0.0), jacobians=rule))  # type: ignore[arg-type]
        ekf.observe([2.0, 2.0], [0.5, -0.5], [1, 2], 0.05, 0.01)
        ekf.predict([1.0, 0.0, 0.0])  # propagated pose (1, 0, 0)
        ekf.observe([1.2, 1.2], [1.0, -0.9], [1, 2], 0.05, 0.01)  # pulls the pose away from (1, 0, 0)
        p_upd, x_upd, cross = ekf.pose_cov, ekf.pose, ekf.P[:3, 3:].copy()
        ekf.predict([1.0, 0.0, 0.0])
        new = se2.compose(x_upd, np.array([1.0, 0.0, 0.0]))
        base = x_upd if rule == "standard" else np.array([1.0, 0.0, 0.0])
        f = np.array([[1.0, 0.0, -(new[1] - base[1])], [0.0, 1.0, new[0] - base[0]], [0.0, 0.0, 1.0]])
        g = se2.rot(x_upd[2])
        q = np.diag([0.01, 0.01, 0.01])
        gq = np.eye(3)
        gq[:2, :2] = g
        np.testing.assert_allclose(ekf.pose, new, atol=1e-12)
        np.testing.assert_allclose(ekf.pose_cov, f @ p_upd @ f.T + gq @ q @ gq.T, atol=1e-12)
        np.testing.assert_allclose(ekf.P[:3, 3:], f @ cross, atol=1e-12)
        out[rule] = ekf.pose_cov
    assert not np.allclose(out["standard"], out["first_estimates"], atol=1e-6)  # the update did move the pose


def test_fej_is_consistent_and_as_accurate() -> None:
    """Seeded worlds: FEJ-EKF's landmark and robot NEES within two-sided bounds, its map as good as the EKF's."""
    for seed in (1, 2, 3):
        landmarks, steps = landmark_world(seed, 400)
        fej = EkfSlam(EkfSlamConfig(odometry_noise=NOISE, jacobians="first_estimates"))
        poses = []
        for s in steps:
            fej.predict(s.increment)
            res = fej.observe(s.ranges, s.bearings, s.ids, SIGMA_R, SIGMA_B)
            poses.append((res.pose, res.pose_cov))
        sf = score(fej.estimates(), fej.marginal_covariances(), fej.feature_ids, landmarks, poses, steps)
        se, _ = run_ekf(seed)
        assert 0.2 <= sf.landmark_nees <= 3.0, (seed, sf)
        assert 0.2 <= sf.robot_nees <= 4.0, (seed, sf)
        assert sf.landmark_nees <= se.landmark_nees + 0.3, (seed, sf, se)
        assert sf.rmse <= 1.2 * se.rmse + 0.005, (seed, sf, se)
