"""iFMI registration: the OpenCV convention, known answers, the 180-degree case, PNR, bad input."""

from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np
import pytest
import scipy.fft

from slamreplay.algorithms.ifmi import (
    IfmiConfig,
    SequentialRegistrar,
    Status,
    affine,
    prepare,
    register,
    register_prepared,
    spectral,
)
from slamreplay.algorithms.ifmi.mapping import flatten_illumination
from slamreplay.algorithms.observe import Image, Scalar
from slamreplay.recorder.sim.seabed import procedural_texture
from slamreplay.replay.engine.observer import MemoryObserver

N = 256


@pytest.fixture(scope="module")
def texture() -> np.ndarray:
    """A deterministic 1024x1024 procedural seabed texture."""
    return procedural_texture(1024, 1024, np.random.default_rng(7))


def warp(ref: np.ndarray, angle: float, scale: float, dx: float, dy: float) -> np.ndarray:
    """The issue's convention, verbatim with OpenCV."""
    h, w = ref.shape
    a = cv2.getRotationMatrix2D(((w - 1) / 2, (h - 1) / 2), angle, scale)
    a[:, 2] += (dx, dy)
    return cv2.warpAffine(ref, a, (w, h))


def errors(texture: np.ndarray, angle: float, scale: float, dx: float, dy: float,
           at: tuple[int, int] = (300, 200)) -> tuple[float, float, float, Status, float]:
    """Register a warped crop; (angle error deg, scale error %, shift error px, status, pnr)."""
    ref = texture[at[0]:at[0] + N, at[1]:at[1] + N]
    r = register(ref, warp(ref, angle, scale, dx, dy))
    da = abs((r.angle_deg - angle + 180.0) % 360.0 - 180.0)
    return da, 100 * abs(r.scale / scale - 1), math.hypot(r.shift_px[0] - dx, r.shift_px[1] - dy), r.status, r.pnr


def test_matrix_is_the_opencv_convention() -> None:
    """Registration.matrix / affine equal getRotationMatrix2D about the centre plus the shift."""
    a = cv2.getRotationMatrix2D(((320 - 1) / 2, (240 - 1) / 2), 33.0, 1.1)
    a[:, 2] += (4.0, -7.0)
    np.testing.assert_allclose(affine((240, 320), 33.0, 1.1, (4.0, -7.0)), a)


@pytest.mark.parametrize(("dx", "dy"), [(10.0, 0.0), (0.0, -7.25), (-40.3, 25.6), (51.0, 51.0)])
def test_known_shifts(texture: np.ndarray, dx: float, dy: float) -> None:
    """Pure shifts up to 20% of the size are recovered to 0.2 px (one pair; the batch median is 0.1)."""
    da, ds, dt, status, _ = errors(texture, 0.0, 1.0, dx, dy)
    assert status is Status.OK and dt < 0.2 and da < 0.05 and ds < 0.1


@pytest.mark.parametrize("angle", [-179.0, -90.0, -12.5, 3.3, 45.0, 135.0, 170.2])
def test_known_rotations(texture: np.ndarray, angle: float) -> None:
    """Rotations anywhere in [-180, 180) are recovered to 0.05 deg."""
    da, _, dt, status, _ = errors(texture, angle, 1.0, 5.0, -3.0)
    assert status is Status.OK and da < 0.05 and dt < 0.2


@pytest.mark.parametrize("scale", [0.8, 0.9, 1.12, 1.25])
def test_known_scales(texture: np.ndarray, scale: float) -> None:
    """Scales in [0.8, 1.25] are recovered to 0.1 %."""
    _, ds, dt, status, _ = errors(texture, 20.0, scale, -8.0, 4.0)
    assert status is Status.OK and ds < 0.1 and dt < 0.2


@pytest.mark.parametrize("angle", [180.0, -180.0, 179.7, -0.3, 90.3])
def test_180_degree_ambiguity(texture: np.ndarray, angle: float) -> None:
    """A half turn is told from no turn (the translation stage decides), and 180 wraps to -180.

    Near a multiple of 90 degrees the pixel grid's imprint pulled the estimate onto it (up to
    0.22 deg); the estimate redone with the reference turned away from the grid is within 0.08.
    """
    da, _, dt, status, _ = errors(texture, angle, 1.0, 12.0, 6.0)
    assert status is Status.OK and da < 0.08 and dt < 0.3


