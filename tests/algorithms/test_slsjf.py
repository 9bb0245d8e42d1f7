"""SLSJF: local maps joined into a sparse information map (known answers, sparsity, the EKF it wraps, errors)."""

from __future__ import annotations

import numpy as np
import pytest

from slamreplay.algorithms.common import se2
from slamreplay.algorithms.ekfslam import EkfSlam, EkfSlamConfig
from slamreplay.algorithms.slsjf import GlobalMap, Slsjf, SlsjfConfig


def local_map(start: np.ndarray, end: np.ndarray, feats: np.ndarray, sigma: float = 0.1) -> tuple[np.ndarray, ...]:
    """A noise-free local map from ``start`` to ``end`` seeing ``feats`` (world frame), with covariance sigma^2 I."""
    z = np.concatenate([se2.between(start, end), se2.transform_points(se2.inverse(start), feats).reshape(-1)])
    return z, sigma**2 * np.eye(len(z))


POSES = np.array([[0.0, 0.0, 0.0], [5.0, 1.0, 0.4], [9.0, 4.0, 1.2], [8.0, 9.0, 2.5]])
FEATS = np.array([[2.0, 3.0], [6.0, -1.0], [10.0, 6.0], [4.0, 8.0], [12.0, 1.0]])
SEEN = [np.array([0, 1]), np.array([1, 2, 4]), np.array([2, 3])]  # features each local map sees


@pytest.mark.parametrize("linearization", ["once", "iterated"])
def test_noise_free_local_maps_join_into_the_true_map(linearization: str) -> None:
    """Three exact local maps along a curving path: the joined poses and features are the truth."""
    gm = GlobalMap(linearization)  # type: ignore[arg-type]
    start = -1
    for k, seen in enumerate(SEEN):
        z, p = local_map(POSES[k], POSES[k + 1], FEATS[seen])
        start = gm.join(start, z[:3], seen, z, p)
    for k in range(3):
        np.testing.assert_allclose(gm.pose(k), POSES[k + 1], atol=1e-9)
    for g in range(5):
        np.testing.assert_allclose(gm.feature(g), FEATS[g], atol=1e-9)


def test_one_joined_local_map_keeps_its_estimate_and_covariance() -> None:
    """Joining a single local map started at the origin: the global map is that map, and so is its covariance."""
    rng = np.random.default_rng(1)
    z, _ = local_map(POSES[0], POSES[1], FEATS[[0, 1]])
    a = rng.normal(size=(7, 7))
    p = a @ a.T / 7 + 0.01 * np.eye(7)
    gm = GlobalMap("iterated")
    gm.join(-1, z[:3], np.array([0, 1]), z, p)
    np.testing.assert_allclose(gm.x, z, atol=1e-9)
    np.testing.assert_allclose(gm.pose_covariance(0), p[:3, :3], rtol=1e-6)
    np.testing.assert_allclose(gm.joint_feature_covariance([0, 1]), p[3:, 3:], rtol=1e-6)


def test_the_information_matrix_is_exactly_sparse() -> None:
    """A feature seen only in the third local map has no link to the first local map's end pose."""
    gm = GlobalMap("iterated")
    start = -1
    for k, seen in enumerate(SEEN):
        z, p = local_map(POSES[k], POSES[k + 1], FEATS[seen])
        start = gm.join(start, z[:3], seen, z, p)
    info = gm.information().toarray()
    pose0, feat3 = gm.pose_at[0], gm.feat_at[3]
    assert np.all(info[pose0:pose0 + 3, feat3:feat3 + 2] == 0)
    assert np.any(info[gm.pose_at[1]:gm.pose_at[1] + 3, feat3:feat3 + 2] != 0)  # map 3 starts at pose 1


def test_noisy_joining_recovers_the_truth_within_its_covariance() -> None:
    """Local maps with noise of known covariance: the joined estimate's error is consistent (NEES over 200
    trials of the 5 features near 2 per feature, inside the chi2 band)."""
    rng = np.random.default_rng(7)
    nees = []
    for _ in range(200):
        gm = GlobalMap("iterated")
        start = -1
        for k, seen in enumerate(SEEN):
            z, p = local_map(POSES[k], POSES[k + 1], FEATS[seen], sigma=0.05)
            zn = z + rng.multivariate_normal(np.zeros(len(z)), p)
            start = gm.join(start, zn[:3], seen, zn, p)
        e = np.concatenate([gm.feature(g) - FEATS[g] for g in range(5)])
        cov = gm.joint_feature_covariance(list(range(5)))
        nees.append(float(e @ np.linalg.solve(cov, e)))
    mean = float(np.mean(nees))  # chi2(10) / trial: mean 10, sd of the mean sqrt(20 / 200) = 0.32
    assert 10 - 1.0 < mean < 10 + 1.0


def test_one_unending_local_map_is_ekf_slam() -> None:
    """With local maps larger than the run, SLSJF is EkfSlam on the same inputs, to rounding."""
    cfg = EkfSlamConfig()
    ekf, sl = EkfSlam(cfg), Slsjf(SlsjfConfig(cfg, local_map_scans=10**6, local_map_distance_m=1e9))
    rng = np.random.default_rng(3)
    for k in range(40):
        u = np.array([0.2, 0.0, 0.05]) + rng.normal(0, 0.01, 3)
        ekf.predict(u)
        sl.predict(u)
        if k % 4 == 0:
            r, b, ids = rng.uniform(2, 5, 3), rng.uniform(-1, 1, 3), rng.choice(8, 3, replace=False)
            a, c = ekf.observe(r, b, ids), sl.observe(r, b, ids)
            np.testing.assert_allclose(c.pose, a.pose, atol=1e-12)
    np.testing.assert_allclose(sl.estimates()[[sl.by_id[i] for i in ekf.feature_ids]], ekf.estimates(), atol=1e-12)
    sl.join()  # one local map joined into an empty global map: the same numbers
    np.testing.assert_allclose(sl.estimates()[[sl.by_id[i] for i in ekf.feature_ids]], ekf.estimates(), atol=1e-7)


def test_local_maps_end_by_scans_and_by_distance() -> None:
    """A local map is joined after local_map_scans scans, or once the robot drove local_map_distance_m."""
    sl = Slsjf(SlsjfConfig(local_map_scans=2, local_map_distance_m=1.0))
    sl.observe([3.0], [0.1], [5])
    assert len(sl.map.maps) == 0
    res = sl.observe([3.0], [0.1], [5])
    assert res.joined and len(sl.map.maps) == 1
    for _ in range(6):
        sl.predict([0.2, 0.0, 0.0])
    assert len(sl.map.maps) == 2  # 1.2 m driven


def test_bad_settings_are_refused() -> None:
    """Unknown ids, an empty local map size, and a malformed local map each raise ValueError naming them."""
    with pytest.raises(ValueError, match="association must be 'known'"):
        SlsjfConfig(EkfSlamConfig(association="unknown"))
    with pytest.raises(ValueError, match="local_map_scans"):
        SlsjfConfig(local_map_scans=0)
    with pytest.raises(ValueError, match="linearization"):
        GlobalMap("twice")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="3 \\+ 2m"):
        GlobalMap().join(-1, np.zeros(3), np.array([0]), np.zeros(3), np.eye(3))
    with pytest.raises(ValueError, match="ids"):
        Slsjf().observe([3.0], [0.1], None)
