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
