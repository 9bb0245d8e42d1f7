"""Covariance Intersection (algorithms/common/ci.py): closed-form cases, consistency, errors."""

from __future__ import annotations

import numpy as np
import pytest

from slamreplay.algorithms.common.ci import covariance_intersection


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
