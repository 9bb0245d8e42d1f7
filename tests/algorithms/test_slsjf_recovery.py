"""SLSJF's state and covariance recovery by preconditioned CG (``recovery="pcg"``): the direct factor's answers."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp

from slamreplay.algorithms.dslam.recovery import coarse_space, pcg
from slamreplay.algorithms.ekfslam import EkfSlamConfig
from slamreplay.algorithms.slsjf import GlobalMap, Slsjf, SlsjfConfig
from slamreplay.algorithms.slsjf.recovery import Matrix, TwoLevel, block_jacobi
from tests.algorithms.test_dslam_sim import NOISE, SIGMA_B, SIGMA_R, landmark_world
from tests.algorithms.test_slsjf import three_local_maps


def _spd(n: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    a = rng.normal(size=(n, n))
    return a @ a.T + n * np.eye(n)


def test_block_jacobi_inverts_the_pose_and_feature_blocks() -> None:
    """3x3 blocks at the pose offsets and 2x2 at the feature offsets, each the inverse of A's block; nothing else."""
    a = _spd(7, 0)
    d = block_jacobi(sp.csr_matrix(a), np.array([0]), np.array([3, 5])).toarray()
    np.testing.assert_allclose(d[:3, :3], np.linalg.inv(a[:3, :3]), rtol=1e-12)
    np.testing.assert_allclose(d[3:5, 3:5], np.linalg.inv(a[3:5, 3:5]), rtol=1e-12)
    np.testing.assert_allclose(d[5:, 5:], np.linalg.inv(a[5:, 5:]), rtol=1e-12)
    assert np.all(d[:3, 3:] == 0) and np.all(d[3:5, 5:] == 0)


def test_the_coarse_space_moves_each_cell_rigidly() -> None:
    """Two cells: a pose and a feature in one (a rotation column, which turns the pose's heading too), a lone feature
    in the other (translations only). A coarse rotation by w about the first cell's centroid moves its points by
    w x (p - c) and turns the heading by w."""
    x = np.array([1.0, 1.0, 0.3, 3.0, 1.0, 25.0, 25.0])  # pose (1, 1, 0.3), features (3, 1) and (25, 25)
    p = coarse_space(x, 10.0, np.array([0]), np.array([3, 5])).toarray()
    assert p.shape == (7, 5)  # 2 translations per cell, 1 rotation for the first
    np.testing.assert_allclose(p[:, 0], [1, 0, 0, 1, 0, 0, 0])  # first cell, x translation
    w = 0.01
    move = p[:, 4] * 10.0 * w  # the rotation column is scaled by 1 / cell_m
    np.testing.assert_allclose(move[:3], [0.0, -1.0 * w, w], atol=1e-15)  # centroid (2, 1): pose at (-1, 0)
    np.testing.assert_allclose(move[3:5], [0.0, 1.0 * w], atol=1e-15)
    assert np.all(move[5:] == 0)


def test_pcg_with_the_two_level_preconditioner_solves_a_joined_map() -> None:
    """The information matrix of three joined local maps: PCG from zero reaches the direct solution."""
    gm = three_local_maps("once")
    a = gm.information()
    b = np.arange(gm.dim, dtype=float)
    m = TwoLevel(a, gm.x, np.array(list(gm.pose_at.values())), np.array(list(gm.feat_at.values())))
    res = pcg(Matrix(a), b, np.zeros(gm.dim), None, 1e-12, 200, m)
    assert res.converged
    np.testing.assert_allclose(res.x, np.linalg.solve(a.toarray(), b), rtol=1e-9, atol=1e-9)


def _run(seed: int, association: str, linearization: str, recovery: str, **map_args: int) -> tuple[Slsjf, np.ndarray]:
    _, steps = landmark_world(seed, 400)
    sl = Slsjf(SlsjfConfig(EkfSlamConfig(odometry_noise=NOISE, association=association),  # type: ignore[arg-type]
                           local_map_scans=20, linearization=linearization,  # type: ignore[arg-type]
                           state_recovery=recovery))  # type: ignore[arg-type]
    for k, v in map_args.items():
        setattr(sl.map, k, v)
    poses = []
    for s in steps:
        sl.predict(s.increment)
        poses.append(sl.observe(s.ranges, s.bearings, s.ids if association == "known" else None, SIGMA_R,
                                SIGMA_B).pose)
    sl.join()
    return sl, np.array(poses)


@pytest.mark.parametrize(("association", "linearization"), [("known", "once"), ("unknown", "iterated")])
def test_pcg_recovery_gives_the_direct_factors_map(association: str, linearization: str) -> None:
    """A 400-step world (20 local maps, the joined robot: covariance columns at every scan): the map, every robot
    pose and the covariances with PCG are the direct factor's to the solves' tolerances (measured on seeds 1-3, both
    linearizations, with ids and without: maps within 4.2e-6 m, robots within 4.9e-6 m, covariances within 1.1e-5
    relative), with no fallback, and no factor is held."""
    direct, p_direct = _run(2, association, linearization, "direct")
    cg, p_cg = _run(2, association, linearization, "pcg")
    assert cg.n == direct.n and cg.map.fallbacks == 0 and cg.map._factor is None
    np.testing.assert_allclose(cg.estimates(), direct.estimates(), atol=2e-5)
    np.testing.assert_allclose(p_cg, p_direct, atol=2e-5)
    feats = list(range(cg.n))
    np.testing.assert_allclose(cg.map.feature_covariances(feats), direct.map.feature_covariances(feats), rtol=1e-4)
    np.testing.assert_allclose(cg.marginal_covariances(), direct.marginal_covariances(), rtol=1e-4)
    assert 0 < np.mean(cg.map.pcg_iterations) < 60 and len(cg.map.column_iterations) >= 20


def test_a_pcg_that_does_not_converge_falls_back_to_the_factor() -> None:
    """Two CG iterations at most: every solve is redone directly and counted, and the map is still the direct one."""
    direct, _ = _run(1, "known", "once", "direct")
    capped, _ = _run(1, "known", "once", "pcg", pcg_max_iterations=2)
    assert capped.map.fallbacks >= len(capped.map.maps)
    np.testing.assert_allclose(capped.estimates(), direct.estimates(), atol=1e-9)


def test_bad_recovery_settings_are_refused() -> None:
    with pytest.raises(ValueError, match="recovery must be one of direct, pcg"):
        GlobalMap(recovery="cholesky")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="state_recovery must be one of direct, pcg"):
        SlsjfConfig(state_recovery="invert")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="pcg_max_iterations"):
        GlobalMap(pcg_max_iterations=0)
    with pytest.raises(ValueError, match="no local map has been joined"):
        GlobalMap(recovery="pcg").covariance_columns([0])
