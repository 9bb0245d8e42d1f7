"""Batch pose-landmark least squares: known answers on seeded worlds, Jacobians, bad input."""

from __future__ import annotations

import math

import numpy as np
import pytest

from slamreplay.algorithms.common.landmark_graph import (
    LandmarkGraph,
    LsqConfig,
    _system,
    _whiten,
    chi2,
    landmark_covariance,
    optimize,
    pose_landmark_covariance,
    residuals,
    solve_incremental,
)


def _world(seed: int, noise: bool, n: int = 120) -> tuple[LandmarkGraph, np.ndarray, np.ndarray]:
    """A robot on a circle among 12 landmarks; odometry and range-bearing edges, noisy or exact."""
    rng = np.random.default_rng(seed)
    lms = np.column_stack([rng.uniform(-12, 12, 12), rng.uniform(-2, 22, 12)])  # all within 12 m of the circle
    poses = np.zeros((n, 3))
    step = np.array([0.5, 0.0, 2 * math.pi / 60])
    for k in range(1, n):
        c, s = math.cos(poses[k - 1, 2]), math.sin(poses[k - 1, 2])
        poses[k] = poses[k - 1] + [c * step[0], s * step[0], step[2]]
    poses[:, 2] = (poses[:, 2] + np.pi) % (2 * np.pi) - np.pi
    sig_o, sig_r, sig_b = np.array([0.02, 0.01, 0.005]), 0.1, 0.01
    z_o = np.tile(step, (n - 1, 1)) + (rng.normal(0, sig_o, (n - 1, 3)) if noise else 0)
    op, ol, oz = [], [], []
    for k in range(n):
        for m in range(len(lms)):
            c, s = math.cos(poses[k, 2]), math.sin(poses[k, 2])
            dx, dy = lms[m] - poses[k, :2]
            d0, d1 = c * dx + s * dy, -s * dx + c * dy
            if math.hypot(d0, d1) < 14:
                op.append(k)
                ol.append(m)
                oz.append([math.hypot(d0, d1) + (rng.normal(0, sig_r) if noise else 0),
                           math.atan2(d1, d0) + (rng.normal(0, sig_b) if noise else 0)])
    k_obs = len(op)
    g = LandmarkGraph(n, len(lms), np.arange(n - 1), np.arange(1, n), z_o,
                      np.broadcast_to(np.diag(1 / sig_o**2), (n - 1, 3, 3)).copy(), np.array(op), np.array(ol),
                      np.array(oz), np.broadcast_to(np.diag([1 / sig_r**2, 1 / sig_b**2]), (k_obs, 2, 2)).copy())
    return g, poses, lms


def test_exact_measurements_give_the_truth() -> None:
    """With noise-free measurements the incremental solve lands on the true poses and landmarks (χ² ≈ 0)."""
    g, poses, lms = _world(0, noise=False)
    res = solve_incremental(g, LsqConfig(chunk_poses=30))
    assert res.converged and res.chi2 < 1e-12
    np.testing.assert_allclose(res.poses, poses, atol=1e-6)
    np.testing.assert_allclose(res.landmarks, lms, atol=1e-6)


def test_noisy_optimum_is_consistent() -> None:
    """With noise the minimum χ² is near its degrees of freedom (two-sided), below the truth's, and close to it."""
    g, poses, lms = _world(1, noise=True)
    res = solve_incremental(g, LsqConfig(chunk_poses=30))
    dof = 3 * len(g.odo_i) + 2 * len(g.obs_pose) - 3 * (g.n_poses - 1) - 2 * g.n_landmarks
    assert 0.7 * dof < res.chi2 < 1.3 * dof
    assert res.chi2 < chi2(g, poses, lms)
    assert np.sqrt(np.mean(np.sum((res.landmarks - lms) ** 2, 1))) < 0.3
    # a second optimize from the optimum does not move it
    again = optimize(g, res.poses, res.landmarks)
    assert again.chi2 == pytest.approx(res.chi2, rel=1e-9)


def test_jacobian_matches_finite_differences() -> None:
    """The whitened analytic Jacobian equals central differences of the whitened residuals."""
    g, poses, lms = _world(2, noise=True, n=15)
    rng = np.random.default_rng(3)
    poses = poses + rng.normal(0, 0.1, poses.shape)
    lms = lms + rng.normal(0, 0.3, lms.shape)
    wo, wl = _whiten(g.odo_info), _whiten(g.obs_info)
    J, _ = _system(g, poses, lms, wo, wl)

    def whitened(x: np.ndarray) -> np.ndarray:
        eo, el = residuals(g, x[:3 * g.n_poses].reshape(-1, 3), x[3 * g.n_poses:].reshape(-1, 2))
        return np.concatenate([np.einsum("nij,nj->ni", wo, eo).ravel(), np.einsum("nij,nj->ni", wl, el).ravel()])

    x0 = np.concatenate([poses.ravel(), lms.ravel()])
    num = np.zeros(J.shape)
    for c in range(len(x0)):
        d = np.zeros_like(x0)
        d[c] = 1e-6
        num[:, c] = (whitened(x0 + d) - whitened(x0 - d)) / 2e-6
    np.testing.assert_allclose(J.toarray(), num, atol=1e-4 * np.abs(num).max())


