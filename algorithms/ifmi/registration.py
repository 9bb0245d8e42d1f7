"""iFMI spectral registration with the POMF covariance and PNR of Pfingsthorn et al. [1]_, section II.

``register(reference, moving, config)`` estimates the similarity transform that takes
``reference`` onto ``moving``. Convention (the one OpenCV uses):

    A = cv2.getRotationMatrix2D(((w - 1) / 2, (h - 1) / 2), angle_deg, scale)
    A[:, 2] += shift_px
    moving ~= cv2.warpAffine(reference, A, (w, h))

so ``angle_deg`` is counter-clockwise as displayed (y down), about the image centre, and
``shift_px = (dx, dy)`` is where the reference's centre lands in ``moving``, minus the centre.

The nine steps of section II-A: (1) spectra of the windowed images, (2) their magnitudes
(high-passed, [2]_), (3-4) log-polar resampling, (5) a POMF of the two descriptors, (6) the
rotation/scale from its Dirac peak (subpixel, cyclic in angle), (7) re-rotate/re-scale the
reference, (8) a POMF against ``moving``, (9) the translation from its Dirac peak. The
magnitude spectrum cannot tell ``angle`` from ``angle + 180``: step (8) runs for both and the
stronger peak wins. Section II-B gives each POMF peak a covariance (eq. 10) and a
peak-to-noise ratio (eqs. 11-13); the translation PNR decides ``status`` (threshold 0.2).

References
----------
.. [1] M. Pfingsthorn, A. Birk, S. Schwertfeger, H. Bülow, K. Pathak, "Maximum Likelihood
   Mapping with Spectral Image Registration", ICRA 2010, section II.
.. [2] B. S. Reddy, B. N. Chatterji, IEEE TIP 5(8), 1996.
"""

from __future__ import annotations

import enum
import functools
import math
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from algorithms.ifmi import spectral
from algorithms.observe import NULL_OBSERVER, Image, Observer, Points, Scalar

F32 = NDArray[np.float32]
F64 = NDArray[np.float64]
MIN_SIZE = 32


class Status(enum.Enum):
    """Outcome of a registration; never an exception."""

    OK = "ok"  # translation PNR >= min_pnr
    AMBIGUOUS = "ambiguous"  # a result, but its PNR is below min_pnr (eq. 13): reject it
    FLAT = "flat"  # an image has no texture: nothing to register


@dataclass(frozen=True, slots=True)
class IfmiConfig:
    """Parameters of :func:`register`.

    Attributes
    ----------
    n_angle, n_radius : log-polar descriptor size (angle bins over 180 degrees, log-radius bins).
    r_min_cycles : lowest spectral radius resampled, cycles per image (smaller side).
    window_alpha : taper fraction of the elliptical Tukey window (step 1).
    peak_neighbourhood : K of eq. (10), odd.
    min_pnr : PNR threshold of eq. (13) deciding ``status`` (the paper's 0.2).
    max_scale : largest scale change searched (and its inverse).
    refine_translation : repeat steps 7-9 with the reference warped by the whole estimate
        (:func:`_refine_translation`); the translation PNR then comes from that pass.
    """

    n_angle: int = 256
    n_radius: int = 256
    r_min_cycles: float = 4.0
    window_alpha: float = 0.5
    peak_neighbourhood: int = 5
    min_pnr: float = 0.2
    max_scale: float = 2.0
    refine_translation: bool = True

    def __post_init__(self) -> None:
        for name in ("n_angle", "n_radius"):
            if getattr(self, name) < 16:
                raise ValueError(f"{name} must be >= 16, got {getattr(self, name)}")
        if not 0.0 < self.r_min_cycles <= 0.125 * MIN_SIZE:
            raise ValueError(f"r_min_cycles must be in (0, {0.125 * MIN_SIZE}], got {self.r_min_cycles}")
        if not 0.0 <= self.window_alpha <= 1.0:
            raise ValueError(f"window_alpha must be in [0, 1], got {self.window_alpha}")
        if self.peak_neighbourhood < 3 or self.peak_neighbourhood % 2 == 0:
            raise ValueError(f"peak_neighbourhood must be odd and >= 3, got {self.peak_neighbourhood}")
        if not self.min_pnr >= 0.0:
            raise ValueError(f"min_pnr must be >= 0, got {self.min_pnr}")
        if not self.max_scale > 1.0:
            raise ValueError(f"max_scale must be > 1, got {self.max_scale}")


