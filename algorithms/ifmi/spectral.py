"""Spectral building blocks of iFMI registration: windows, spectra, the magnitude high-pass,
log-polar resampling, the phase-only matched filter (POMF), its bands, subpixel peaks and the
peak statistics of section II-B of [1]_.

All arrays are float32/complex64 for speed (real FFTs through OpenCV's packed DFT, about twice
as fast as pocketfft here); statistics are accumulated in float64.
Image axes are (row, column) = (y, x), x to the right and y down, as in OpenCV.

References
----------
.. [1] M. Pfingsthorn, A. Birk, S. Schwertfeger, H. Bülow, K. Pathak, "Maximum Likelihood
   Mapping with Spectral Image Registration", ICRA 2010.
.. [2] B. S. Reddy, B. N. Chatterji, "An FFT-based technique for translation, rotation and
   scale-invariant image registration", IEEE TIP 5(8), 1996 (the magnitude high-pass).
.. [3] H. Foroosh, J. B. Zerubia, M. Berthod, "Extension of phase correlation to subpixel
   registration", IEEE TIP 11(3), 2002 (the sinc-peak subpixel estimate).
.. [4] K. Takita, T. Aoki, Y. Sasaki, T. Higuchi, K. Kobayashi, "High-accuracy subpixel image
   registration based on phase-only correlation", IEICE Trans. Fundamentals E86-A(8), 2003
   (band-limited phase-only correlation).
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import NamedTuple, cast

import cv2
import numpy as np
from numpy.typing import NDArray

from slamreplay.algorithms.ifmi.fft import irfft2, rfft2

__all__ = ["irfft2", "rfft2"]  # re-exported: the spectra of this module are theirs

F32 = NDArray[np.float32]
C64 = NDArray[np.complex64]
F64 = NDArray[np.float64]


def tukey_window(shape: tuple[int, int], alpha: float = 0.5) -> F32:
    """Elliptical Tukey window (H, W): 1 inside normalized radius ``1 - alpha``, a raised cosine to 0 at 1.

    The radius is normalized by the half-sizes, so the window is circularly symmetric on a
    square image: a rotation of the content does not meet a rotation-dependent window (step 1).
    """
    h, w = shape
    y = (np.arange(h) - (h - 1) / 2.0) / (h / 2.0)
    x = (np.arange(w) - (w - 1) / 2.0) / (w / 2.0)
    r = np.hypot(x[None, :], y[:, None])
    flat = 1.0 - alpha
    taper = 0.5 * (1.0 + np.cos(np.pi * np.clip((r - flat) / max(alpha, 1e-9), 0.0, 1.0)))
    return np.where(r <= flat, 1.0, taper).astype(np.float32)


def highpass(radius_cycles: F64) -> F32:
    """Reddy-Chatterji high-pass ``(1 - X)(2 - X)`` [2]_ with ``X = cos(pi r)``, r in cycles per pixel.

    The radial form of ``X = cos(pi fx) cos(pi fy)`` (equal on the axes): it does not prefer the
    image axes, and on the log-polar grid it is one weight per radius column, applied for free
    with the radius taper.
    """
    x = np.cos(np.pi * np.asarray(radius_cycles, dtype=np.float64))
    return ((1.0 - x) * (2.0 - x)).astype(np.float32)


@dataclass(frozen=True, slots=True, eq=False)
class LogPolarMap:
    """Sampling maps of the log-polar resampling (steps 3-4).

    Row ``k`` of the descriptor is the spectrum direction ``phi_k = -pi/2 + k pi / n_angle``
    (the magnitude spectrum is point-symmetric, so ``[-pi/2, pi/2)`` covers every direction
    once and the axis is cyclic); column ``j`` is the radius ``r_j = r_min exp(j log_step)``
    in cycles per pixel.
    """

    map_x: F32  # (n_angle, n_radius) column in the rfft magnitude
    map_y: F32  # (n_angle, n_radius) row in the row-fftshifted rfft magnitude
    radius_cycles: F64  # (n_radius,) r_j, cycles per pixel
    deg_per_bin: float
    log_step: float  # ln(scale) per radius bin


def log_polar_map(shape: tuple[int, int], n_angle: int, n_radius: int, r_min_cycles: float) -> LogPolarMap:
    """Maps for :func:`cv2.remap` from the row-fftshifted rfft magnitude to a log-polar descriptor.

    Frequencies are in cycles per pixel on both axes, so non-square images resample correctly.
    ``r_min_cycles`` is the lowest radius, in cycles per image (of the smaller side).
    """
    h, w = shape
    r_min = r_min_cycles / min(h, w)
    r_max = 0.5 * (1.0 - 2.0 / min(h, w))  # stay one bin inside Nyquist: no wrap in the rfft columns
    log_step = math.log(r_max / r_min) / (n_radius - 1)
    phi = -0.5 * np.pi + np.pi * np.arange(n_angle) / n_angle
    r = r_min * np.exp(log_step * np.arange(n_radius))
    fx = np.cos(phi)[:, None] * r[None, :]
    fy = np.sin(phi)[:, None] * r[None, :]
    return LogPolarMap((fx * w).astype(np.float32), (fy * h + h // 2).astype(np.float32), r, 180.0 / n_angle,
                       log_step)


def spectrum(image: F32, window: F32) -> C64:
    """rfft2 of the windowed, mean-free image (step 1 of the POMF), made in place: ``image`` is a float32 temporary."""
    image -= np.float32(cv2.mean(image)[0])  # in place: faster than two cv2 calls or a new array
    image *= window
    return rfft2(image)


TINY = np.float32(1e-30)  # added to a magnitude before dividing by it: a zero keeps phase 0


def phase_only(spec: C64) -> C64:
    """``F / |F|``: the phase of a spectrum (zero where the spectrum is zero), in place: returns ``spec``.

    The coarse pass's normalized cross spectra are products of two of these (step 2 of the
    POMF): the moving image's coarse phase is computed once, for both half turns and, in the
    sequential mode, for every pair it is in.
    """
    inv = np.abs(spec)
    inv += TINY  # 1 / (|F| + TINY): 5x faster than np.maximum(|F|, TINY) here
    np.divide(np.float32(1.0), inv, out=inv)
    spec *= inv  # (complex64 * float32 -> complex64)
    return spec


def normalized_cross(spec_a: C64, spec_b: C64, overwrite_a: bool = False) -> C64:
    """The normalized cross spectrum ``B A* / |B A*|`` of two spectra (POMF steps 1-2).

    Equal to the product of their phases (:func:`cross_phase`), for one normalization instead of
    two: the descriptors and the full-resolution translation POMF take this path. With
    ``overwrite_a`` (a temporary ``spec_a``) the result is made in ``spec_a``.
    """
    cross = np.conjugate(spec_a, out=spec_a) if overwrite_a else np.conjugate(spec_a)
    cross *= spec_b
    inv = np.abs(cross)
    inv += TINY
    np.divide(np.float32(1.0), inv, out=inv)
    cross *= inv
    return cross


def log_polar_magnitude(spec: C64, lp: LogPolarMap) -> F32:
    """Steps 2-4: the magnitude of an rfft2 resampled on the log-polar grid, (n_angle, n_radius).

    (An fftshift and a constant border remap 4x faster than ``BORDER_WRAP`` on the unshifted rows.)
    """
    h = spec.shape[0]
    mid = (h + 1) // 2  # row 0 goes to h // 2, as np.fft.fftshift puts it
    mag = np.empty(spec.shape, np.float32)
    np.abs(spec[:mid], out=mag[h - mid:])
    np.abs(spec[mid:], out=mag[:h - mid])
    return cast(F32, cv2.remap(mag, lp.map_x, lp.map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT,
                               borderValue=0.0))


@dataclass(frozen=True, slots=True, eq=False)
class RadiusTaper:
    """The column weights of an FMI descriptor made of the first ``n`` log-polar radius columns."""

    weight: F32  # (1, n) the magnitude high-pass at each radius (:func:`highpass`) times the taper
    inv_taper: F32  # (n,) 1 / taper (a Hann window, nowhere zero) / n
    taper_rfft: C64  # (n // 2 + 1,) rfft of the taper


def radius_taper(radius_weight: F32, taper: F32) -> RadiusTaper:
    """:class:`RadiusTaper` from the high-pass ``radius_weight`` (1, n) and the radius ``taper`` (1, n)."""
    t = np.asarray(taper, dtype=np.float64).ravel()
    return RadiusTaper((radius_weight * taper).astype(np.float32), (1.0 / (t * t.size)).astype(np.float32),
                       np.fft.rfft(t).astype(np.complex64))


def descriptor_spectrum(polar: F32, taper: RadiusTaper) -> C64:
    """The FMI descriptor's spectrum from the first ``n`` radius columns (``taper`` of :func:`radius_taper`).

    The descriptor is the high-passed log-polar magnitude, made mean-free and then tapered
    along the (non-cyclic) radius axis; returns its rfft2, for the rotation/scale POMF (step 5,
    :func:`normalized_cross`). The mean times the taper is the same in every row, so its
    spectrum is the taper's rfft in row ``ky = 0``: it is subtracted there, after one pass over
    the descriptor (the column sums give the mean, the taper divided out).
    """
    desc = polar[:, : taper.weight.shape[1]] * taper.weight
    col_sums = cv2.reduce(desc, 0, cv2.REDUCE_SUM)  # (1, n) sums over the angles of polar * high-pass * taper
    spec = rfft2(desc)
    spec[0] -= taper.taper_rfft * float(col_sums[0] @ taper.inv_taper)  # rows * mean * rfft(taper)
    return spec


def cross_phase(phase_a: C64, phase_b: C64) -> C64:
    """The normalized cross spectrum ``B A* / |B A*|`` from two phase-only spectra (POMF steps 1-2)."""
    cross = np.conjugate(phase_a)
    cross *= phase_b
    return cross


def pomf(cross: C64, shape: tuple[int, int]) -> F32:
    """Phase-only matched filter surface: the inverse FFT of the normalized cross spectrum (POMF step 3).

    A Dirac at ``t`` when ``b(x) = a(x - t)`` (eq. 2); by Parseval its squares sum to ~1.
    """
    return irfft2(cross, shape)


def low_band(spec: C64, shape: tuple[int, int], factor: int) -> C64:
    """The part of an (H, W) rfft half-plane that is the rfft half-plane of a ``factor`` times coarser grid.

    Its inverse (:func:`irfft2` at ``(H // factor, W // factor)``) is the band-limited POMF sampled
    every ``factor`` pixels: the same Dirac, a ``factor``-th of the size, at a ``factor**2``-th of the cost.
    """
    h, w = shape
    hc, wc = h // factor, w // factor
    pos, cols = hc // 2 + 1, wc // 2 + 1
    neg = hc - pos
    return np.concatenate([spec[:pos, :cols], spec[h - neg:, :cols]]) if neg else spec[:pos, :cols].copy()


MIN_BAND_SIDE = 48  # cells per side of the coarsest band's POMF: a random K-neighbourhood stays far below eq. 13's 0.2


@functools.lru_cache(maxsize=16)
def bands(shape: tuple[int, int]) -> tuple[int, ...]:
    """The band factors 1, 2, 4, ... whose POMF keeps at least :data:`MIN_BAND_SIDE` cells per side."""
    out, b = [1], 2
    while min(shape) // b >= MIN_BAND_SIDE:
        out.append(b)
        b *= 2
    return tuple(out)


def band_peak(cross: C64, shape: tuple[int, int], k: int, min_pnr: float, full: Peak | None = None,
              surface: F32 | None = None, refine: bool = True, min_band: int = 1) -> tuple[Peak, int, F32]:
    """The POMF's Dirac in the finest band where eq. (13) reaches ``min_pnr``, else in the band where it is largest.

    Eqs. (11)-(13) read the Dirac's share of the whole POMF, and the phase-only spectrum gives
    every frequency the same weight: where a band holds only noise (sensor noise, blur, the
    low texture of mud) its frequencies add their energy everywhere and the share falls,
    although the peak is where it belongs. The POMF of the lower frequencies alone (the
    band-limited phase-only correlation of Takita et al. [4]_, :func:`low_band`, sampled every
    ``b`` pixels) still holds the Dirac at the same place; a band keeps at least
    :data:`MIN_BAND_SIDE` cells per side, so chance alignments stay far below the threshold
    (non-overlapping pairs: 100 % rejected). Returns the peak in pixels of the full grid (its
    location refined on the band's trigonometric interpolant, :func:`refine_peak`, unless
    ``refine`` is False; the covariance of eq. (10) scaled by ``b**2``), the band ``b`` and its
    surface.

    ``min_band`` leaves the finer bands out (``IfmiConfig.translation_band``): the search starts at
    the first band ``b >= min_band`` (at the coarsest band when the image has none that coarse).
    ``full`` and ``surface``, the full band's peak and POMF, save a transform when band 1 is searched.
    """
    usable = [b for b in bands(shape) if b >= min_band] or [bands(shape)[-1]]
    best: tuple[Peak, int, F32] | None = None
    for b in usable:
        if best is not None and best[0].pnr >= min_pnr:
            break
        if b == 1:
            if full is None or surface is None:
                surface = pomf(cross, shape)
                full = find_peak(surface, k)
            candidate = (full, 1, surface)
        else:
            sub_shape = (shape[0] // b, shape[1] // b)
            sub_cross = low_band(cross, shape, b)
            sub = pomf(sub_cross, sub_shape)
            peak = find_peak(sub, k, cross=sub_cross if refine else None)
            (crr, crc), (_, ccc) = peak.cov
            candidate = (Peak(b * peak.row, b * peak.col, ((b * b * crr, b * b * crc), (b * b * crc, b * b * ccc)),
                              peak.s, peak.pnr, peak.value), b, sub)
        if best is None or candidate[0].pnr > best[0].pnr:
            best = candidate
    assert best is not None  # usable is never empty
    return best


def _parabola_offset(c_minus: float, c0: float, c_plus: float) -> float:
    """Vertex of the parabola through three samples: the start of :func:`refine_peak` (~0.06 bin on FMI peaks)."""
    d = c_minus - 2.0 * c0 + c_plus
    if not d < 0:
        return 0.0
    off = 0.5 * (c_minus - c_plus) / d
    return 0.5 if off > 0.5 else -0.5 if off < -0.5 else off


def _sinc_offset(c_minus: float, c0: float, c_plus: float) -> float:
    """Subpixel offset of a Dirichlet (sinc) peak from three samples [3]_: ``c1 / (c1 + c0)`` toward the larger side."""
    if c_plus >= c_minus:
        d = c_plus / (c_plus + c0) if c_plus + c0 > 0 else 0.0
    else:
        d = -c_minus / (c_minus + c0) if c_minus + c0 > 0 else 0.0
    return 0.5 if d > 0.5 else -0.5 if d < -0.5 else d


BLAS_SERIAL_MACS = 1 << 18  # OpenBLAS runs a product below 4 * 65536 multiply-adds on the calling thread


@dataclass(frozen=True, slots=True, eq=False)
class _TrigAxes:
    """What :func:`refine_peak` needs of an (H, W) rfft half-plane's frequencies, computed once per shape."""

    iy: NDArray[np.complex128]  # (H,) 2 pi i f_y of every row
    ix: NDArray[np.complex128]  # (W',) 2 pi i f_x of every column
    dy: NDArray[np.complex128]  # (3, H) (1, iy, iy^2): the y derivatives
    dx: NDArray[np.complex128]  # (3, W') c_k (1, ix, ix^2): column weight times the x derivatives
    blocks: tuple[slice, ...]  # row blocks of the (H, W') x (W', 3) product, each one serial in BLAS


@functools.lru_cache(maxsize=16)
def _trig_axes(shape: tuple[int, int]) -> _TrigAxes:
    """Angular frequencies of an (H, W) rfft half-plane and the column weights of its real interpolant."""
    h, w = shape
    weights = np.full(w // 2 + 1, 2.0)
    weights[0] = 1.0
    if w % 2 == 0:
        weights[-1] = 1.0
    iy = np.asarray(2j * np.pi * np.fft.fftfreq(h), dtype=np.complex128)
    ix = np.asarray(2j * np.pi * np.fft.rfftfreq(w), dtype=np.complex128)
    rows = max(1, BLAS_SERIAL_MACS // (3 * (w // 2 + 1)) - 1)
    n_blocks = -(-h // rows)
    step = -(-h // n_blocks)  # equal blocks
    blocks = tuple(slice(i, min(h, i + step)) for i in range(0, h, step))
    return _TrigAxes(iy, ix, np.stack([np.ones(h), iy, iy * iy]), np.stack([weights, weights * ix, weights * ix * ix]),
                     blocks)


def refine_peak(cross: C64, shape: tuple[int, int], row: float, col: float, iterations: int = 3
                ) -> tuple[float, float]:
    """Subpixel maximum of the POMF near ``(row, col)``: Newton steps on its trigonometric interpolant.

    The POMF is a trigonometric polynomial, ``v(y, x) = (1/N) Re sum_k c_k R_k exp(2 pi i (f_y y + f_x x))``
    over the rfft half-plane (``c_k`` = 2 for columns that stand for a conjugate pair); its value,
    gradient and Hessian at any off-grid point cost one (H, W') x (W', 3) product (the
    matrix-multiply DFT of upsampled-DFT registration, evaluated only where needed): the x
    derivatives of order 0-2 summed over the columns, then the y ones over the rows. Steps are
    clipped to half a bin and stop when the Hessian is not negative definite, so the estimate
    never leaves the peak found on the grid. From a start within ~0.1 bin (the parabolic
    estimate of :func:`find_peak`) one step leaves < 0.01 bin (Newton converges quadratically).
    """
    ax = _trig_axes(shape)
    spec = np.asarray(cross, dtype=np.complex64)
    y, x = float(row), float(col)
    for _ in range(iterations):
        # Row blocks small enough that OpenBLAS keeps each on this thread (a threaded product of
        # this size took milliseconds on a busy machine).
        cols = (ax.dx * np.exp(ax.ix * x)).astype(np.complex64).T  # (W', 3), phases in float64
        by_row = spec @ cols if len(ax.blocks) == 1 else np.concatenate([spec[b] @ cols for b in ax.blocks])
        g = ((ax.dy * np.exp(ax.iy * y)).astype(np.complex64) @ by_row).real  # g[i, j] = N d^i/dy^i d^j/dx^j v
        gy, gx, hyy, hxx, hxy = float(g[1, 0]), float(g[0, 1]), float(g[2, 0]), float(g[0, 2]), float(g[1, 1])
        det = hyy * hxx - hxy * hxy
        if not (hyy < 0.0 and det > 0.0):
            break
        sy = -(hxx * gy - hxy * gx) / det
        sx = -(-hxy * gy + hyy * gx) / det
        y += min(0.5, max(-0.5, sy))
        x += min(0.5, max(-0.5, sx))
        if abs(sy) < 0.1 and abs(sx) < 0.1:  # quadratic convergence: what is left is < 0.01 bin
            break
    if abs(y - row) > 1.0 or abs(x - col) > 1.0:
        return row, col
    return float(y), float(x)


class Peak(NamedTuple):
    """The Dirac peak of a POMF surface and its section II-B statistics.

    ``row``/``col`` are the subpixel location as signed shifts (cyclic, in bins);
    ``cov`` the 2x2 covariance of eq. (10) over (row, col) in bins^2; ``s`` the peak's
    share of the normalized intensity (eqs. 11-12) and ``pnr = s / (1 - s)`` (eq. 13).
    (A named tuple: built several times per registration, faster than a frozen dataclass.)
    """

    row: float
    col: float
    cov: tuple[tuple[float, float], tuple[float, float]]
    s: float
    pnr: float
    value: float  # POMF value at the integer maximum


def find_peak(surface: F32, k: int, col_limit: int | None = None, cross: C64 | None = None) -> Peak:
    """Locate the Dirac peak and compute eqs. (10)-(13) on its ``k x k`` neighbourhood.

    Parameters
    ----------
    surface : (R, C) POMF, cyclic on both axes (a DFT result).
    k : odd neighbourhood size K of eq. (10).
    col_limit : search only columns with |shift| <= col_limit (the log-radius range of the
        allowed scales); None searches everything.
    cross : the normalized cross spectrum the surface came from; when given, the subpixel
        location is the parabolic estimate refined by :func:`refine_peak` (the rotation/scale
        peak, smeared by the resampling); else the sinc estimate of [3]_, exact for the
        Dirichlet peak of a translation.

    Notes
    -----
    The intensity of a cell is the squared POMF value: by Parseval the normalization of eq. (11)
    is then the POMF's total energy. ``s`` sums the normalized intensity over the K-neighbourhood
    rather than one cell (eq. 12), because a peak at a subpixel position splits between cells:
    a perfect match at a half-pixel shift keeps ~0.16 of the energy per cell, which eq. (12)
    would read as a failure. The covariance of eq. (10) uses the neighbourhood's intensities
    renormalized to a PMF, centered at the subpixel peak, plus 1/12 bin^2 on the diagonal
    (a PMF cell spreads its mass uniformly over one bin: Sheppard's correction). On
    low-texture or noisy images the K-neighbourhood is not what fails (K = 5 holds a clean
    peak's energy): the frequencies that hold only noise spread their energy over the whole
    surface; :func:`band_peak` reads eqs. (11)-(13) in a lower band then.
    """
    rows, cols = surface.shape
    if col_limit is None or 2 * col_limit + 1 >= cols:
        c0, r0 = cv2.minMaxLoc(surface)[3]
    else:
        _, high, _, (c0, r0) = cv2.minMaxLoc(surface[:, : col_limit + 1])  # views: no copy
        _, high_neg, _, (cn, rn) = cv2.minMaxLoc(surface[:, cols - col_limit:])
        if high_neg > high:
            c0, r0 = cols - col_limit + cn, rn
    half = k // 2
    # Python floats (float64) from here: a K x K neighbourhood is faster in plain Python than in NumPy calls.
    if half <= r0 < rows - half and half <= c0 < cols - half:
        cells: list[list[float]] = surface[r0 - half:r0 + half + 1, c0 - half:c0 + half + 1].tolist()
    else:  # the neighbourhood wraps around the cyclic surface (the translation peak, near 0, always does):
        # element by element, 5 % of a registration faster than fancy indexing with take(mode="wrap")
        item = surface.item
        wrapped = [(c0 + d) % cols for d in range(-half, half + 1)]
        cells = [[item(r, c) for c in wrapped] for r in [(r0 + d) % rows for d in range(-half, half + 1)]]
    centre = cells[half][half]
    up, down, left, right = cells[half - 1][half], cells[half + 1][half], cells[half][half - 1], cells[half][half + 1]
    if cross is None:
        dr, dc = _sinc_offset(up, centre, down), _sinc_offset(left, centre, right)
    else:
        dr, dc = _parabola_offset(up, centre, down), _parabola_offset(left, centre, right)
        y, x = refine_peak(cross, (rows, cols), r0 + dr, c0 + dc)
        dr, dc = y - r0, x - c0
    total = float(cv2.norm(surface, cv2.NORM_L2SQR))  # accumulated in float64
    # Intensities and their moments about the subpixel peak in one loop (a PMF after dividing by their sum).
    local = m_rr = m_cc = m_rc = 0.0
    for i, line in enumerate(cells):
        dy = i - half - dr
        row_sum = row_x = 0.0
        for j, v in enumerate(line):
            dx = j - half - dc
            e = v * v
            row_sum += e
            row_x += e * dx
            m_cc += e * dx * dx
        local += row_sum
        m_rr += row_sum * dy * dy
        m_rc += row_x * dy
    s = min(local / total, 1.0 - 1e-12) if total > 0 else 0.0
    if local > 0:
        crr, ccc, crc = m_rr / local + 1.0 / 12.0, m_cc / local + 1.0 / 12.0, m_rc / local
    else:  # no energy: a uniform PMF
        d2r = sum((i - half - dr) ** 2 for i in range(k)) / k
        d2c = sum((j - half - dc) ** 2 for j in range(k)) / k
        crc = sum(i - half - dr for i in range(k)) * sum(j - half - dc for j in range(k)) / (k * k)
        crr, ccc = d2r + 1.0 / 12.0, d2c + 1.0 / 12.0
    row = r0 + dr
    col = c0 + dc
    row = row - rows if row > rows / 2 else row
    col = col - cols if col > cols / 2 else col
    return Peak(row, col, ((crr, crc), (crc, ccc)), s, s / (1.0 - s), centre)