def test_no_pull_toward_the_grid(texture: np.ndarray) -> None:
    """Small rotations about 0, 90 and 180 degrees: no systematic pull toward the multiple of 90."""
    pulls = []
    for angle in (-0.3, 0.2, 90.3, 179.7):
        for at in [(300, 200), (100, 600), (600, 100)]:
            ref = texture[at[0]:at[0] + N, at[1]:at[1] + N]
            err = (register(ref, warp(ref, angle, 1.0, 12.0, 6.0)).angle_deg - angle + 180.0) % 360.0 - 180.0
            near = (angle + 45.0) % 90.0 - 45.0  # signed distance to the grid angle
            pulls.append(-math.copysign(1.0, near) * err)
            assert abs(err) < 0.1
    assert float(np.mean(pulls)) < 0.05  # it was 0.13


def test_known_answer_batch(texture: np.ndarray) -> None:
    """30 random similarity warps: all accepted and right; medians within the issue's targets."""
    rng = np.random.default_rng(1)
    rows = []
    for _ in range(30):
        angle = rng.uniform(-180, 180)
        scale = math.exp(rng.uniform(math.log(0.8), math.log(1.25)))
        dx, dy = rng.uniform(-0.2, 0.2, 2) * N
        at = (int(rng.integers(0, 1024 - N)), int(rng.integers(0, 1024 - N)))
        rows.append(errors(texture, angle, scale, dx, dy, at))
    e = np.array([r[:3] for r in rows])
    assert all(r[3] is Status.OK for r in rows) and e[:, 0].max() < 0.5 and e[:, 2].max() < 1.0
    assert np.median(e[:, 0]) <= 0.03 and np.median(e[:, 1]) <= 0.05 and np.median(e[:, 2]) <= 0.1


def test_skerki_known_answers(shared_data: Path) -> None:
    """Real underwater frames warped by random similarities: all accepted, medians within target."""
    frames = sorted((shared_data / "skerki-underwater-group29").glob("*.png"))
    rng = np.random.default_rng(2)
    e = []
    for k in range(20):
        img = cv2.imread(str(frames[k % len(frames)]), cv2.IMREAD_GRAYSCALE)
        y, x = int(rng.integers(0, img.shape[0] - N)), int(rng.integers(0, img.shape[1] - N))
        ref = img[y:y + N, x:x + N]
        angle, scale = rng.uniform(-180, 180), math.exp(rng.uniform(math.log(0.8), math.log(1.25)))
        dx, dy = rng.uniform(-0.2, 0.2, 2) * N
        r = register(ref, warp(ref, angle, scale, dx, dy))
        assert r.status is Status.OK
        e.append((abs((r.angle_deg - angle + 180) % 360 - 180), 100 * abs(r.scale / scale - 1),
                  math.hypot(r.shift_px[0] - dx, r.shift_px[1] - dy)))
    med = np.median(np.array(e), axis=0)
    assert med[0] <= 0.03 and med[1] <= 0.05 and med[2] <= 0.1


def test_non_overlapping_pairs_are_rejected(texture: np.ndarray) -> None:
    """Crops of different places fall below the paper's PNR threshold of 0.2 (eq. 13)."""
    rng = np.random.default_rng(3)
    rejected = 0
    for _ in range(10):
        a = texture[:N, :N]
        y, x = rng.integers(N + 10, 1024 - N, 2)
        rejected += register(a, texture[y:y + N, x:x + N]).status is Status.AMBIGUOUS
    assert rejected >= 10


def test_flat_image_is_a_status(texture: np.ndarray) -> None:
    """A constant image cannot be registered: status FLAT, PNR 0, no exception."""
    r = register(np.full((64, 64), 7.0), texture[:64, :64])
    assert r.status is Status.FLAT and r.pnr == 0.0


def test_covariance_and_observer(texture: np.ndarray) -> None:
    """The eq. (10) covariance is symmetric positive definite; surfaces and PNR reach the observer."""
    ref = texture[:N, :N]
    obs = MemoryObserver()
    r = register(ref, warp(ref, 10.0, 1.05, 3.0, 2.0), observer=obs)
    assert np.all(np.linalg.eigvalsh(r.covariance) > 0) and r.scale_var > 0
    assert isinstance(obs.of("ifmi/pomf/translation")[0], Image) and isinstance(obs.of("ifmi/pnr")[0], Scalar)


