"""Covariance Intersection (algorithms/common/ci.py): closed-form cases, consistency, errors."""

from __future__ import annotations

import numpy as np
import pytest

from slamreplay.algorithms.common.ci import covariance_intersection, covariance_intersection_update


def test_symmetric_closed_form_det_and_trace() -> None:
    """Mirror-image covariances: omega = 1/2 and C = (A^-1/2 + B^-1/2)^-1 for both criteria."""
    a, cov_a = np.zeros(2), np.diag([1.0, 0.25])
    b, cov_b = np.ones(2), np.diag([0.25, 1.0])
    for criterion in ("det", "trace"):
        out = covariance_intersection(a, cov_a, b, cov_b, criterion=criterion)
        assert out.omega == pytest.approx(0.5, abs=1e-8)
        np.testing.assert_allclose(out.cov, np.diag([0.4, 0.4]), atol=1e-8)
        np.testing.assert_allclose(out.mean, [0.8, 0.2], atol=1e-8)


def test_dominated_estimate_is_ignored() -> None:
    """When A < B in every direction, CI keeps a alone (omega = 1), under both criteria."""
    cov_b = np.array([[2.0, 0.3], [0.3, 1.0]])
    for criterion in ("det", "trace"):
        out = covariance_intersection([1.0, 2.0], 0.5 * cov_b, [5.0, 5.0], cov_b, criterion=criterion)
        assert out.omega == 1.0
        np.testing.assert_allclose(out.mean, [1.0, 2.0], atol=1e-12)
        np.testing.assert_allclose(out.cov, 0.5 * cov_b, atol=1e-12)


def test_omega_minimises_the_criterion() -> None:
    """The chosen omega beats a fine grid of alternatives for det and for trace."""
    rng = np.random.default_rng(4)
    for _ in range(5):
        ma, mb = rng.normal(size=(3, 3)), rng.normal(size=(3, 3))
        cov_a, cov_b = ma @ ma.T + 0.1 * np.eye(3), mb @ mb.T + 0.1 * np.eye(3)
        ia, ib = np.linalg.inv(cov_a), np.linalg.inv(cov_b)
        for criterion, f in (("det", np.linalg.det), ("trace", np.trace)):
            out = covariance_intersection(np.zeros(3), cov_a, np.zeros(3), cov_b, criterion=criterion)
            grid = [f(np.linalg.inv(w * ia + (1 - w) * ib)) for w in np.linspace(0, 1, 2001)]
            assert f(out.cov) <= min(grid) + 1e-9


def test_consistent_for_any_cross_correlation() -> None:
    """C bounds the true covariance of the fused estimate whatever the correlation of the inputs."""
    rng = np.random.default_rng(7)
    cov_a, cov_b = np.diag([0.2, 1.0, 0.05]), np.diag([1.0, 0.1, 0.02])
    out = covariance_intersection(np.zeros(3), cov_a, np.zeros(3), cov_b)
    k_a = out.cov @ (out.omega * np.linalg.inv(cov_a))
    k_b = out.cov @ ((1 - out.omega) * np.linalg.inv(cov_b))
    la, lb = np.linalg.cholesky(cov_a), np.linalg.cholesky(cov_b)
    for _ in range(50):
        q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
        cross = la @ (rng.uniform(-1, 1) * q) @ lb.T  # any admissible cross-covariance
        true = k_a @ cov_a @ k_a.T + k_b @ cov_b @ k_b.T + k_a @ cross @ k_b.T + k_b @ cross.T @ k_a.T
        assert np.linalg.eigvalsh(out.cov - true).min() >= -1e-12


def test_angles_are_fused_on_one_branch() -> None:
    """Headings 3.1 and -3.1 rad fuse near +-pi, not near 0."""
    cov = np.diag([0.1, 0.1, 0.01])
    out = covariance_intersection([0.0, 0.0, 3.1], cov, [0.0, 0.0, -3.1], cov, angular=(2,))
    assert abs(abs(out.mean[2]) - np.pi) < 0.05


def test_bad_input_raises() -> None:
    """Shapes, non-finite means, indefinite covariances and unknown criteria raise ValueError."""
    eye = np.eye(2)
    with pytest.raises(ValueError, match="mean_a and mean_b"):
        covariance_intersection([0.0, 0.0], eye, [0.0], eye)
    with pytest.raises(ValueError, match="mean_a and mean_b"):
        covariance_intersection([np.nan, 0.0], eye, [0.0, 0.0], eye)
    with pytest.raises(ValueError, match="cov_b must be positive definite"):
        covariance_intersection([0.0, 0.0], eye, [0.0, 0.0], np.diag([1.0, -1.0]))
    with pytest.raises(ValueError, match="cov_a must be symmetric"):
        covariance_intersection([0.0, 0.0], np.array([[1.0, 0.5], [0.0, 1.0]]), [0.0, 0.0], eye)
    with pytest.raises(ValueError, match=r"cov_a must be a finite \(2, 2\)"):
        covariance_intersection([0.0, 0.0], np.eye(3), [0.0, 0.0], eye)
    with pytest.raises(ValueError, match="criterion must be"):
        covariance_intersection([0.0, 0.0], eye, [0.0, 0.0], eye, criterion="max")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="angular indices"):
        covariance_intersection([0.0, 0.0], eye, [0.0, 0.0], eye, angular=(2,))


