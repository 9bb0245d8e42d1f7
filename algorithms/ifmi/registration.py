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
Eq. (10) measures the peak's width, not the error of its location, and is 10 to 200 times too
large; ``IfmiConfig.covariance`` (default ``"calibrated"``) replaces it by the calibrated form of
:mod:`slamreplay.algorithms.ifmi.covariance` (``"paper"`` keeps eq. 10).

Beyond the paper, each for a measured failure: steps 7-9 run coarse first (half resolution,
both half turns) and then at full resolution with the reference warped by the whole estimate;
the translation peak and its PNR are read in the finest band of the POMF, from
``IfmiConfig.translation_band`` on (default 2: the upper half of the frequencies holds the
bilinear warps' garbled phase), where the Dirac is clear (noise, blur and low-texture mud
otherwise drown eq. 13, :func:`spectral.band_peak`); a weak pair also tries the
rotation/scale of the lower radii and the other half turn (:func:`register_prepared`); and a
rotation within 1.5 degrees of a multiple of 90 is re-measured away from the pixel grid's
imprint (:func:`_rotation_scale`).

References
----------
.. [1] M. Pfingsthorn, A. Birk, S. Schwertfeger, H. Bülow, K. Pathak, "Maximum Likelihood
   Mapping with Spectral Image Registration", ICRA 2010, section II.
.. [2] B. S. Reddy, B. N. Chatterji, IEEE TIP 5(8), 1996.
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass
from typing import cast

import cv2
import numpy as np
from numpy.typing import NDArray

from slamreplay.algorithms.ifmi import covariance, spectral
from slamreplay.algorithms.ifmi.plan import DEFAULT_CONFIG, IfmiConfig, Plan, Prepared, affine, plan, prepare
from slamreplay.algorithms.observe import NULL_OBSERVER, Image, Observer, Points, Scalar

F32 = NDArray[np.float32]
F64 = NDArray[np.float64]


class Status(enum.Enum):
    """Outcome of a registration; never an exception."""

    OK = "ok"  # translation PNR >= min_pnr
    AMBIGUOUS = "ambiguous"  # a result, but its PNR is below min_pnr (eq. 13): reject it
    FLAT = "flat"  # an image has no texture: nothing to register


@dataclass(frozen=True, slots=True, eq=False)
class Registration:
    """A similarity transform taking the reference onto the moving image (module convention).

    Attributes
    ----------
    angle_deg : rotation about the image centre, degrees, counter-clockwise as displayed, in [-180, 180).
    scale : scale factor (moving / reference).
    shift_px : (dx, dy), pixels.
    covariance : (3, 3) over (dx, dy, angle_deg), px^2 and deg^2: eq. (10) of both POMF stages
        (``covariance="paper"``) or its calibrated form (:mod:`slamreplay.algorithms.ifmi.covariance`:
        eq. 10 / (PNR sqrt(H W)) for the shift, the phase-residual sandwich for the angle, and the
        angle's and scale's lever on the shift, with its cross-covariance).
    scale_var : variance of ``scale`` (eq. 10 on the rotation/scale POMF, or its calibrated form).
    pnr : PNR of the translation POMF (eq. 13); decides ``status``.
    pnr_rotation_scale : PNR of the rotation/scale POMF (eq. 13).
    status : OK, AMBIGUOUS (pnr < min_pnr) or FLAT.
    band : the translation POMF's band (1: all frequencies; b: those below 1/b of Nyquist), where the PNR was read.
    """

    angle_deg: float
    scale: float
    shift_px: tuple[float, float]
    covariance: F64
    scale_var: float
    pnr: float
    pnr_rotation_scale: float
    status: Status
    band: int = 1

    def matrix(self, shape: tuple[int, int]) -> F64:
        """The 2x3 affine ``A`` of the module convention for images of ``shape`` (H, W)."""
        return affine(shape, self.angle_deg, self.scale, self.shift_px)


