"""Spectral building blocks of iFMI registration: windows, spectra, the magnitude high-pass,
log-polar resampling, the phase-only matched filter (POMF), subpixel peaks and the peak
statistics of section II-B of [1]_.

All arrays are float32/complex64 for speed; statistics are accumulated in float64.
Image axes are (row, column) = (y, x), x to the right and y down, as in OpenCV.

References
----------
.. [1] M. Pfingsthorn, A. Birk, S. Schwertfeger, H. Bülow, K. Pathak, "Maximum Likelihood
   Mapping with Spectral Image Registration", ICRA 2010.
.. [2] B. S. Reddy, B. N. Chatterji, "An FFT-based technique for translation, rotation and
   scale-invariant image registration", IEEE TIP 5(8), 1996 (the magnitude high-pass).
.. [3] H. Foroosh, J. B. Zerubia, M. Berthod, "Extension of phase correlation to subpixel
   registration", IEEE TIP 11(3), 2002 (the sinc-peak subpixel estimate).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
import scipy.fft as sfft
from numpy.typing import NDArray

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


def highpass(shape: tuple[int, int]) -> F32:
    """Reddy-Chatterji high-pass ``(1 - X)(2 - X)``, ``X = cos(pi fx) cos(pi fy)`` [2]_, on the rfft grid.

    Shape ``(H, W // 2 + 1)``, rows in fftshifted order (zero frequency at row ``H // 2``).
    """
    h, w = shape
    fy = np.fft.fftshift(np.fft.fftfreq(h))
    fx = np.fft.rfftfreq(w)
    x = np.cos(np.pi * fy)[:, None] * np.cos(np.pi * fx)[None, :]
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
    deg_per_bin: float
    log_step: float  # ln(scale) per radius bin


def log_polar_map(shape: tuple[int, int], n_angle: int, n_radius: int, r_min_cycles: float) -> LogPolarMap:
    """Maps for :func:`cv2.remap` from the fftshifted rfft magnitude to a log-polar descriptor.

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
    return LogPolarMap((fx * w).astype(np.float32), (fy * h + h // 2).astype(np.float32),
                       180.0 / n_angle, log_step)


def spectrum(image: F32, window: F32) -> C64:
    """rfft2 of the windowed, mean-free image (step 1 of the POMF)."""
    mean = cv2.mean(image)[0]
    return sfft.rfft2(cv2.multiply(cv2.subtract(image, mean, dtype=cv2.CV_32F), window), workers=1)


def phase_only(spec: C64) -> C64:
    """``F / |F|``: the phase of a spectrum (zero where the spectrum is zero).

    The POMF's normalized cross spectrum is the product of two of these (step 2 of the POMF),
    so each image's phase is computed once and reused (the sequential mode).
    """
    mag = np.abs(spec)
    np.maximum(mag, np.float32(1e-30), out=mag)
    np.reciprocal(mag, out=mag)
    return spec * mag.astype(np.complex64)


def magnitude_descriptor(spec: C64, hp: F32, lp: LogPolarMap, radius_window: F32) -> C64:
    """Steps 2-4 and the phase of the FMI descriptor's spectrum: |F|, high-pass, log-polar, rfft2.

    Returns the phase-only rfft2 of the mean-free log-polar descriptor, tapered along the
    (non-cyclic) radius axis, ready for the rotation/scale POMF (step 5).
    """
    mag = np.fft.fftshift(np.abs(spec), axes=0)
    mag *= hp
    desc = cv2.remap(mag, lp.map_x, lp.map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0.0)
    desc -= np.float32(cv2.mean(desc)[0])
    desc *= radius_window
    return phase_only(sfft.rfft2(desc, workers=1))


def cross_phase(phase_a: C64, phase_b: C64) -> C64:
    """The normalized cross spectrum ``B A* / |B A*|`` from two phase-only spectra (POMF steps 1-2)."""
    return phase_b * np.conj(phase_a)


def pomf(cross: C64, shape: tuple[int, int]) -> F32:
    """Phase-only matched filter surface: the inverse FFT of the normalized cross spectrum (POMF step 3).

    A Dirac at ``t`` when ``b(x) = a(x - t)`` (eq. 2); by Parseval its squares sum to ~1.
    """
    return sfft.irfft2(cross, s=shape, workers=1)


def shift_spectrum(spec: C64, shape: tuple[int, int], dy: float, dx: float) -> C64:
    """The rfft2 of the image shifted by ``(dy, dx)`` (cyclically, with subpixel exactness)."""
    h, w = shape
    ky = np.fft.fftfreq(h).astype(np.float32)[:, None]
    kx = np.fft.rfftfreq(w).astype(np.float32)[None, :]
    return spec * np.exp(np.complex64(-2j * np.pi) * (ky * np.float32(dy) + kx * np.float32(dx)))


def _sinc_offset(c_minus: float, c0: float, c_plus: float) -> float:
    """Subpixel offset of a Dirichlet (sinc) peak from three samples [3]_: ``c1 / (c1 + c0)`` toward the larger side."""
    if c_plus >= c_minus:
        d = c_plus / (c_plus + c0) if c_plus + c0 > 0 else 0.0
    else:
        d = -c_minus / (c_minus + c0) if c_minus + c0 > 0 else 0.0
    return float(min(0.5, max(-0.5, d)))


def refine_peak(cross: C64, shape: tuple[int, int], row: float, col: float, iterations: int = 3
                ) -> tuple[float, float]:
    """Subpixel maximum of the POMF near ``(row, col)``: Newton steps on its trigonometric interpolant.

    The POMF is a trigonometric polynomial, ``v(y, x) = (1/N) Re sum_k c_k R_k exp(2 pi i (f_y y + f_x x))``
    over the rfft half-plane (``c_k`` = 2 for columns that stand for a conjugate pair); its value,
    gradient and Hessian at any off-grid point cost three matrix-vector products (the
    matrix-multiply DFT of upsampled-DFT registration, evaluated only where needed). Steps are
    clipped to half a bin and stop when the Hessian is not negative definite, so the estimate
    never leaves the peak found on the grid.
    """
    h, w = shape
    fy = 2.0 * np.pi * np.fft.fftfreq(h)
    fx = 2j * np.pi * np.fft.rfftfreq(w)
    weights = np.full(fx.shape, 2.0)
    weights[0] = 1.0
    if w % 2 == 0:
        weights[-1] = 1.0
    # Real arithmetic without BLAS: a threaded BLAS matrix-vector product took ms on a busy machine.
    re, im = np.ascontiguousarray(cross.real), np.ascontiguousarray(cross.imag)
    y, x = float(row), float(col)
    for _ in range(iterations):
        c, s = np.cos(fy * y), np.sin(fy * y)
        # Rows of (ey, i fy ey, -fy^2 ey) split into real and imaginary parts, ey = exp(i fy y).
        er = np.stack([c, -fy * s, -fy * fy * c]).astype(np.float32)
        ei = np.stack([s, fy * c, -fy * fy * s]).astype(np.float32)
        a = (np.einsum("ki,ij->kj", er, re) - np.einsum("ki,ij->kj", ei, im)
             + 1j * (np.einsum("ki,ij->kj", er, im) + np.einsum("ki,ij->kj", ei, re)))
        ex = np.exp(fx * x) * weights
        a0, a1, a2 = a[0], a[1], a[2]
        gy, gx = np.sum(a1 * ex).real, np.sum(a0 * ex * fx).real
        hyy, hxx, hxy = np.sum(a2 * ex).real, np.sum(a0 * ex * fx * fx).real, np.sum(a1 * ex * fx).real
        det = hyy * hxx - hxy * hxy
        if not (hyy < 0.0 and det > 0.0):
            break
        sy = -(hxx * gy - hxy * gx) / det
        sx = -(-hxy * gy + hyy * gx) / det
        y += min(0.5, max(-0.5, sy))
        x += min(0.5, max(-0.5, sx))
        if abs(sy) < 1e-3 and abs(sx) < 1e-3:
            break
    if abs(y - row) > 1.0 or abs(x - col) > 1.0:
        return row, col
    return y, x


@dataclass(frozen=True, slots=True)
class Peak:
    """The Dirac peak of a POMF surface and its section II-B statistics.

    ``row``/``col`` are the subpixel location as signed shifts (cyclic, in bins);
    ``cov`` the 2x2 covariance of eq. (10) over (row, col) in bins^2; ``s`` the peak's
    share of the normalized intensity (eqs. 11-12) and ``pnr = s / (1 - s)`` (eq. 13).
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
        location is refined by :func:`refine_peak` (else the sinc estimate of [3]_ is kept).

    Notes
    -----
    The intensity of a cell is the squared POMF value: by Parseval the normalization of eq. (11)
    is then the POMF's total energy. ``s`` sums the normalized intensity over the K-neighbourhood
    rather than one cell (eq. 12), because a peak at a subpixel position splits between cells:
    a perfect match at a half-pixel shift keeps ~0.16 of the energy per cell, which eq. (12)
    would read as a failure. The covariance of eq. (10) uses the neighbourhood's intensities
    renormalized to a PMF, centered at the subpixel peak, plus 1/12 bin^2 on the diagonal
    (a PMF cell spreads its mass uniformly over one bin: Sheppard's correction).
    """
    rows, cols = surface.shape
    if col_limit is None or 2 * col_limit + 1 >= cols:
        idx = int(np.argmax(surface))
        r0, c0 = divmod(idx, cols)
    else:
        sub = np.concatenate([surface[:, : col_limit + 1], surface[:, cols - col_limit:]], axis=1)
        r0, cc = divmod(int(np.argmax(sub)), sub.shape[1])
        c0 = cc if cc <= col_limit else cols - (sub.shape[1] - cc)
    half = k // 2
    ri = (np.arange(r0 - half, r0 + half + 1)) % rows
    ci = (np.arange(c0 - half, c0 + half + 1)) % cols
    patch = surface[np.ix_(ri, ci)].astype(np.float64)
    centre = patch[half, half]
    dr = _sinc_offset(patch[half - 1, half], centre, patch[half + 1, half])
    dc = _sinc_offset(patch[half, half - 1], centre, patch[half, half + 1])
    if cross is not None:
        y, x = refine_peak(cross, surface.shape, r0 + dr, c0 + dc)  # type: ignore[arg-type]
        dr, dc = y - r0, x - c0
    energy = patch * patch
    flat = surface.ravel()
    total = float(np.einsum("i,i->", flat, flat, dtype=np.float64))
    local = float(energy.sum())
    s = min(local / total, 1.0 - 1e-12) if total > 0 else 0.0
    p = energy / local if local > 0 else np.full_like(energy, 1.0 / energy.size)
    off = np.arange(-half, half + 1, dtype=np.float64)
    yr = off[:, None] - dr
    xc = off[None, :] - dc
    crr = float((p * yr * yr).sum()) + 1.0 / 12.0
    ccc = float((p * xc * xc).sum()) + 1.0 / 12.0
    crc = float((p * yr * xc).sum())
    row = r0 + dr
    col = c0 + dc
    row = row - rows if row > rows / 2 else row
    col = col - cols if col > cols / 2 else col
    return Peak(row, col, ((crr, crc), (crc, ccc)), s, s / (1.0 - s), float(centre))
