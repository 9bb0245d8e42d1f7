"""Registration covariance: the paper's POMF covariance (eq. 10 of [1]_) and a calibrated one.

Eq. (10) reads the covariance off the POMF as if the Dirac's neighbourhood were the probability
mass function of the shift: its second moment is the *width* of the correlation peak, which the
window and the images' spectral extent set (about 0.26 px^2 in the full band, ``b^2`` times that
in band ``b``), whatever the noise. The error of the peak's *location* shrinks with the noise;
on known warps eq. (10) was 10 to 200 times too large (translation NEES 0.005-0.2 where 2 is
calibrated; benchmarks/ifmi_calibration.py).

``calibrated`` (docs/ifmi.md, "Calibrated covariance"):

- Translation: a peak of width ``w`` in a surface whose disturbance-to-peak energy is
  ``1 / PNR`` (eq. 13 is exactly the peak's energy over the rest) is located to
  ``sigma^2 ~ w^2 / (PNR n)``, ``n`` the number of independent disturbance samples that move
  it (a Cramér-Rao argument for a peak of known shape). If the disturbance were white over all
  ``N = H W`` cells of the POMF, ``n = N`` (the phase-residual sandwich,
  :func:`peak_sandwich`, which came out 100-1000 times too optimistic); the disturbances of a
  real pair (noise whitened by the phase-only spectrum, interpolation, illumination, content
  leaving the window) are not white, and measured on procedural images at 128, 256 and 512 px
  ``n`` is the side ``sqrt(H W)`` within a factor 0.7-1.1. Hence
  ``C = C_eq10 / (PNR sqrt(H W))``: no fitted constant.
- Rotation and scale: the log-polar descriptor's POMF is of another kind (a resampled
  magnitude spectrum, its PNR low though its peak is well placed: the formula above gave
  NEES 0.1). Its phase-residual sandwich (:func:`peak_sandwich`) is too small by a factor that
  grows like the square root of the descriptor's side (the log-polar grid oversamples the
  low frequencies, so neighbouring descriptor frequencies are correlated):
  ``C = ROTATION_GAIN sqrt(side) C_sandwich``, ``ROTATION_GAIN`` fitted on procedural images
  (3.7, 5.6, 7.9 at 128, 256, 512 px: 0.33-0.35 sqrt(side)) and validated on held-out Skerki frames.
- The lever (:func:`with_overlap_lever`): the shift is measured where the images overlap, half
  the shift away from the centre about which the first stage's rotation and scale were
  applied, so their errors move it; without this term the translation NEES grew with the
  shift (geometric mean 0.4 below 10 % of the side, 9 at 30-40 %).

Measured (benchmarks/ifmi_calibration.py, 256 px, 7 conditions, 280 pairs per source, docs/ifmi.md),
the translation read in band 2 (``IfmiConfig.translation_band``): translation NEES mean 1.23 on
procedural images and 1.23-1.45 on the held-out Skerki frames (2 is calibrated; clean pairs 2.1-2.4,
noisy ones 0.47-0.94; eq. 10: 0.015-0.017); read in the full band as the paper does, 2.19 and 4.2-4.3.
Rotation 0.87 and 0.75-0.81 (1 is calibrated; eq. 10: 0.011).

References
----------
.. [1] M. Pfingsthorn, A. Birk, S. Schwertfeger, H. Bülow, K. Pathak, "Maximum Likelihood
   Mapping with Spectral Image Registration", ICRA 2010, eqs. (10)-(13).
"""

from __future__ import annotations

import functools
import math

import numpy as np
from numpy.typing import NDArray

C64 = NDArray[np.complex64]
F64 = NDArray[np.float64]
Cov2 = tuple[tuple[float, float], tuple[float, float]]

COVARIANCES = ("paper", "calibrated")  # values of IfmiConfig.covariance
LEVERS = ("overlap", "content")  # values of IfmiConfig.lever (:func:`with_overlap_lever`)
ROTATION_GAIN = 0.35  # rotation/scale: sandwich times ROTATION_GAIN sqrt(side); fitted on procedural images only


def translation(cov_eq10: Cov2, pnr: float, shape: tuple[int, int]) -> Cov2:
    """The calibrated translation covariance ``C_eq10 / (PNR sqrt(H W))`` (px^2, over (row, col)).

    Parameters
    ----------
    cov_eq10 : the eq. (10) covariance of the translation peak, px^2 (``b^2`` times the band's, in band ``b``).
    pnr : eq. (13) of that peak.
    shape : (H, W) of the full-resolution images.
    """
    f = math.inf if not pnr > 0.0 else 1.0 / (pnr * math.sqrt(shape[0] * shape[1]))
    (crr, crc), (_, ccc) = cov_eq10
    return ((f * crr, f * crc), (f * crc, f * ccc))


def rotation_scale(cross: C64, shape: tuple[int, int], row: float, col: float) -> Cov2:
    """The calibrated covariance of the rotation/scale peak, bins^2 over (angle row, log-radius column).

    ``ROTATION_GAIN sqrt(R C)`` times :func:`peak_sandwich` of the descriptors' cross spectrum
    ``cross`` (an (R, C) POMF) at the peak ``(row, col)``; infinite where it has no coherent peak.
    """
    (crr, crc), (_, ccc) = peak_sandwich(cross, shape, row, col)
    g = ROTATION_GAIN * math.sqrt(math.sqrt(shape[0] * shape[1]))
    return ((g * crr, g * crc), (g * crc, g * ccc))


