"""iFMI registration covariance: calibrated NEES on known warps, the paper switch, the sandwich, bad config."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from slamreplay.algorithms.ifmi import IfmiConfig, Status, register
from slamreplay.algorithms.ifmi import covariance as ifmi_cov
from slamreplay.recorder.sim.seabed import procedural_texture
from tests.algorithms.test_ifmi import N, perturbed

CHI2_2_95, CHI2_1_95 = 5.991, 3.841


@pytest.fixture(scope="module")
def texture() -> np.ndarray:
    """A deterministic 1024x1024 procedural seabed texture."""
    return procedural_texture(1024, 1024, np.random.default_rng(7))


def test_calibrated_nees_is_within_two_sided_bounds(texture: np.ndarray) -> None:
    """60 known warps with noise sigma 2 and 5: mean NEES within 0.5x-2x the dof, most inside the 95 % band.

    Too low is a failure as well as too high: the paper's eq. (10) gives translation NEES ~0.02.
    """
    rng = np.random.default_rng(21)
    t_nees, r_nees = [], []
    for k in range(60):
        ref, mov, (dx, dy), angle = perturbed(texture, rng, (2.0, 5.0)[k % 2], 0.0)
        r = register(ref, mov)
        assert r.status is Status.OK
        e = np.array([r.shift_px[0] - dx, r.shift_px[1] - dy])
        t_nees.append(float(e @ np.linalg.solve(r.covariance[:2, :2], e)))
        r_nees.append(((r.angle_deg - angle + 180.0) % 360.0 - 180.0) ** 2 / float(r.covariance[2, 2]))
    t, rot = np.array(t_nees), np.array(r_nees)
    assert 1.0 <= t.mean() <= 4.0 and np.mean(t <= CHI2_2_95) >= 0.85
    assert 0.5 <= rot.mean() <= 2.0 and np.mean(rot <= CHI2_1_95) >= 0.85


def test_paper_switch_gives_the_previous_covariance(texture: np.ndarray) -> None:
    """``covariance="paper"`` is eq. (10) as before (values of the code before the switch), and the calibrated
    translation block is it divided by PNR sqrt(H W) plus the overlap lever."""
    ref = texture[300:300 + N, 200:200 + N].astype(np.float32)
    a = cv2.getRotationMatrix2D(((N - 1) / 2, (N - 1) / 2), 10.0, 1.05)
    a[:, 2] += (3.0, 2.0)
    mov = cv2.warpAffine(ref, a, (N, N))
    p = register(ref, mov, IfmiConfig(covariance="paper"))
    np.testing.assert_allclose(p.covariance, [[0.08340470782052702, 3.7863093105270746e-05, 0.0],
                                              [3.7863093105270746e-05, 0.0834581952083801, 0.0],
                                              [0.0, 0.0, 0.11274355281089062]], rtol=1e-6)  # numpy/FFT builds
    assert p.scale_var == pytest.approx(6.961853452681873e-05, rel=1e-6)
    c = register(ref, mov, IfmiConfig(covariance="calibrated"))
    assert c.shift_px == p.shift_px and c.angle_deg == p.angle_deg and c.pnr == p.pnr
    (cyy, cyx), (_, cxx) = ifmi_cov.translation(((p.covariance[1, 1], p.covariance[0, 1]),
                                                 (p.covariance[0, 1], p.covariance[0, 0])), p.pnr, (N, N))
    base = np.array([[cxx, cyx, 0.0], [cyx, cyy, 0.0], [0.0, 0.0, c.covariance[2, 2]]])
    np.testing.assert_allclose(c.covariance, ifmi_cov.with_overlap_lever(base, c.scale_var, c.scale, c.shift_px),
                               rtol=1e-12)
    assert c.covariance[0, 0] < 0.1 * p.covariance[0, 0] and c.covariance[2, 2] < 0.1 * p.covariance[2, 2]


def test_sandwich_of_a_clean_and_of_a_random_cross_spectrum() -> None:
    """A pure phase ramp locates its shift exactly (zero covariance); random phases have no peak (infinite)."""
    shape = (64, 48)
    fy, fx = np.fft.fftfreq(64)[:, None], np.fft.rfftfreq(48)[None, :]
    ramp = np.exp(-2j * np.pi * (fy * 3.25 + fx * -5.5)).astype(np.complex64)
    (crr, crc), (_, ccc) = ifmi_cov.peak_sandwich(ramp, shape, 3.25, -5.5)
    assert abs(crr) < 1e-9 and abs(ccc) < 1e-9 and abs(crc) < 1e-9
    rng = np.random.default_rng(0)
    phases = np.exp(1j * rng.uniform(-np.pi, np.pi, ramp.shape)).astype(np.complex64)
    noisy = ifmi_cov.peak_sandwich(phases * ramp, shape, 3.25, -5.5)
    assert noisy[0][0] == math.inf or noisy[0][0] > 1.0


def test_sandwich_matches_monte_carlo_phase_noise() -> None:
    """Independent phase noise of sigma 0.5 rad: the sandwich's variance of the shift is its spread over draws."""
    shape = (64, 64)
    fx = np.fft.rfftfreq(64)[None, :]
    rng = np.random.default_rng(1)
    est, predicted = [], []
    for _ in range(200):
        eps = rng.normal(0.0, 0.5, (64, 33))
        cross = np.exp(1j * eps).astype(np.complex64)  # true shift (0, 0)
        # The maximum of the POMF, to first order: the Gauss-Newton step from the truth (0, 0).
        w = np.where((np.arange(33) == 0) | (np.arange(33) == 32), 1.0, 2.0)[None, :]
        a = (w * fx**2 * np.cos(eps)).sum()
        est.append(float((w * fx * np.sin(eps)).sum() / (2 * np.pi * a)))
        predicted.append(ifmi_cov.peak_sandwich(cross, shape, 0.0, 0.0)[1][1])
    assert np.var(est) == pytest.approx(np.mean(predicted), rel=0.25)


@pytest.mark.parametrize("value", ["Paper", "", "eq10"])
def test_bad_covariance_value_names_the_key(value: str) -> None:
    """An unknown ``covariance`` raises ValueError naming the key, in the registration and the pipeline config."""
    from slamreplay.replay.pipelines.ifmi import IfmiPipelineConfig

    with pytest.raises(ValueError, match=r"covariance must be one of paper, calibrated"):
        IfmiConfig(covariance=value)
    with pytest.raises(ValueError, match=r"covariance must be one of paper, calibrated"):
        IfmiPipelineConfig(covariance=value)


def test_paper_preset_selects_the_paper_covariance() -> None:
    """``--preset paper`` sets ``covariance`` to the paper's, and every preset key has a note."""
    from slamreplay.replay.pipelines.ifmi import IfmiPipeline, IfmiPipelineConfig

    paper = IfmiPipeline.presets["paper"]
    assert paper == {"covariance": "paper"} and set(paper) == set(IfmiPipeline.preset_notes)
    assert IfmiPipelineConfig(**paper).covariance == "paper"