@dataclass(frozen=True, slots=True, eq=False)
class Registration:
    """A similarity transform taking the reference onto the moving image (module convention).

    Attributes
    ----------
    angle_deg : rotation about the image centre, degrees, counter-clockwise as displayed, in [-180, 180).
    scale : scale factor (moving / reference).
    shift_px : (dx, dy), pixels.
    covariance : (3, 3) over (dx, dy, angle_deg), px^2 and deg^2 (eq. 10, both POMF stages).
    scale_var : variance of ``scale`` (eq. 10 on the rotation/scale POMF).
    pnr : PNR of the translation POMF (eq. 13); decides ``status``.
    pnr_rotation_scale : PNR of the rotation/scale POMF (eq. 13).
    status : OK, AMBIGUOUS (pnr < min_pnr) or FLAT.
    """

    angle_deg: float
    scale: float
    shift_px: tuple[float, float]
    covariance: F64
    scale_var: float
    pnr: float
    pnr_rotation_scale: float
    status: Status

    def matrix(self, shape: tuple[int, int]) -> F64:
        """The 2x3 affine ``A`` of the module convention for images of ``shape`` (H, W)."""
        return affine(shape, self.angle_deg, self.scale, self.shift_px)


def affine(shape: tuple[int, int], angle_deg: float, scale: float, shift_px: tuple[float, float]) -> F64:
    """``cv2.getRotationMatrix2D`` about the centre of an (H, W) image, plus ``shift_px``."""
    h, w = shape
    a = cv2.getRotationMatrix2D(((w - 1) / 2.0, (h - 1) / 2.0), float(angle_deg), float(scale))
    a[:, 2] += shift_px
    return np.asarray(a, dtype=np.float64)


@dataclass(frozen=True, slots=True, eq=False)
class Plan:
    """Everything that depends only on the image shape and the config (computed once per shape)."""

    shape: tuple[int, int]
    window: F32
    highpass: F32
    log_polar: spectral.LogPolarMap
    radius_window: F32
    flip_phase: NDArray[np.complex64]  # spectrum of a 180-degree rotation: conj(F) * flip_phase
    col_limit: int