def test_update_with_a_full_observation_is_ci_of_two_estimates() -> None:
    """H = I, S = B: the update is covariance_intersection of (a, A) and (b, B), to rounding."""
    a, big_a = np.array([1.0, 2.0, 0.1]), np.diag([0.5, 0.3, 0.02])
    b, big_b = np.array([1.2, 1.9, 0.12]), np.diag([0.2, 0.6, 0.05])
    two = covariance_intersection(a, big_a, b, big_b)
    upd = covariance_intersection_update(a, big_a, b - a, np.eye(3), big_b)
    assert upd.omega == pytest.approx(two.omega, abs=1e-9)
    np.testing.assert_allclose(upd.mean, two.mean, atol=1e-12)
    np.testing.assert_allclose(upd.cov, two.cov, atol=1e-12)


def test_update_with_a_partial_observation() -> None:
    """Observing x alone: omega is the brute-force maximiser of det(C^-1) (5/6 here, by hand: det C^-1 is
    w^2 (w/0.5 + 10 (1 - w)) / 0.006, stationary at w = 5/6), the unobserved y and heading only lose weight, and
    the fused x lies between the estimate and the observation
    (its variance, 0.3, below the estimate's 0.5 but above the observation's 0.1: CI's price for not knowing the
    correlation)."""
    a, big_a = np.array([1.0, 2.0, 0.1]), np.diag([0.5, 0.3, 0.02])
    h, s = np.array([[1.0, 0.0, 0.0]]), np.array([[0.1]])
    upd = covariance_intersection_update(a, big_a, np.array([0.3]), h, s)
    ws = np.linspace(1e-3, 1 - 1e-3, 9999)
    dets = [np.linalg.det(w * np.linalg.inv(big_a) + (1 - w) * h.T @ np.linalg.inv(s) @ h) for w in ws]
    assert upd.omega == pytest.approx(5 / 6, abs=1e-9) and abs(ws[int(np.argmax(dets))] - 5 / 6) < 2e-4
    np.testing.assert_allclose(upd.mean[1:], a[1:])
    assert 1.0 < upd.mean[0] < 1.3
    np.testing.assert_allclose(np.diag(upd.cov)[1:], np.diag(big_a)[1:] / upd.omega)  # y, heading: inflated by 1/w
    assert upd.cov[0, 0] == pytest.approx(1 / (upd.omega / 0.5 + (1 - upd.omega) / 0.1))  # 0.3: below the prior's


def test_update_is_consistent_for_any_cross_correlation() -> None:
    """Whatever the (valid) cross-covariance X between the estimate's error and the observation's, the true error
    covariance of the fused estimate is below C (C - true is PSD); and C is no larger than the prior in det."""
    rng = np.random.default_rng(7)
    for _ in range(200):
        root = rng.normal(size=(5, 5))
        joint = root @ root.T + 0.05 * np.eye(5)  # [[P, X], [X^T, S]]: estimate (3) and observation (2) errors
        p, x_cov, s = joint[:3, :3], joint[:3, 3:], joint[3:, 3:]
        h = rng.normal(size=(2, 3))
        upd = covariance_intersection_update(np.zeros(3), p, np.zeros(2), h, s)
        k = (1 - upd.omega) * upd.cov @ h.T @ np.linalg.inv(s)
        a = np.eye(3) - k @ h  # error of the fused estimate: A e_x + K (e_z) with e_z the observation's error
        true = a @ p @ a.T + k @ s @ k.T + a @ x_cov @ k.T + k @ x_cov.T @ a.T
        assert np.linalg.eigvalsh(upd.cov - true).min() > -1e-9
        assert np.linalg.det(upd.cov) <= np.linalg.det(p) * (1 + 1e-9)


def test_update_bad_input_raises() -> None:
    with pytest.raises(ValueError, match="h must be"):
        covariance_intersection_update(np.zeros(3), np.eye(3), np.zeros(2), np.eye(3), np.eye(2))
    with pytest.raises(ValueError, match="s must be positive definite"):
        covariance_intersection_update(np.zeros(3), np.eye(3), np.zeros(2), np.ones((2, 3)), np.zeros((2, 2)))
