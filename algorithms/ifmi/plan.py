"""What iFMI registration computes once: per image shape (:class:`Plan`) and per image (:class:`Prepared`).

Steps 1-4 of section II-A of [1]_ for one image: the windowed spectrum, its magnitude resampled
on a log-polar grid and the FMI descriptor's spectrum, plus what the coarse translation pass
needs: a downsampled copy of the reference (to warp) and, for the moving image, the phase of the
low band of its spectrum (no second transform: a half-size spectrum of the band-limited image,
shifted onto the downsampled copy's pixel centres). The sequential mode computes them once per image.

References
----------
.. [1] M. Pfingsthorn, A. Birk, S. Schwertfeger, H. Bülow, K. Pathak, "Maximum Likelihood
   Mapping with Spectral Image Registration", ICRA 2010, section II.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import Any, cast

import cv2
import numpy as np
from numpy.typing import NDArray

from slamreplay.algorithms.ifmi import spectral
from slamreplay.algorithms.ifmi.covariance import COVARIANCES, LEVERS

F32 = NDArray[np.float32]
F64 = NDArray[np.float64]
MIN_SIZE = 32
COARSE = 2  # the coarse translation pass runs on images downsampled COARSE times


@dataclass(frozen=True, slots=True)
class IfmiConfig:
    """Parameters of :func:`register`.

    Attributes
    ----------
    n_angle, n_radius : log-polar descriptor size (angle bins over 180 degrees, log-radius bins); 0 (the
        default) takes the image's smaller side (rounded up to a fast FFT size): a fixed 256 lost
        accuracy on 512 x 512 images (0.15 % scale, 0.15 px) and 128 on 256 x 256 ones.
    r_min_cycles : lowest spectral radius resampled, cycles per image (smaller side).
    window_alpha : taper fraction of the elliptical Tukey window (step 1).
    peak_neighbourhood : K of eq. (10), odd.
    min_pnr : PNR threshold of eq. (13) deciding ``status`` (the paper's 0.2).
    max_scale : largest scale change searched (and its inverse).
    covariance : ``"calibrated"`` (the default, chosen by measurement) or ``"paper"``: eq. (10) on the POMF
        peaks, 10 to 200 times too large; ``calibrated`` divides the translation's by PNR sqrt(H W) and
        takes the rotation/scale's from the phase residuals (:mod:`slamreplay.algorithms.ifmi.covariance`).
    refine_translation : after the coarse pass of steps 7-9, warp the reference by the whole estimate,
        shift included, before the full-resolution POMF; else that POMF uses the reference re-rotated
        and re-scaled only (:mod:`slamreplay.algorithms.ifmi.registration`).
    translation_band : the finest band the translation peak is read in (1: all frequencies, as in the paper;
        b: those below 1/b of Nyquist, a power of 2; :func:`spectral.band_peak`). The default 2 leaves out the
        upper half of the frequencies, where the bilinear warps of the pair and of step 7 garble the phase
        (docs/ifmi.md, "The translation's band").
    lever : the arm of the angle's and scale's errors on the calibrated shift (:func:`covariance.with_overlap_lever`):
        ``"overlap"`` (the default) half the shift, the overlap's centre; ``"content"`` the centroid of the
        whitened match (where the POMF's evidence lies; two more band-sized inverse transforms): larger on a
        window-weighted uniform texture (translation NEES 1.23-1.45 -> 0.73-0.84 on the seabed sources), closer
        on scenes of a few edges (RTAB-Map's indoor frames: clean pairs 6.74 -> 3.44; docs/ifmi.md).
    """

    n_angle: int = 0
    n_radius: int = 0
    r_min_cycles: float = 4.0
    window_alpha: float = 0.5
    peak_neighbourhood: int = 5
    min_pnr: float = 0.2
    max_scale: float = 2.0
    refine_translation: bool = True
    covariance: str = "calibrated"
    translation_band: int = 2
    lever: str = "overlap"

    def __post_init__(self) -> None:
        for name in ("n_angle", "n_radius"):
            if getattr(self, name) != 0 and getattr(self, name) < 16:
                raise ValueError(f"{name} must be 0 (automatic) or >= 16, got {getattr(self, name)}")
        if not 0.0 < self.r_min_cycles <= 0.125 * MIN_SIZE:
            raise ValueError(f"r_min_cycles must be in (0, {0.125 * MIN_SIZE}], got {self.r_min_cycles}")
        if not 0.0 <= self.window_alpha <= 1.0:
            raise ValueError(f"window_alpha must be in [0, 1], got {self.window_alpha}")
        if self.peak_neighbourhood < 3 or self.peak_neighbourhood % 2 == 0:
            raise ValueError(f"peak_neighbourhood must be odd and >= 3, got {self.peak_neighbourhood}")
        if not self.min_pnr >= 0.0:
            raise ValueError(f"min_pnr must be >= 0, got {self.min_pnr}")
        if self.covariance not in COVARIANCES:
            raise ValueError(f"covariance must be one of {', '.join(COVARIANCES)}, got {self.covariance!r}")
        if self.lever not in LEVERS:
            raise ValueError(f"lever must be one of {', '.join(LEVERS)}, got {self.lever!r}")
        if self.translation_band < 1 or self.translation_band & (self.translation_band - 1):
            raise ValueError(f"translation_band must be a power of 2 (1, 2, 4, ...), got {self.translation_band}")
        if not self.max_scale > 1.0:
            raise ValueError(f"max_scale must be > 1, got {self.max_scale}")


DEFAULT_CONFIG = IfmiConfig()


def affine(shape: tuple[int, int], angle_deg: float, scale: float, shift_px: tuple[float, float]) -> F64:
    """``cv2.getRotationMatrix2D`` about the centre of an (H, W) image, plus ``shift_px``."""
    h, w = shape
    cx, cy = (w - 1) / 2.0, (h - 1) / 2.0
    theta = math.radians(angle_deg)  # OpenCV's formula, in Python floats (a few NumPy calls fewer)
    alpha, beta = math.cos(theta) * scale, math.sin(theta) * scale
    return np.array([[alpha, beta, (1.0 - alpha) * cx - beta * cy + shift_px[0]],
                     [-beta, alpha, beta * cx + (1.0 - alpha) * cy + shift_px[1]]])


@dataclass(frozen=True, slots=True, eq=False)
class Plan:
    """Everything that depends only on the image shape and the config (computed once per shape)."""

    shape: tuple[int, int]
    window: F32
    log_polar: spectral.LogPolarMap
    taper: spectral.RadiusTaper  # the descriptor's radius weights (high-pass and taper), all n_radius columns
    low_taper: spectral.RadiusTaper  # those of the low-radius descriptor (the first half of the columns)
    col_limit: int
    coarse_shape: tuple[int, int]  # (H // COARSE, W // COARSE)
    coarse_window: F32
    coarse_turn: NDArray[np.complex64]  # a coarse image turned by 180 degrees has the spectrum conj(F / coarse_turn)
    coarse_ramp: NDArray[np.complex64]  # moves the low band of a spectrum onto the coarse image's pixel centres
    coarse_grid: tuple[float, float, float, float]  # (sx, sy, ox, oy): full-resolution pixel (x, y) -> coarse
    # pixel (sx x + ox, sy y + oy), cv2.resize's pixel-centre convention


@functools.lru_cache(maxsize=8)
def plan(shape: tuple[int, int], config: IfmiConfig) -> Plan:
    """The precomputed windows and maps for images of ``shape`` (a pure function, memoized)."""
    h, w = shape
    auto = cv2.getOptimalDFTSize(min(h, w))
    n_angle, n_radius = config.n_angle or auto, config.n_radius or auto
    lp = spectral.log_polar_map(shape, n_angle, n_radius, config.r_min_cycles)
    weight = spectral.highpass(lp.radius_cycles)[None, :]
    taper = np.hanning(n_radius + 2)[1:-1].astype(np.float32)[None, :]
    low_taper = np.hanning(n_radius // 2 + 2)[1:-1].astype(np.float32)[None, :]
    col_limit = min(n_radius // 2 - 1, math.ceil(math.log(config.max_scale) / lp.log_step) + 1)
    hc, wc = h // COARSE, w // COARSE
    fy = np.fft.fftfreq(hc)[:, None]
    fx = np.fft.rfftfreq(wc)[None, :]
    turn = np.exp(-2j * np.pi * (fy + fx)).astype(np.complex64)
    sx, sy = wc / w, hc / h
    ox, oy = 0.5 * sx - 0.5, 0.5 * sy - 0.5
    ramp = np.exp(-2j * np.pi * (fy * oy + fx * ox)).astype(np.complex64)  # a shift by (-ox, -oy) coarse pixels
    return Plan(shape, spectral.tukey_window(shape, config.window_alpha), lp, spectral.radius_taper(weight, taper),
                spectral.radius_taper(weight[:, : low_taper.shape[1]], low_taper), col_limit, (hc, wc),
                spectral.tukey_window((hc, wc), config.window_alpha), turn, ramp, (sx, sy, ox, oy))


@dataclass(frozen=True, slots=True, eq=False)
class Prepared:
    """One image's reusable spectra: the sequential mode computes them once per image.

    An image registered only as the reference needs no ``spectrum`` or ``coarse_phase``, one
    registered only as the moving image no ``coarse``: :func:`register` leaves them out (None).
    """

    centred: F32  # (H, W) float32: the image minus its mean (a warp fills pixels from outside it with 0, the mean)
    mean: float  # the image's mean
    spectrum: NDArray[np.complex64] | None  # rfft2 of the windowed image (step 1)
    coarse: F32 | None  # ``centred`` downsampled COARSE times (pixel areas averaged): the coarse pass warps it
    coarse_phase: NDArray[np.complex64] | None  # phase of the low band of ``spectrum`` (the rfft2 of the windowed
    # image on the COARSE times coarser grid, band-limited), moved onto ``coarse``'s pixel centres
    polar: F32 | None  # the log-polar magnitude (steps 2-4); None if flat
    descriptor: NDArray[np.complex64] | None  # rfft2 of the FMI descriptor (steps 2-4); None if flat

    @property
    def image(self) -> F32:
        """The (H, W) float32 image (recomputed from ``centred`` and ``mean``)."""
        return self.centred + np.float32(self.mean)


EXACT_STATS = (np.dtype(np.uint8), np.dtype(np.uint16), np.dtype(np.int16), np.dtype(np.float32))  # OpenCV reads


def _check(name: str, image: object) -> NDArray[Any]:
    """The image, validated: as given if OpenCV reads its dtype exactly (else as float32), never to be written."""
    arr = np.asarray(image)
    if arr.ndim != 2:
        raise ValueError(f"{name} must be a 2-D (H, W) image, got shape {arr.shape}")
    if arr.dtype.kind not in "uif":  # bool, complex, object, ...
        raise ValueError(f"{name} must hold real numbers, got dtype {arr.dtype}")
    if min(arr.shape) < MIN_SIZE:
        raise ValueError(f"{name} must be at least {MIN_SIZE}x{MIN_SIZE}, got {arr.shape}")
    src = arr if arr.dtype in EXACT_STATS else arr.astype(np.float32)
    if src.dtype.kind == "f" and not cv2.checkRange(src)[0]:
        raise ValueError(f"{name} contains NaN or infinite values")
    return src


def prepare(image: NDArray[np.generic], config: IfmiConfig = IfmiConfig(), name: str = "image", *,
            reference: bool = True, moving: bool = True) -> Prepared:
    """Validate an (H, W) image and compute its spectra (steps 1-4); ValueError naming ``name`` on bad input.

    ``reference`` / ``moving``: compute what registering it in that role needs (default: both).
    """
    src = _check(name, image)
    p = plan((src.shape[0], src.shape[1]), config)
    lo, hi, _, _ = cv2.minMaxLoc(src)
    flat = hi - lo <= 1e-6 * max(1.0, abs(lo), abs(hi))
    mean = cv2.mean(src)[0]
    centred = src.astype(np.float32)  # a copy even if float32: the input is never written
    centred -= np.float32(mean)
    spec = spectral.rfft2(centred * p.window)  # step 1 (:func:`spectral.spectrum`, the mean known)
    polar = None if flat else spectral.log_polar_magnitude(spec, p.log_polar)
    desc = None if polar is None else spectral.descriptor_spectrum(polar, p.taper)
    coarse = cast(F32, cv2.resize(centred, p.coarse_shape[::-1], interpolation=cv2.INTER_AREA)) if reference else None
    coarse_phase = None
    if moving:  # the coarse pass's spectrum: the low band of the full one, no second transform
        low = spectral.low_band(spec, p.shape, COARSE)
        low *= p.coarse_ramp
        coarse_phase = spectral.phase_only(low)
    return Prepared(centred, mean, spec if moving else None, coarse, coarse_phase, polar, desc)