def test_sequential_mode_equals_pairwise(texture: np.ndarray) -> None:
    """The sequential registrar reuses spectra and gives the same result as register()."""
    a, b = texture[:N, :N], texture[10:10 + N, 20:20 + N]
    seq = SequentialRegistrar()
    assert seq.step(a) is None
    r1, r2 = seq.step(b), register(a, b)
    assert r1 is not None and r1.shift_px == r2.shift_px and r1.angle_deg == r2.angle_deg
    with pytest.raises(ValueError, match="image has shape"):
        seq.step(texture[:64, :64])


def test_bad_input_names_the_argument(texture: np.ndarray) -> None:
    """NaN, mismatched shapes, wrong dimensions and tiny images raise ValueError naming the argument."""
    a = texture[:64, :64].astype(float)
    bad = a.copy()
    bad[3, 3] = np.nan
    with pytest.raises(ValueError, match="moving contains NaN"):
        register(a, bad)
    with pytest.raises(ValueError, match="reference contains NaN"):
        register(bad, a)
    with pytest.raises(ValueError, match="moving has shape"):
        register(a, texture[:64, :70])
    with pytest.raises(ValueError, match="reference must be a 2-D"):
        register(np.zeros((64, 64, 3)), a)
    with pytest.raises(ValueError, match="at least 32x32"):
        register(a[:16, :16], a[:16, :16])
    with pytest.raises(ValueError, match="for their roles"):
        register_prepared(prepare(a), prepare(a, moving=False))


def test_config_validation() -> None:
    """Each IfmiConfig error path names its field."""
    for kwargs, match in [({"n_angle": 8}, "n_angle"), ({"peak_neighbourhood": 4}, "peak_neighbourhood"),
                          ({"min_pnr": -1.0}, "min_pnr"), ({"max_scale": 1.0}, "max_scale"),
                          ({"window_alpha": 2.0}, "window_alpha"), ({"r_min_cycles": 0.0}, "r_min_cycles")]:
        with pytest.raises(ValueError, match=match):
            IfmiConfig(**kwargs)


@pytest.mark.parametrize("shape", [(64, 64), (63, 64), (64, 63), (33, 35)])
def test_opencv_packed_fft_matches_scipy(shape: tuple[int, int]) -> None:
    """rfft2/irfft2 through OpenCV's packed real DFT equal scipy's, for even and odd sizes."""
    rng = np.random.default_rng(0)
    a, b = rng.standard_normal((2, *shape)).astype(np.float32)
    fa = spectral.rfft2(a)
    np.testing.assert_allclose(fa, scipy.fft.rfft2(a), atol=1e-3)
    cross = spectral.rfft2(b) * np.conj(fa)
    kept = cross.copy()
    np.testing.assert_allclose(spectral.irfft2(cross, shape), scipy.fft.irfft2(cross, s=shape), atol=1e-4)
    np.testing.assert_array_equal(cross, kept)  # packed in place for the DFT, then restored


def test_descriptor_spectrum_is_the_mean_free_tapered_descriptor() -> None:
    """The descriptor's mean, removed in its spectrum's row 0, equals removing it before the taper."""
    rng = np.random.default_rng(1)
    polar = rng.uniform(0.0, 50.0, (64, 64)).astype(np.float32)
    weight = rng.uniform(0.1, 2.0, (1, 32)).astype(np.float32)
    taper = np.hanning(34)[1:-1].astype(np.float32)[None, :]
    desc = polar[:, :32].astype(np.float64) * weight
    expected = scipy.fft.rfft2((desc - desc.mean()) * taper)
    got = spectral.descriptor_spectrum(polar, spectral.radius_taper(weight, taper))
    np.testing.assert_allclose(got, expected, atol=1e-4 * np.abs(expected).max())


def test_prepared_keeps_the_image(texture: np.ndarray) -> None:
    """``Prepared`` holds the image minus its mean; ``image`` gives it back, and the input is not written."""
    img = texture[:64, :96].astype(np.float32)
    before = img.copy()
    prep = prepare(img)
    np.testing.assert_allclose(prep.image, before, atol=1e-4)
    np.testing.assert_array_equal(img, before)
    assert prep.image.dtype == np.float32 and abs(float(prep.centred.mean())) < 1e-3


