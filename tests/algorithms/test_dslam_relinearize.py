"""D-SLAM's final relinearisation (algorithms/dslam/relinearize.py): known answers and the filter's use of it."""

from __future__ import annotations

import numpy as np
import pytest
from numpy.typing import NDArray

from slamreplay.algorithms.common import se2
from slamreplay.algorithms.common.rangebearing import noise, predict
from slamreplay.algorithms.dslam import DSlam, DSlamConfig
from slamreplay.algorithms.dslam.mapping import phase_one_terms, recast_terms
from slamreplay.algorithms.dslam.recast import recast
from slamreplay.algorithms.dslam.recovery import direct
from slamreplay.algorithms.dslam.relinearize import MeasurementLog, relinearize

F64 = NDArray[np.float64]
TRUTH = np.array([[2.0, 1.0], [2.5, -1.5], [5.0, 0.5], [6.0, -2.0], [8.5, -0.5]])


def _exact_log() -> MeasurementLog:
    """Noise-free measurements: phase I readings of features 0 and 1, two recast scans along the row."""
    log = MeasurementLog()
    z, _, _ = predict(np.zeros(3), TRUTH[:2])
    for f in (0, 1):
        log.phase_one(f, z[f], np.diag([0.05**2, 0.02**2]))
    for scan, pose in (([0, 1, 2, 3], np.array([3.0, 0.0, 0.3])), ([2, 3, 4], np.array([6.0, 0.5, -0.2]))):
        zz, _, _ = predict(pose, TRUTH[scan])
        rc = recast(zz[:, 0], zz[:, 1], noise(len(scan), 0.05, 0.02))
        log.recast(scan, rc.z_map, rc.r_map)
    return log


def test_relinearization_recovers_a_map_linearised_in_a_rotated_frame() -> None:
    """Exact data linearised at a map rotated 3 degrees: the EIF is biased, Gauss-Newton returns the truth."""
    log = _exact_log()
    rotated = se2.transform_points(np.array([0.0, 0.0, np.radians(3.0)]), TRUTH).reshape(-1)
    info = log.information(len(TRUTH), rotated)
    eif = direct(info, np.array(info.vector))
    assert np.max(np.abs(eif - TRUTH.reshape(-1))) > 1e-3
    result = relinearize(log, len(TRUTH), eif, 10, 1e-10)
    np.testing.assert_allclose(result.x, TRUTH.reshape(-1), atol=1e-8)
    assert result.iterations <= 6 and result.step_m <= 1e-10


def test_log_rebuilds_the_filter_terms() -> None:
    """At one linearisation point, the log gives the same I and i as the eq. (10) terms it recorded."""
    log = _exact_log()
    x = TRUTH + 0.01 * np.arange(10).reshape(5, 2)
    info = log.information(5, x.reshape(-1))
    dense = np.zeros((10, 10))
    vec = np.zeros(10)
    z, _, _ = predict(np.zeros(3), TRUTH[:2])
    for f in (0, 1):
        d_matrix, d_vector, _ = phase_one_terms(x[f], z[f], np.diag([0.05**2, 0.02**2]))
        dense[2 * f:2 * f + 2, 2 * f:2 * f + 2] += d_matrix
        vec[2 * f:2 * f + 2] += d_vector
    for scan, pose in (([0, 1, 2, 3], np.array([3.0, 0.0, 0.3])), ([2, 3, 4], np.array([6.0, 0.5, -0.2]))):
        zz, _, _ = predict(pose, TRUTH[scan])
        d_matrix, d_vector, _ = recast_terms(x[scan], recast(zz[:, 0], zz[:, 1], noise(len(scan), 0.05, 0.02)))
        idx = np.array([[2 * f, 2 * f + 1] for f in scan]).reshape(-1)
        dense[np.ix_(idx, idx)] += d_matrix
        vec[idx] += d_vector
    np.testing.assert_allclose(info.csc().toarray(), dense, atol=1e-9)
    np.testing.assert_allclose(info.vector, vec, atol=1e-9)
    with pytest.raises(ValueError, match="x0 must have shape"):
        relinearize(log, 5, np.zeros(3), 5, 1e-6)
    with pytest.raises(ValueError, match="max_iterations"):
        relinearize(log, 5, x.reshape(-1), 0, 1e-6)