@functools.lru_cache(maxsize=8)
def plan(shape: tuple[int, int], config: IfmiConfig) -> Plan:
    """The precomputed windows and maps for images of ``shape`` (a pure function, memoized)."""
    h, w = shape
    lp = spectral.log_polar_map(shape, config.n_angle, config.n_radius, config.r_min_cycles)
    radius_window = np.hanning(config.n_radius + 2)[1:-1].astype(np.float32)[None, :]
    fy = np.fft.fftfreq(h)[:, None]
    fx = np.fft.rfftfreq(w)[None, :]
    flip_phase = np.exp(2j * np.pi * (fy + fx)).astype(np.complex64)
    col_limit = min(config.n_radius // 2 - 1, math.ceil(math.log(config.max_scale) / lp.log_step) + 1)
    return Plan(shape, spectral.tukey_window(shape, config.window_alpha), spectral.highpass(shape), lp,
                radius_window, flip_phase, col_limit)


@dataclass(frozen=True, slots=True, eq=False)
class Prepared:
    """One image's reusable spectra: the sequential mode computes them once per image."""

    image: F32  # (H, W) float32 as given
    phase: NDArray[np.complex64]  # phase of the rfft2 of the windowed image (step 1)
    descriptor: NDArray[np.complex64] | None  # phase of the rfft2 of the FMI descriptor (steps 2-4); None if flat


def _check(name: str, image: object) -> F32:
    arr = np.asarray(image)
    if arr.ndim != 2:
        raise ValueError(f"{name} must be a 2-D (H, W) image, got shape {arr.shape}")
    if not (np.issubdtype(arr.dtype, np.number) and not np.iscomplexobj(arr)):
        raise ValueError(f"{name} must hold real numbers, got dtype {arr.dtype}")
    if min(arr.shape) < MIN_SIZE:
        raise ValueError(f"{name} must be at least {MIN_SIZE}x{MIN_SIZE}, got {arr.shape}")
    out = arr.astype(np.float32)
    if not np.all(np.isfinite(out)):
        raise ValueError(f"{name} contains NaN or infinite values")
    return out


def prepare(image: NDArray[np.generic], config: IfmiConfig = IfmiConfig(), name: str = "image") -> Prepared:
    """Validate an (H, W) image and compute its spectra (steps 1-4); ValueError naming ``name`` on bad input."""
    img = _check(name, image)
    p = plan(img.shape, config)  # type: ignore[arg-type]
    _, std = cv2.meanStdDev(img)
    lo, hi, _, _ = cv2.minMaxLoc(img)
    flat = float(std[0, 0]) <= 1e-6 * max(1.0, abs(lo), abs(hi))
    spec = spectral.spectrum(img, p.window)
    desc = None if flat else spectral.magnitude_descriptor(spec, p.highpass, p.log_polar, p.radius_window)
    return Prepared(img, spectral.phase_only(spec), desc)


def register(reference: NDArray[np.generic], moving: NDArray[np.generic], config: IfmiConfig = IfmiConfig(),
             observer: Observer = NULL_OBSERVER) -> Registration:
    """Estimate the similarity transform taking ``reference`` onto ``moving`` (module convention).

    Parameters
    ----------
    reference, moving : (H, W) real arrays of the same shape, finite, at least 16x16.
    config : IfmiConfig.
    observer : receives ``ifmi/pomf/rotation_scale`` and ``ifmi/pomf/translation`` (Image, the
        fftshifted POMF surfaces), their ``.../peak`` (Points, pixel coordinates in the surface)
        and ``ifmi/pnr`` (Scalar).

    Returns
    -------
    Registration : with ``status`` FLAT when either image is constant, AMBIGUOUS when the
        translation PNR is below ``config.min_pnr``.

    Raises
    ------
    ValueError : an argument is not a finite 2-D real image, or the shapes differ (names it).
    """
    ref = prepare(reference, config, "reference")
    mov_arr = np.asarray(moving)
    if mov_arr.shape != ref.image.shape:
        raise ValueError(f"moving has shape {mov_arr.shape} but reference has {ref.image.shape}: they must match")
    return register_prepared(ref, prepare(mov_arr, config, "moving"), config, observer)


def _flat() -> Registration:
    inf = math.inf
    return Registration(0.0, 1.0, (0.0, 0.0), np.diag([inf, inf, inf]), inf, 0.0, 0.0, Status.FLAT)


def register_prepared(ref: Prepared, mov: Prepared, config: IfmiConfig = IfmiConfig(),
                      observer: Observer = NULL_OBSERVER) -> Registration:
    """:func:`register` on images already prepared with :func:`prepare` (the sequential mode)."""
    if ref.image.shape != mov.image.shape:
        raise ValueError(f"mov has shape {mov.image.shape} but ref has {ref.image.shape}: they must match")
    if ref.descriptor is None or mov.descriptor is None:
        return _flat()
    p = plan(ref.image.shape, config)  # type: ignore[arg-type]
    lp = p.log_polar
    # Steps 5-6: rotation/scale from the POMF of the two FMI descriptors.
    rs_cross = spectral.cross_phase(ref.descriptor, mov.descriptor)
    rs_surface = spectral.pomf(rs_cross, (config.n_angle, config.n_radius))
    rs = spectral.find_peak(rs_surface, config.peak_neighbourhood, p.col_limit, rs_cross)
    angle = -rs.row * lp.deg_per_bin
    scale = math.exp(-rs.col * lp.log_step)
    # Steps 7-9, for angle and angle + 180 (the magnitude spectrum's ambiguity).
    t_surface, t, angle = _translation(ref, mov, p, config, angle, scale)
    shift = (t.col, t.row)
    if config.refine_translation:
        t_surface, t, shift = _refine_translation(ref, mov, p, config, angle, scale, shift)
    angle = (angle + 180.0) % 360.0 - 180.0
    cov = np.zeros((3, 3))
    cov[0, 0], cov[1, 1] = t.cov[1][1], t.cov[0][0]
    cov[0, 1] = cov[1, 0] = t.cov[0][1]
    cov[2, 2] = rs.cov[0][0] * lp.deg_per_bin**2
    scale_var = rs.cov[1][1] * (scale * lp.log_step) ** 2
    status = Status.OK if t.pnr >= config.min_pnr else Status.AMBIGUOUS
    if observer is not NULL_OBSERVER:
        _log_surface(observer, "ifmi/pomf/rotation_scale", rs_surface, rs)
        _log_surface(observer, "ifmi/pomf/translation", t_surface, t)
        observer.log("ifmi/pnr", Scalar(t.pnr))
    return Registration(float(angle), float(scale), (float(shift[0]), float(shift[1])), cov, float(scale_var),
                        float(t.pnr), float(rs.pnr), status)


def _warped_spectrum(ref: Prepared, p: Plan, angle: float, scale: float,
                     shift: tuple[float, float] = (0.0, 0.0)) -> NDArray[np.complex64]:
    """Step 7: the phase of the windowed spectrum of the reference re-rotated and re-scaled onto ``moving``."""
    h, w = p.shape
    warped = cv2.warpAffine(ref.image, affine(p.shape, angle, scale, shift), (w, h), flags=cv2.INTER_LINEAR,
                            borderMode=cv2.BORDER_REFLECT)
    return spectral.spectrum(warped, p.window)


def _translation(ref: Prepared, mov: Prepared, p: Plan, config: IfmiConfig, angle: float,
                 scale: float) -> tuple[F32, spectral.Peak, float]:
    """Steps 7-9 for ``angle`` and ``angle + 180``: the stronger translation peak wins."""
    phase = spectral.phase_only(_warped_spectrum(ref, p, angle, scale))
    best: tuple[F32, spectral.Peak, float, NDArray[np.complex64]] | None = None
    for flipped in (False, True):
        cross = spectral.cross_phase(np.conj(phase) * p.flip_phase if flipped else phase, mov.phase)
        surface = spectral.pomf(cross, p.shape)
        peak = spectral.find_peak(surface, config.peak_neighbourhood)
        if best is None or peak.s > best[1].s:
            best = (surface, peak, angle + 180.0 if flipped else angle, cross)
    assert best is not None
    surface, peak, angle, cross = best
    return surface, peak, angle


def _refine_translation(ref: Prepared, mov: Prepared, p: Plan, config: IfmiConfig, angle: float, scale: float,
                        shift: tuple[float, float]) -> tuple[F32, spectral.Peak, tuple[float, float]]:
    """Steps 7-9 again with the reference warped by the whole estimate, shift included.

    The shift is rounded to whole pixels: a bilinear warp by a constant fraction of a pixel
    shifts the phase of the spectrum non-linearly and would bias the estimate. The residual
    shift is then within half a pixel, where the subpixel estimate is unbiased, and both
    windows see the same content, so the PNR measures the match rather than the overlap lost
    to the window.
    """
    whole = (float(round(shift[0])), float(round(shift[1])))
    phase = spectral.phase_only(_warped_spectrum(ref, p, angle, scale, whole))
    cross = spectral.cross_phase(phase, mov.phase)
    surface = spectral.pomf(cross, p.shape)
    t = spectral.find_peak(surface, config.peak_neighbourhood)
    return surface, t, (whole[0] + t.col, whole[1] + t.row)


def _log_surface(observer: Observer, path: str, surface: F32, peak: spectral.Peak) -> None:
    """A POMF surface, fftshifted so zero shift is at the centre, with its peak marked."""
    rows, cols = surface.shape
    observer.log(path, Image(np.fft.fftshift(surface).astype(np.float32)))
    observer.log(f"{path}/peak", Points(np.array([[peak.col + cols // 2, peak.row + rows // 2]]), radius=2.0))


class SequentialRegistrar:
    """The sequential mode of [1]_, section IV-C: each image's spectra are computed once.

    ``step(image)`` registers the previous image (reference) onto ``image`` (moving) and keeps
    ``image``'s spectra for the next pair, so a pair costs one image's steps 1-4 instead of two.
    """

    def __init__(self, config: IfmiConfig = IfmiConfig()) -> None:
        self.config = config
        self.previous: Prepared | None = None

    def step(self, image: NDArray[np.generic], observer: Observer = NULL_OBSERVER) -> Registration | None:
        """Register the previous image onto ``image``; None for the first image.

        Raises
        ------
        ValueError : ``image`` is not a finite 2-D real image, or its shape differs from the previous one.
        """
        current = prepare(image, self.config, "image")
        previous, self.previous = self.previous, current
        if previous is None:
            return None
        if previous.image.shape != current.image.shape:
            self.previous = previous
            raise ValueError(f"image has shape {current.image.shape} but the previous image has "
                             f"{previous.image.shape}: a sequence must keep one size")
        return register_prepared(previous, current, self.config, observer)