def perturbed(texture: np.ndarray, rng: np.random.Generator, noise: float, blur: float
              ) -> tuple[np.ndarray, np.ndarray, tuple[float, float], float]:
    """A random similarity pair (docs/ifmi.md convention) rendered from the texture, sensor noise of sigma ``noise``
    on both images and a blur on the moving one; the true shift and angle (degrees)."""
    y, x = (int(v) for v in rng.integers(0, 1024 - N, 2))
    angle, scale = rng.uniform(-180, 180), math.exp(rng.uniform(math.log(0.8), math.log(1.25)))
    dx, dy = rng.uniform(-0.2, 0.2, 2) * N
    a = cv2.getRotationMatrix2D(((N - 1) / 2, (N - 1) / 2), angle, scale)
    a[:, 2] += (dx, dy)
    a[:, 2] -= a[:, :2] @ np.array([x, y], float)  # render the moving image from the texture around the crop
    mov = cv2.warpAffine(texture, a, (N, N)).astype(np.float32)
    if blur:
        mov = cv2.GaussianBlur(mov, (0, 0), blur)
    ref = texture[y:y + N, x:x + N].astype(np.float32)
    ref += rng.normal(0, noise, ref.shape).astype(np.float32)
    mov += rng.normal(0, noise, mov.shape).astype(np.float32)
    return ref, mov, (dx, dy), float(angle)


def test_paper_translation_covariance_is_conservative(texture: np.ndarray) -> None:
    """NEES of the translation against the paper's eq. (10) covariance on noisy, blurred pairs: far below 2.

    The paper's heuristic measures the width of the POMF peak (about half a pixel), not the
    error of its subpixel location (a few hundredths): it is not calibrated but conservative,
    by one to two orders of magnitude (benchmarks/ifmi_calibration.py). The bounds are loose
    on purpose: all within the chi2(2) 95 % bound, mean NEES between 1e-4 and 0.5.
    """
    rng = np.random.default_rng(11)
    nees = []
    for noise, blur in [(0.0, 0.0), (3.0, 0.0), (0.0, 1.0), (3.0, 1.0)] * 3:
        ref, mov, (dx, dy), _ = perturbed(texture, rng, noise, blur)
        r = register(ref, mov, IfmiConfig(covariance="paper"))
        assert r.status is Status.OK
        e = np.array([r.shift_px[0] - dx, r.shift_px[1] - dy])
        nees.append(float(e @ np.linalg.solve(r.covariance[:2, :2], e)))
    assert max(nees) < 5.991 and 1e-4 < float(np.mean(nees)) < 0.5


def test_noisy_blurred_pairs_are_accepted_in_a_lower_band(texture: np.ndarray) -> None:
    """Noise over a blurred image leaves the full-band PNR below 0.2; a lower band holds the Dirac, rightly placed."""
    rng = np.random.default_rng(12)
    bands = []
    for _ in range(4):
        ref, mov, (dx, dy), _ = perturbed(texture, rng, 4.0, 1.0)
        r = register(ref, mov)
        assert r.status is Status.OK and math.hypot(r.shift_px[0] - dx, r.shift_px[1] - dy) < 0.5
        bands.append(r.band)
    assert max(bands) > 1


def test_non_overlapping_noisy_pairs_are_rejected(texture: np.ndarray) -> None:
    """The lower bands do not let chance peaks through: different places stay below the threshold."""
    rng = np.random.default_rng(13)
    for _ in range(6):
        y1, x1 = rng.integers(0, 1024 - N, 2)
        y2, x2 = (int(y1) + N + 20) % (1024 - N), (int(x1) + N + 20) % (1024 - N)
        a = texture[y1:y1 + N, x1:x1 + N].astype(np.float32) + rng.normal(0, 6.0, (N, N)).astype(np.float32)
        b = texture[y2:y2 + N, x2:x2 + N].astype(np.float32) + rng.normal(0, 6.0, (N, N)).astype(np.float32)
        assert register(a, cv2.GaussianBlur(b, (0, 0), 1.5)).status is Status.AMBIGUOUS


def test_skerki_sequence_consecutive_pairs(shared_data: Path) -> None:
    """Real consecutive Skerki frames (lamp hot spot, mud): most pairs accepted, all accepted ones plausible.

    The vehicle flies along the image's vertical axis, 110 to 145 px per frame (the data README's
    phase correlation after mean-image subtraction gives a median of 127 px), with little turn.
    """
    frames = sorted((shared_data / "skerki-underwater-seq0658-0714").glob("*.png"))[:21]
    seq = SequentialRegistrar()
    regs = [seq.step(flatten_illumination(cv2.imread(str(f), cv2.IMREAD_GRAYSCALE))) for f in frames]
    ok = [r for r in regs if r is not None and r.status is Status.OK]
    assert len(ok) >= 17  # of 20
    for r in ok:
        dx, dy = r.shift_px
        assert abs(r.angle_deg) < 5.0 and 90.0 < math.hypot(dx, dy) < 160.0 and abs(dy) > 3 * abs(dx)