def register(reference: NDArray[np.generic], moving: NDArray[np.generic], config: IfmiConfig = DEFAULT_CONFIG,
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
    ref = prepare(reference, config, "reference", moving=False)
    mov_arr = np.asarray(moving)
    if mov_arr.shape != ref.centred.shape:
        raise ValueError(f"moving has shape {mov_arr.shape} but reference has {ref.centred.shape}: they must match")
    return register_prepared(ref, prepare(mov_arr, config, "moving", reference=False), config, observer)


def _flat() -> Registration:
    inf = math.inf
    return Registration(0.0, 1.0, (0.0, 0.0), np.diag([inf, inf, inf]), inf, 0.0, 0.0, Status.FLAT)


FLIP_AMBIGUITY = 3.0  # coarse PNRs of angle and angle + 180 closer than this ratio: both go to the full pass


@dataclass(frozen=True, slots=True, eq=False)
class _Candidate:
    """A rotation/scale hypothesis carried through the translation stage."""

    rs: spectral.Peak  # its rotation/scale peak (eq. 10 covariance in bins)
    rs_surface: F32
    rs_cross: NDArray[np.complex64]  # the normalized cross spectrum of that POMF (the calibrated covariance reads it)
    angle: float  # degrees, the 180-degree decision included
    scale: float
    coarse_shift: tuple[float, float]  # (dx, dy) from the coarse pass, pixels


@dataclass(frozen=True, slots=True, eq=False)
class _Result:
    candidate: _Candidate
    whole: tuple[float, float]
    surface: F32
    peak: spectral.Peak
    band: int
    centroid: tuple[float, float] | None = None  # where the POMF's match is, (x, y) px from the image centre


def register_prepared(ref: Prepared, mov: Prepared, config: IfmiConfig = DEFAULT_CONFIG,
                      observer: Observer = NULL_OBSERVER) -> Registration:
    """:func:`register` on images already prepared with :func:`prepare` (the sequential mode).

    Steps 5-6 give a rotation/scale candidate from the FMI descriptors; a coarse pass of steps
    7-9 tests it at ``angle`` and ``angle + 180`` (:func:`_coarse_translation`) and the winner
    goes through steps 7-9 at full resolution (:func:`_translation_pass`). That is all when its
    PNR (eq. 13) reaches ``min_pnr`` and the coarse pass told the half turn apart clearly. Else
    the other hypotheses are carried to full resolution too, and the strongest translation Dirac
    wins: the other half turn, and the peak of the descriptors of the lower half of the radii
    (the first half of the log-polar columns). On low-texture images (the mud of the Skerki
    frames) the outer radii of the magnitude spectrum are noise and the full descriptor's peak
    is a chance one; textured images keep their information in the outer radii.
    """
    if ref.centred.shape != mov.centred.shape:
        raise ValueError(f"mov has shape {mov.centred.shape} but ref has {ref.centred.shape}: they must match")
    if ref.coarse is None or mov.spectrum is None or mov.coarse_phase is None:
        raise ValueError("ref was prepared with reference=False or mov with moving=False: prepare them for their roles")
    if ref.descriptor is None or mov.descriptor is None or ref.polar is None or mov.polar is None:
        return _flat()
    p = plan((ref.centred.shape[0], ref.centred.shape[1]), config)
    lp = p.log_polar
    k = config.peak_neighbourhood
    n_radius = p.taper.weight.shape[1]
    rs, rs_surface, rs_cross, angle, scale = _rotation_scale(ref, mov, p, k, n_radius)
    first, *others = _coarse_translation(ref, mov, p, config, rs, rs_surface, rs_cross, angle, scale)
    best = _translation_pass(ref, mov, p, config, first)
    if best.peak.pnr < config.min_pnr or others:
        pending = list(others)
        if best.peak.pnr < config.min_pnr:
            low = _rotation_scale(ref, mov, p, k, p.low_taper.weight.shape[1])
            d_angle = (low[3] - angle + 90.0) % 180.0 - 90.0
            if abs(d_angle) > lp.deg_per_bin or abs(math.log(low[4] / scale)) > lp.log_step:
                pending += _coarse_translation(ref, mov, p, config, *low)
        for cand in pending:
            result = _translation_pass(ref, mov, p, config, cand)
            if result.peak.pnr > best.peak.pnr:
                best = result
    c, t = best.candidate, best.peak
    shift = (best.whole[0] + t.col, best.whole[1] + t.row)
    angle = (c.angle + 180.0) % 360.0 - 180.0
    rs_cov, t_cov, floor = c.rs.cov, t.cov, best.band > 1
    if config.covariance == "calibrated":  # docs/ifmi.md, "Calibrated covariance"
        t_cov = covariance.translation(t.cov, t.pnr, p.shape)
        rs_cal = covariance.rotation_scale(c.rs_cross, (c.rs_surface.shape[0], c.rs_surface.shape[1]), c.rs.row,
                                           c.rs.col)
        if math.isfinite(rs_cal[0][0]) and math.isfinite(rs_cal[1][1]):
            rs_cov, floor = rs_cal, False
    angle_var = rs_cov[0][0] * lp.deg_per_bin**2
    scale_var = rs_cov[1][1] * (c.scale * lp.log_step) ** 2
    if floor:
        # The translation Dirac of band b confirms the rotation and scale only as far as they move the
        # image's edge (half the smaller side, r) by less than b pixels: b / r radians, b / r in scale.
        tol = best.band / (0.5 * min(p.shape))
        angle_var = max(angle_var, math.degrees(tol) ** 2)
        scale_var = max(scale_var, (c.scale * tol) ** 2)
    (t_yy, t_yx), (_, t_xx) = t_cov  # (row, col) = (y, x) bins -> (dx, dy)
    cov = np.array([[t_xx, t_yx, 0.0], [t_yx, t_yy, 0.0], [0.0, 0.0, angle_var]])
    if config.covariance == "calibrated":
        # The reference turns about its centre, which lies at the shift in the moving image: the lever of the
        # angle and scale errors is the match's position from there (the overlap's centre: half the shift).
        arm = None if best.centroid is None else (shift[0] - best.centroid[0], shift[1] - best.centroid[1])
        cov = covariance.with_overlap_lever(cov, scale_var, c.scale, shift, arm)
    status = Status.OK if t.pnr >= config.min_pnr else Status.AMBIGUOUS
    if observer is not NULL_OBSERVER:
        _log_surface(observer, "ifmi/pomf/rotation_scale", c.rs_surface, c.rs)
        _log_surface(observer, "ifmi/pomf/translation", best.surface, t, best.band)
        observer.log("ifmi/pnr", Scalar(t.pnr))
    return Registration(float(angle), float(c.scale), (float(shift[0]), float(shift[1])), cov, float(scale_var),
                        float(t.pnr), float(c.rs.pnr), status, best.band)


GRID_BIAS_DEG = 1.5  # rotation estimates this close to a multiple of 90 degrees are redone (_rotation_scale)
GRID_OFFSET_DEG = 20.0  # 15, 20 and 30 did alike; 22.5, half way to the diagonals, did worse


def _rotation_scale(ref: Prepared, mov: Prepared, p: Plan, k: int, n_cols: int
                    ) -> tuple[spectral.Peak, F32, NDArray[np.complex64], float, float]:
    """Steps 5-6 on the descriptors of the first ``n_cols`` radius columns: peak, POMF, cross spectrum, angle
    (mod 180), scale.

    Both magnitude spectra are sampled on the same pixel grid, and its imprint on the
    descriptors (the bilinear resampling of the finely speckled magnitude) matches itself when
    the rotation is a multiple of 90 degrees: near one, the POMF's maximum is pulled onto it
    (0.3 degrees came out as 0.08). There the estimate is redone with the reference turned by
    :data:`GRID_OFFSET_DEG`, so that the imprint peaks away from the true one: the mean error of
    rotations within 1.2 degrees of 0, 90 or 180 fell from 0.13 to 0.028 degrees (largest 0.22
    to 0.06). The circular window keeps only the disc that a turn about the centre keeps in the
    image, so the turn loses no content.
    """
    lp = p.log_polar
    assert ref.polar is not None and mov.polar is not None
    taper = p.taper if n_cols == p.taper.weight.shape[1] else p.low_taper
    if taper is p.taper and ref.descriptor is not None and mov.descriptor is not None:
        ref_desc, mov_desc = ref.descriptor, mov.descriptor
    else:
        ref_desc = spectral.descriptor_spectrum(ref.polar, taper)
        mov_desc = spectral.descriptor_spectrum(mov.polar, taper)
    col_limit = min(p.col_limit, n_cols // 2 - 1)
    cross = spectral.normalized_cross(ref_desc, mov_desc)
    surface = spectral.pomf(cross, (lp.map_x.shape[0], n_cols))
    peak = spectral.find_peak(surface, k, col_limit, cross)
    angle, scale = -peak.row * lp.deg_per_bin, math.exp(-peak.col * lp.log_step)
    if abs((angle + 45.0) % 90.0 - 45.0) < GRID_BIAS_DEG:
        h, w = p.shape
        turned = cast(F32, cv2.warpAffine(ref.centred, affine(p.shape, GRID_OFFSET_DEG, 1.0, (0.0, 0.0)), (w, h),
                                          flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0.0))
        polar = spectral.log_polar_magnitude(spectral.spectrum(turned, p.window), lp)
        cross2 = spectral.normalized_cross(spectral.descriptor_spectrum(polar, taper), mov_desc, overwrite_a=True)
        surface2 = spectral.pomf(cross2, (lp.map_x.shape[0], n_cols))
        peak2 = spectral.find_peak(surface2, k, col_limit, cross2)
        angle2 = angle + (GRID_OFFSET_DEG - peak2.row * lp.deg_per_bin - angle + 90.0) % 180.0 - 90.0
        if abs(angle2 - angle) < GRID_BIAS_DEG:  # the same peak, seen away from the imprint
            peak, surface, cross = peak2, surface2, cross2
            angle, scale = angle2, math.exp(-peak2.col * lp.log_step)
    return peak, surface, cross, angle, scale


def _warped_spectrum(ref: Prepared, p: Plan, angle: float, scale: float,
                     shift: tuple[float, float] = (0.0, 0.0)) -> NDArray[np.complex64]:
    """Step 7: the windowed spectrum of the reference re-rotated, re-scaled (and shifted) onto ``moving``.

    Pixels from outside the reference get its mean (0 in ``ref.centred``), which the spectrum's mean
    removal keeps near zero: they add nothing to the POMF (a mirrored border adds texture that matches nothing,
    and lowered the PNR of large shifts).
    """
    h, w = p.shape
    warped = cast(F32, cv2.warpAffine(ref.centred, affine(p.shape, angle, scale, shift), (w, h),
                                      flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0.0))
    return spectral.spectrum(warped, p.window)


def _coarse_affine(p: Plan, angle: float, scale: float) -> F64:
    """The (2, 3) :func:`affine` (no shift) in the coarse image's pixels: ``G A G^-1`` for the grid map ``G``."""
    h, w = p.shape
    sx, sy, ox, oy = p.coarse_grid
    theta = math.radians(angle)
    alpha, beta = math.cos(theta) * scale, math.sin(theta) * scale
    tx = (1.0 - alpha) * ((w - 1) / 2.0) - beta * ((h - 1) / 2.0)
    ty = beta * ((w - 1) / 2.0) + (1.0 - alpha) * ((h - 1) / 2.0)
    b01, b10 = beta * sx / sy, -beta * sy / sx  # the linear part, conjugated by the grid's scaling
    return np.array([[alpha, b01, sx * tx + ox - (alpha * ox + b01 * oy)],
                     [b10, alpha, sy * ty + oy - (b10 * ox + alpha * oy)]])


def _coarse_translation(ref: Prepared, mov: Prepared, p: Plan, config: IfmiConfig, rs: spectral.Peak,
                        rs_surface: F32, rs_cross: NDArray[np.complex64], angle: float, scale: float
                        ) -> list[_Candidate]:
    """Steps 7-9 on the coarse images for the rotation/scale estimate at ``angle`` and ``angle + 180``.

    Both half turns share one warp and one FFT (a half turn conjugates the spectrum and shifts
    its phase), on images downsampled ``COARSE`` times: the decision and a shift good to a pixel
    or two need no more, at a ``COARSE**2``-th of the cost. When the full band does not tell
    them apart, each one's PNR is that of its first band to reach ``min_pnr``
    (:func:`spectral.band_peak`). Returns the stronger first, and the other too when their PNRs
    are within :data:`FLIP_AMBIGUITY` (textured pairs: 6 to 50 apart).
    """
    hc, wc = p.coarse_shape
    assert ref.coarse is not None and mov.coarse_phase is not None  # register_prepared checked the roles
    warped = cast(F32, cv2.warpAffine(ref.coarse, _coarse_affine(p, angle, scale), (wc, hc), flags=cv2.INTER_LINEAR,
                                      borderMode=cv2.BORDER_CONSTANT, borderValue=0.0))
    phase = spectral.phase_only(spectral.spectrum(warped, p.coarse_window))
    k = config.peak_neighbourhood
    # The half-turned hypothesis: conj(conj(phase) / coarse_turn) * moving = phase * moving * coarse_turn.
    turned = phase * mov.coarse_phase
    turned *= p.coarse_turn
    crosses = [spectral.cross_phase(phase, mov.coarse_phase), turned]
    surfaces = [spectral.pomf(c, p.coarse_shape) for c in crosses]
    peaks = [spectral.find_peak(sf, k) for sf in surfaces]
    if min(pk.pnr for pk in peaks) * FLIP_AMBIGUITY > max(pk.pnr for pk in peaks) or max(
            pk.pnr for pk in peaks) < config.min_pnr:  # not told apart in the full band: read the lower bands
        peaks = [spectral.band_peak(c, p.coarse_shape, k, config.min_pnr, pk, sf, refine=False)[0]
                 for c, pk, sf in zip(crosses, peaks, surfaces, strict=True)]
    out = []
    for flipped, peak in zip((False, True), peaks, strict=True):
        shift = (peak.col / p.coarse_grid[0], peak.row / p.coarse_grid[1])
        out.append((peak.pnr, _Candidate(rs, rs_surface, rs_cross, angle + 180.0 if flipped else angle, scale, shift)))
    out.sort(key=lambda pc: -pc[0])
    (p0, c0), (p1, c1) = out
    return [c0, c1] if p1 * FLIP_AMBIGUITY > p0 else [c0]


def _translation_pass(ref: Prepared, mov: Prepared, p: Plan, config: IfmiConfig, cand: _Candidate) -> _Result:
    """Steps 7-9 at full resolution with the reference warped by the candidate, its coarse shift rounded.

    The shift is whole pixels: a bilinear warp by a constant fraction of a pixel shifts the
    phase of the spectrum non-linearly and would bias the estimate. The residual shift is then
    within about a pixel, where the subpixel estimate is unbiased, and both windows see the same
    content, so the PNR measures the match rather than the overlap lost to the window. The
    peak is that of the finest band from ``config.translation_band`` on whose PNR reaches
    ``min_pnr`` (:func:`spectral.band_peak`).
    """
    cx, cy = cand.coarse_shift
    whole = (float(round(cx)), float(round(cy))) if config.refine_translation else (0.0, 0.0)
    assert mov.spectrum is not None  # register_prepared checked the roles
    warped = _warped_spectrum(ref, p, cand.angle, cand.scale, whole)
    centroid = None
    if config.covariance == "calibrated" and config.lever == "content":
        centroid = _match_centroid(warped, mov.spectrum, p.shape, config.translation_band)
    cross = spectral.normalized_cross(warped, mov.spectrum, overwrite_a=True)
    peak, band, surface = spectral.band_peak(cross, p.shape, config.peak_neighbourhood, config.min_pnr,
                                             min_band=config.translation_band)
    return _Result(cand, whole, surface, peak, band, centroid)


def _match_centroid(warped: NDArray[np.complex64], moving: NDArray[np.complex64], shape: tuple[int, int],
                    band: int) -> tuple[float, float]:
    """Where the translation POMF's match lies: the centroid of ``max(a b, 0)``, ``a`` and ``b`` the whitened
    (phase-only) images of the reference warped onto ``moving`` and of ``moving``, in band ``band``.

    The POMF's value at the shift is ``sum_x a(x) b(x)``: each place adds ``a b``, so a displacement
    field moves the peak by its average under that weight. A uniform texture spreads it over the
    overlap (centroid: the overlap's centre); a scene of a few edges puts it on them.
    """
    b = min(band, spectral.bands(shape)[-1])
    sub = (shape[0] // b, shape[1] // b)
    wa = spectral.pomf(spectral.low_band(spectral.phase_only(warped.copy()), shape, b), sub)
    wb = spectral.pomf(spectral.low_band(spectral.phase_only(moving.copy()), shape, b), sub)
    w = np.maximum(wa * wb, 0.0)
    total = float(w.sum())
    if not total > 0.0:
        return (0.0, 0.0)
    ys = np.arange(sub[0], dtype=np.float64) * b - (shape[0] - 1) / 2.0
    xs = np.arange(sub[1], dtype=np.float64) * b - (shape[1] - 1) / 2.0
    return (float(w.sum(axis=0) @ xs) / total, float(w.sum(axis=1) @ ys) / total)


def _log_surface(observer: Observer, path: str, surface: F32, peak: spectral.Peak, band: int = 1) -> None:
    """A POMF surface (of band ``band``: one cell per ``band`` pixels), fftshifted so zero shift is at the centre,
    with its peak marked."""
    rows, cols = surface.shape
    # Drawn on a log scale (decades below the peak, floored at 1e-4): the matched filter's Dirac
    # is one bright pixel on a linear scale, and the noise floor that the PNR measures is invisible.
    mag = np.abs(np.fft.fftshift(surface)).astype(np.float32)
    observer.log(path, Image(np.log10(np.maximum(mag, 1e-4 * float(mag.max()) + 1e-30))))
    observer.log(f"{path}/peak", Points(np.array([[peak.col / band + cols // 2, peak.row / band + rows // 2]]),
                                        radius=4.0))


class SequentialRegistrar:
    """The sequential mode of [1]_, section IV-C: each image's spectra are computed once.

    ``step(image)`` registers the previous image (reference) onto ``image`` (moving) and keeps
    ``image``'s spectra for the next pair, so a pair costs one image's steps 1-4 instead of two.
    """

    def __init__(self, config: IfmiConfig = DEFAULT_CONFIG) -> None:
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
        if previous.centred.shape != current.centred.shape:
            self.previous = previous
            raise ValueError(f"image has shape {current.centred.shape} but the previous image has "
                             f"{previous.centred.shape}: a sequence must keep one size")
        return register_prepared(previous, current, self.config, observer)
