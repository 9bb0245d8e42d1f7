"""The Victoria Park reference and the noise measured about it, on a seeded world with known noise."""

from __future__ import annotations

import math

import numpy as np

from slamreplay.recorder.importers.victoria_park import VictoriaPark
from slamreplay.replay.evaluation.landmark_reference import measured_noise, victoria_park_reference


def _world(seed: int) -> tuple[VictoriaPark, np.ndarray, np.ndarray]:
    """A loop among 15 trees, odometry with 0.01 m / 0.002 rad per step, sightings 0.3 m / 0.05 rad."""
    rng = np.random.default_rng(seed)
    n = 400
    truth = np.zeros((n, 3))
    step = np.array([0.5, 0.0, 2 * math.pi / 200])
    for k in range(1, n):
        c, s = math.cos(truth[k - 1, 2]), math.sin(truth[k - 1, 2])
        truth[k] = [truth[k - 1, 0] + c * 0.5, truth[k - 1, 1] + s * 0.5, math.remainder(truth[k - 1, 2] + step[2],
                                                                                         math.tau)]
    angle = rng.uniform(0, 2 * math.pi, 15)
    radius = rng.uniform(10, 22, 15)
    trees = np.column_stack([radius * np.cos(angle), 15.9 + radius * np.sin(angle)])
    odo_z = step + rng.normal(0, [0.01, 0.002, 0.002], (n - 1, 3))
    op, ol, oxy = [], [], []
    for k in range(0, n, 2):
        c, s = math.cos(truth[k, 2]), math.sin(truth[k, 2])
        for m, (tx, ty) in enumerate(trees):
            d0, d1 = c * (tx - truth[k, 0]) + s * (ty - truth[k, 1]), -s * (tx - truth[k, 0]) + c * (ty - truth[k, 1])
            r, b = math.hypot(d0, d1) + rng.normal(0, 0.3), math.atan2(d1, d0) + rng.normal(0, 0.05)
            if r < 20 and abs(b) < 1.3:
                op.append(k)
                ol.append(100 + m)
                oxy.append([r * math.cos(b), r * math.sin(b)])
    cov = np.diag([1e-4, 4e-6, 4e-6])
    data = VictoriaPark(np.arange(n), np.arange(n - 1), np.arange(1, n), odo_z, np.broadcast_to(cov, (n - 1, 3, 3)),
                        np.array(op), np.array(ol), np.array(oxy), np.broadcast_to(np.eye(2) * 0.4, (len(op), 2, 2)))
    return data, truth, trees


def test_reference_and_measured_noise() -> None:
    """The reference lands near the truth, and the noise measured about it is the simulated one (two-sided)."""
    data, truth, trees = _world(0)
    poses, landmarks, res = victoria_park_reference(data)
    assert res.converged
    assert np.sqrt(np.mean(np.sum((landmarks - trees[data.landmark_ids - 100]) ** 2, 1))) < 0.5
    assert np.sqrt(np.mean(np.sum((poses[:, :2] - truth[:, :2]) ** 2, 1))) < 1.0
    noise = measured_noise(data, poses, landmarks)
    # simulated 0.3 m and 0.05 rad; the leverage correction matters: plain RMS residuals scaled by one
    # residuals-to-dof factor gave 0.41 m and 0.073 rad here
    assert 0.27 < noise["range_sigma_m"] < 0.33
    assert 0.045 < noise["bearing_sigma_rad"] < 0.055
    assert 0.5 * 0.01 / math.sqrt(0.5) < noise["translation_sigma_per_sqrt_m"] < 1.5 * 0.01 / math.sqrt(0.5)
    assert noise["heading_sigma_per_sqrt_rad"] == 0.0