def test_bad_graphs_are_rejected() -> None:
    """Wrong shapes, indices out of range and unobserved landmarks raise ValueError naming the problem."""
    g, poses, lms = _world(0, noise=False, n=10)
    with pytest.raises(ValueError, match="odo_z must have shape"):
        LandmarkGraph(g.n_poses, g.n_landmarks, g.odo_i, g.odo_j, g.odo_z[:, :2], g.odo_info, g.obs_pose,
                      g.obs_landmark, g.obs_z, g.obs_info)
    with pytest.raises(ValueError, match="obs_landmark must index"):
        LandmarkGraph(g.n_poses, 1, g.odo_i, g.odo_j, g.odo_z, g.odo_info, g.obs_pose, g.obs_landmark, g.obs_z,
                      g.obs_info)
    with pytest.raises(ValueError, match="every landmark must be observed"):
        optimize(LandmarkGraph(g.n_poses, g.n_landmarks + 1, g.odo_i, g.odo_j, g.odo_z, g.odo_info, g.obs_pose,
                               g.obs_landmark, g.obs_z, g.obs_info), poses, np.vstack([lms, [0.0, 0.0]]))


def test_landmark_covariance_is_the_optimum_s_error_covariance() -> None:
    """Over 40 seeded worlds the batch optimum's landmark error, measured with the joint covariance
    ``landmark_covariance`` gives, is chi2 with 24 dof (12 landmarks): its mean within 3 sigma of 24, both ways."""
    nees: list[float] = []
    for seed in range(100, 200):
        g, _, lms = _world(seed, noise=True)
        if len(nees) == 40:
            break
        if len(np.unique(g.obs_landmark)) < g.n_landmarks:
            continue  # a landmark no pose sees: not this test's world
        res = solve_incremental(g, LsqConfig(chunk_poses=30))
        cov = landmark_covariance(g, res.poses, res.landmarks)
        e = (res.landmarks - lms).reshape(-1)
        nees.append(float(e @ np.linalg.solve(cov, e)))
    assert abs(float(np.mean(nees)) - 24.0) < 3 * math.sqrt(48 / 40)


def test_landmark_covariance_scales_with_the_noise() -> None:
    """Every kind's noise twice its model: the covariance four times; a bad scale is a ValueError naming it."""
    g, poses, lms = _world(0, noise=False, n=30)
    base = landmark_covariance(g, poses, lms)
    np.testing.assert_allclose(landmark_covariance(g, poses, lms, np.full(5, 2.0)), 4 * base, rtol=1e-8)
    assert np.all(np.linalg.eigvalsh(base) > 0) and base.shape == (24, 24)
    with pytest.raises(ValueError, match="scales must be 5 finite factors > 0"):
        landmark_covariance(g, poses, lms, np.array([1.0, 1.0, 0.0, 1.0, 1.0]))


def test_pose_landmark_covariance_is_the_pose_and_landmark_block() -> None:
    """Its landmark block is ``landmark_covariance``; for a chain of odometry whose last pose sees one landmark once,
    its pose block is the odometry composed to first order (a single sighting says nothing about the pose);
    pose 0, which is fixed, is refused."""
    g, poses, lms = _world(0, noise=False, n=30)
    joint = pose_landmark_covariance(g, poses, lms, 29)
    np.testing.assert_allclose(joint[3:, 3:], landmark_covariance(g, poses, lms), rtol=1e-8, atol=1e-12)
    steps = np.array([[1.0, 0.0, 0.3], [0.5, 0.2, -0.1], [0.8, 0.0, 0.2]])
    q = np.diag([0.02, 0.01, 0.005]) ** 2
    chain = np.zeros((4, 3))
    cov = np.zeros((3, 3))
    for k, u in enumerate(steps):
        c, s_ = math.cos(chain[k, 2]), math.sin(chain[k, 2])
        ja = np.array([[1, 0, -s_ * u[0] - c * u[1]], [0, 1, c * u[0] - s_ * u[1]], [0, 0, 1]])
        jb = np.array([[c, -s_, 0], [s_, c, 0], [0, 0, 1]])
        cov = ja @ cov @ ja.T + jb @ q @ jb.T
        chain[k + 1] = [chain[k, 0] + c * u[0] - s_ * u[1], chain[k, 1] + s_ * u[0] + c * u[1], chain[k, 2] + u[2]]
    mark = chain[3, :2] + [3.0, 1.0]
    c, s_ = math.cos(chain[3, 2]), math.sin(chain[3, 2])
    d = np.array([c * 3.0 + s_ * 1.0, -s_ * 3.0 + c * 1.0])  # the landmark in the last pose's frame
    one = LandmarkGraph(4, 1, np.arange(3), np.arange(1, 4), steps, np.broadcast_to(np.linalg.inv(q), (3, 3, 3)).copy(),
                        np.array([3]), np.array([0]), np.array([[math.hypot(*d), math.atan2(d[1], d[0])]]),
                        np.array([np.diag([100.0, 1e4])]))
    np.testing.assert_allclose(pose_landmark_covariance(one, chain, mark[None], 3)[:3, :3], cov, rtol=1e-8, atol=1e-14)
    with pytest.raises(ValueError, match="pose must be 1..3"):
        pose_landmark_covariance(one, chain, mark[None], 0)
