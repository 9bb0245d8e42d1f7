"""slamreplay.replay.evaluation.metrics: the band of a mean landmark NEES."""

from __future__ import annotations

import numpy as np
import pytest


def test_mean_nees_band_known_answers() -> None:
    """Independent landmarks: chi2(2k)/k exactly; one shared error: the band of one chi2(2); sampled: it holds."""
    from scipy.stats import chi2

    from slamreplay.replay.evaluation.metrics import mean_nees_band

    k = 10
    rng = np.random.default_rng(5)
    blocks = [(lambda a: a @ a.T + 0.1 * np.eye(2))(rng.normal(size=(2, 2))) for _ in range(k)]
    independent = np.zeros((2 * k, 2 * k))
    for i, blk in enumerate(blocks):
        independent[2 * i:2 * i + 2, 2 * i:2 * i + 2] = blk
    np.testing.assert_allclose(mean_nees_band(independent), (chi2.ppf(0.025, 2 * k) / k, chi2.ppf(0.975, 2 * k) / k),
                               rtol=1e-9)
    shared = np.kron(np.ones((k, k)), np.diag([0.04, 0.01])) + 1e-12 * np.eye(2 * k)
    np.testing.assert_allclose(mean_nees_band(shared), (chi2.ppf(0.025, 2), chi2.ppf(0.975, 2)), rtol=1e-4)
    # a map-like mix: a common translation plus independent parts; the sampled 2.5 and 97.5 % points
    mixed = np.kron(np.ones((k, k)), 0.02 * np.eye(2)) + independent * 0.01
    low, high = mean_nees_band(mixed)
    e = rng.multivariate_normal(np.zeros(2 * k), mixed, size=20000).reshape(-1, k, 2)
    inv = np.linalg.inv(mixed.reshape(k, 2, k, 2)[np.arange(k), :, np.arange(k), :])
    means = np.einsum("ski,kij,skj->sk", e, inv, e).mean(1)
    q_low, q_high = np.percentile(means, [2.5, 97.5])
    assert abs(q_high - high) < 0.03 * high and -0.02 < low - q_low < 0.15
    assert high > 1.5 * chi2.ppf(0.975, 2 * k) / k  # far wider than the independent band
    with pytest.raises(ValueError, match="joint_cov must be"):
        mean_nees_band(np.eye(3))


def test_mean_nees_band_against_an_estimated_reference() -> None:
    """Scored against an efficient estimate from the same data: sampled, the band holds both ways; a reference of
    half the estimate's covariance halves the band; an estimate more certain than the reference has no band."""
    from slamreplay.replay.evaluation.metrics import mean_nees_band

    k = 8
    rng = np.random.default_rng(11)
    # two sensors see k landmarks: the estimate uses sensor 1 alone, the reference (efficient) both
    r1 = np.kron(np.ones((k, k)), 0.01 * np.eye(2)) + np.diag(rng.uniform(0.01, 0.05, 2 * k))
    r2 = np.diag(rng.uniform(0.01, 0.05, 2 * k))
    p_ref = np.linalg.inv(np.linalg.inv(r1) + np.linalg.inv(r2))
    low, high = mean_nees_band(r1, reference_cov=p_ref)
    truth = np.zeros(2 * k)
    z1 = rng.multivariate_normal(truth, r1, size=20000)
    z2 = rng.multivariate_normal(truth, r2, size=20000)
    ref = (p_ref @ (np.linalg.solve(r1, z1.T) + np.linalg.solve(r2, z2.T))).T
    e = (z1 - ref).reshape(-1, k, 2)
    inv = np.linalg.inv(r1.reshape(k, 2, k, 2)[np.arange(k), :, np.arange(k), :])
    means = np.einsum("ski,kij,skj->sk", e, inv, e).mean(1)
    q_low, q_high = np.percentile(means, [2.5, 97.5])
    assert abs(q_high - high) < 0.03 * high and -0.02 < low - q_low < 0.15
    truth_low, truth_high = mean_nees_band(r1)
    assert high < truth_high and low < truth_low  # lower than against the truth: the reference shares an error
    half = mean_nees_band(r1, reference_cov=0.5 * r1)
    np.testing.assert_allclose(half, np.array(mean_nees_band(r1)) / 2, rtol=1e-9)
    with pytest.raises(ValueError, match="below the reference's in 2 of 16 directions"):
        mean_nees_band(r1, reference_cov=r1 + np.diag([0.0] * 14 + [0.01, 0.01]))
    with pytest.raises(ValueError, match="reference_cov must be"):
        mean_nees_band(r1, reference_cov=np.eye(3))