def with_overlap_lever(cov: F64, scale_var: float, scale: float, shift_px: tuple[float, float],
                       arm: tuple[float, float] | None = None) -> F64:
    """Add the rotation/scale errors' effect on the shift measured in the overlap (calibrated covariance).

    The translation POMF measures the displacement where the two images overlap: for images
    shifted by ``d`` that is the overlap's centre, ``d / 2`` from the image centre (two equal
    windows). The reference was re-rotated and re-scaled by the estimate about the *image*
    centre, so errors ``da`` (rad) and ``ds / s`` of the first stage move the shift measured
    there by ``da J (d / 2) + (ds / s) (d / 2)``, ``J = [[0, 1], [-1, 0]]`` (module convention:
    y down, angle counter-clockwise as displayed). Its covariance and cross-covariance with the
    angle are added (measured: a least-squares fit of this lever on 674 known warps gave 0.61 and
    0.66 for the 0.5 here, and removed the growth of the translation error with the shift).

    Parameters
    ----------
    cov : (3, 3) over (dx px, dy px, angle deg), the translation block and the angle variance filled.
    scale_var : variance of the scale; ``scale`` the scale.
    shift_px : (dx, dy).
    arm : (x, y) px, the lever to use instead of ``shift_px / 2`` (``IfmiConfig.lever = "content"``: the
        shift minus the whitened match's centroid, both from the image centre).
    """
    lever = 0.5 * np.asarray(shift_px, dtype=np.float64) if arm is None else np.asarray(arm, dtype=np.float64)
    g = np.array([lever[1], -lever[0]]) * (math.pi / 180.0)  # px per degree of angle error
    out = np.array(cov, dtype=np.float64)
    out[:2, :2] += np.outer(g, g) * out[2, 2] + np.outer(lever, lever) * (scale_var / scale**2)
    out[:2, 2] += g * out[2, 2]
    out[2, :2] = out[:2, 2]
    return out


@functools.lru_cache(maxsize=16)
def _frequencies(shape: tuple[int, int]) -> tuple[F64, F64, F64]:
    """Row and column frequencies (cycles per bin) of an (H, W) rfft half-plane, and the column weights."""
    h, w = shape
    c = np.full(w // 2 + 1, 2.0)
    c[0] = 1.0
    if w % 2 == 0:
        c[-1] = 1.0
    return np.fft.fftfreq(h).astype(np.float64), np.fft.rfftfreq(w).astype(np.float64), c


def peak_sandwich(cross: C64, shape: tuple[int, int], row: float, col: float) -> Cov2:
    """Covariance (bins^2, over (row, col)) of the POMF maximum near ``(row, col)``, from its phase residuals.

    The maximum of the POMF ``v(t) = (1/N) Re sum_k c_k C_k exp(2 pi i f_k . t)`` is an
    M-estimator of the shift. With ``eps_k`` the phase of ``C_k exp(2 pi i f_k . t)`` (the
    residual of frequency ``k`` at the estimate) its gradient is ``-(2 pi / N) sum c_k f_k sin eps_k``
    and its Hessian ``-(4 pi^2 / N) sum c_k f_k f_k^T cos eps_k``; with independent residuals
    the first-order covariance of the maximum is the sandwich ``H^-1 E[g g^T] H^-1``::

        Cov = A^-1 B A^-1 / (4 pi^2),  A = sum_k c_k f_k f_k^T cos eps_k,  B = sum_k c_k^2 f_k f_k^T sin^2 eps_k

    (``f`` in cycles per bin; ``c_k`` = 2 for an rfft column that stands for a conjugate pair).
    ``A`` is the peak's curvature, ``B`` the phase noise that moves it. Neighbouring
    frequencies are not independent, so this is a lower bound (module docstring). Returns an
    infinite diagonal when ``A`` is not positive definite (no coherent peak).

    Parameters
    ----------
    cross : (H, W // 2 + 1) normalized cross spectrum (rfft half-plane) of an (H, W) POMF.
    shape : (H, W).
    row, col : the peak, signed bins (cyclic).
    """
    fy, fx, c = _frequencies(shape)
    z = np.asarray(cross, dtype=np.complex64) * np.exp(2j * np.pi * fy * row).astype(np.complex64)[:, None]
    z *= np.exp(2j * np.pi * fx * col).astype(np.complex64)[None, :]
    cos, sin2 = z.real, np.square(z.imag)  # float32: sums over a few 10^4 terms, a variance needs no more
    fy, fx, c = fy.astype(np.float32), fx.astype(np.float32), c.astype(np.float32)
    c2 = c * c
    a_rc, b_rc = float(fy @ cos @ (c * fx)), float(fy @ sin2 @ (c2 * fx))
    a = np.array([[float(fy**2 @ (cos @ c)), a_rc], [a_rc, float((c * fx**2) @ cos.sum(axis=0))]])
    b = np.array([[float(fy**2 @ (sin2 @ c2)), b_rc], [b_rc, float((c2 * fx**2) @ sin2.sum(axis=0))]])
    if not (a[0, 0] > 0.0 and np.linalg.det(a) > 0.0):
        return ((math.inf, 0.0), (0.0, math.inf))
    a_inv = np.linalg.inv(a)
    cov = a_inv @ b @ a_inv / (4.0 * math.pi**2)
    return ((float(cov[0, 0]), float(cov[0, 1])), (float(cov[0, 1]), float(cov[1, 1])))