def test_finalize_relinearizes_and_can_be_turned_off() -> None:
    """finalize: a fixed point of the logged measurements (relinearised), or the EIF's I^-1 i (0: no summary kept)."""
    rng = np.random.default_rng(3)
    for iterations in (0, 10):
        slam = DSlam(DSlamConfig(final_relinearization_iterations=iterations))
        for k in range(60):
            if k >= 10:
                slam.predict([0.05, 0.0, 0.0])
            pose = np.array([0.05 * max(0, k - 9), 0.0, 0.0])
            z, _, _ = predict(pose, TRUTH)
            slam.observe(z[:, 0] + rng.normal(0, 0.05, 5), z[:, 1] + rng.normal(0, 0.02, 5), np.arange(5), 0.05, 0.02)
        report = slam.finalize()
        assert np.all(np.linalg.eigvalsh(slam.marginal_covariances()) > 0)
        if iterations == 0:
            assert report.method == "direct" and len(slam.map_log) == 0  # the paper's rule keeps no summary
            continue
        x = slam.recovery.x
        info = slam.map_log.information(slam.n, np.array(x))
        assert report.method == "relinearized" and len(slam.map_log) > 0
        assert np.max(np.abs(direct(info, np.array(info.vector)) - x)) < 1e-5


def test_summary_is_exact_and_bounded() -> None:
    """Many noisy scans sharing anchor pairs, angles near +-pi: the summary's I and i equal the sum of every
    scan's eq. (10) terms, and its size stops growing once every anchor pair and feature has been seen."""
    rng = np.random.default_rng(7)
    truth = np.array([[2.0, 0.0], [4.0, 0.0], [1.0, 0.05], [3.0, -2.0], [5.0, 1.5], [3.0, 2.5]])  # f3 near alpha = pi
    x = (truth + rng.normal(0, 0.05, truth.shape)).reshape(-1)
    log = MeasurementLog()
    dense, vec = np.zeros((12, 12)), np.zeros(12)
    sizes = []
    for k in range(400):
        scan = [[0, 1, 2, 3], [0, 1, 4], [0, 1, 5, 3, 2], [3, 4, 5]][k % 4]
        pose = np.array([rng.uniform(2, 3), rng.uniform(-0.5, 0.5), rng.uniform(-0.3, 0.3)])
        zz, _, _ = predict(pose, truth[scan])
        rc = recast(zz[:, 0] + rng.normal(0, 0.05, len(scan)), zz[:, 1] + rng.normal(0, 0.02, len(scan)),
                    noise(len(scan), 0.05, 0.02))
        log.recast(scan, rc.z_map, rc.r_map)
        if k % 4 == 3:
            z0, _, _ = predict(np.zeros(3), truth[:1])
            z0 = z0[0] + rng.normal(0, [0.05, 0.02])
            log.phase_one(0, z0, np.diag([0.05**2, 0.02**2]))
            d_matrix, d_vector, _ = phase_one_terms(x.reshape(-1, 2)[0], z0, np.diag([0.05**2, 0.02**2]))
            dense[:2, :2] += d_matrix
            vec[:2] += d_vector
        d_matrix, d_vector, _ = recast_terms(x.reshape(-1, 2)[scan], rc)
        idx = np.array([[2 * f, 2 * f + 1] for f in scan]).reshape(-1)
        dense[np.ix_(idx, idx)] += d_matrix
        vec[idx] += d_vector
        sizes.append(log.nbytes)
    info = log.information(6, x)
    np.testing.assert_allclose(info.csc().toarray(), dense, rtol=1e-9, atol=1e-6)
    np.testing.assert_allclose(info.vector, vec, rtol=1e-9, atol=1e-6)
    assert len(log) == 500 and log.entries == 3  # phase I of f0, anchor pairs (0, 1) and (3, 4)
    assert sizes[8] == sizes[-1]  # O(map), not O(time)
