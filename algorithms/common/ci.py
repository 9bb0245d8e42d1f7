"""Covariance Intersection: fusing two estimates whose cross-correlation is unknown.

For two consistent estimates ``(a, A)`` and ``(b, B)`` of the same quantity, CI [1]_ forms

    C^-1 = w A^-1 + (1 - w) B^-1,        c = C (w A^-1 a + (1 - w) B^-1 b),       w in [0, 1],

which is consistent whatever the correlation between the two errors is. The weight ``w`` is
chosen to minimise either the determinant or the trace of ``C``. D-SLAM fuses its odometry
prediction and its measurement-based robot pose this way ([2]_, section 2.3).

References
----------
.. [1] S. J. Julier, J. K. Uhlmann, "A non-divergent estimation algorithm in the presence of
   unknown correlations", ACC 1997; "Simultaneous localization and map building using split
   covariance intersection", IROS 2001.
.. [2] Z. Wang, S. Huang, G. Dissanayake, "Implementation issues and experimental evaluation
   of D-SLAM", FSR 2005, section 2.3.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np
import scipy.linalg as sla
from numpy.typing import ArrayLike, NDArray

from slamreplay.algorithms.common.se2 import wrap_angle

F64 = NDArray[np.float64]
Criterion = Literal["det", "trace"]


@dataclass(frozen=True, slots=True)
class CIResult:
    """The fused estimate: mean (n,), covariance (n, n) and the weight ``omega`` given to the first input."""

    mean: F64
    cov: F64
    omega: float


def _information(name: str, cov: F64, n: int) -> F64:
    if cov.shape != (n, n) or not np.all(np.isfinite(cov)):
        raise ValueError(f"{name} must be a finite ({n}, {n}) matrix, got shape {cov.shape}")
    if not np.allclose(cov, cov.T, rtol=1e-9, atol=1e-12 * max(1.0, float(np.abs(cov).max()))):
        raise ValueError(f"{name} must be symmetric")
    try:
        chol = np.linalg.cholesky(0.5 * (cov + cov.T))
    except np.linalg.LinAlgError:
        raise ValueError(f"{name} must be positive definite") from None
    inv_chol = np.linalg.inv(chol)
    return inv_chol.T @ inv_chol


def covariance_intersection(mean_a: ArrayLike, cov_a: ArrayLike, mean_b: ArrayLike, cov_b: ArrayLike,
                            criterion: Criterion = "det", angular: Sequence[int] = (),
                            xatol: float = 1e-10) -> CIResult:
    """Fuse two estimates of one quantity by Covariance Intersection ([1]_, [2]_ section 2.3).

    Parameters
    ----------
    mean_a, mean_b : (n,) the two estimates.
    cov_a, cov_b : (n, n) their covariances, symmetric positive definite.
    criterion : ``"det"`` minimises det(C) (the volume of the fused uncertainty ellipsoid);
        ``"trace"`` minimises trace(C) (the mean squared error).
    angular : indices of angle components: ``mean_b`` is moved to the branch of ``mean_a``
        before fusing, and the fused angle is wrapped to [-pi, pi).
    xatol : tolerance on ``omega`` of the bisection.

    Returns
    -------
    CIResult : fused mean and covariance, and ``omega`` (the weight of ``a``; 1 keeps ``a`` only).

    Notes
    -----
    With the generalised eigenpairs ``(A^-1 - B^-1) v_i = l_i B^-1 v_i`` (``v_i^T B^-1 v_i = 1``),
    ``C(w)^-1 = B^-1 + w (A^-1 - B^-1)`` has ``det C(w)^-1 = det B^-1 prod(1 + w l_i)`` and
    ``trace C(w) = sum |v_i|^2 / (1 + w l_i)``. Both criteria are then convex in ``w`` with a
    monotone derivative, whose root in [0, 1] (or the end point) is found by bisection.
    """
    a = np.asarray(mean_a, dtype=np.float64)
    b = np.asarray(mean_b, dtype=np.float64)
    if a.ndim != 1 or b.shape != a.shape or not (np.all(np.isfinite(a)) and np.all(np.isfinite(b))):
        raise ValueError(f"mean_a and mean_b must be finite (n,) arrays of one shape, got {a.shape} and {b.shape}")
    if criterion not in ("det", "trace"):
        raise ValueError(f"criterion must be 'det' or 'trace', got {criterion!r}")
    n = len(a)
    idx = list(angular)
    if any(not 0 <= i < n for i in idx):
        raise ValueError(f"angular indices must be in [0, {n}), got {idx}")
    ia = _information("cov_a", np.asarray(cov_a, dtype=np.float64), n)
    ib = _information("cov_b", np.asarray(cov_b, dtype=np.float64), n)
    b = b.copy()
    if idx:
        b[idx] = a[idx] + wrap_angle(b[idx] - a[idx])
    omega = _optimal_omega(ia, ib, criterion, xatol)
    info = omega * ia + (1.0 - omega) * ib
    cov = np.linalg.inv(info)
    cov = 0.5 * (cov + cov.T)
    mean = cov @ (omega * ia @ a + (1.0 - omega) * ib @ b)
    if idx:
        mean[idx] = wrap_angle(mean[idx])
    return CIResult(mean=mean, cov=cov, omega=omega)


def _optimal_omega(ia: F64, ib: F64, criterion: Criterion, xatol: float) -> float:
    """The minimiser over [0, 1] of det or trace of (w ia + (1 - w) ib)^-1 (see the Notes above).

    The criterion's derivative is increasing in w: its root is found by Newton steps kept
    inside a shrinking bracket (a bisection step whenever Newton would leave it).
    """
    lam_arr, vec = sla.eigh(ia - ib, ib, check_finite=False)
    lam = lam_arr.tolist()
    weight = np.einsum("ij,ij->j", vec, vec).tolist()
    det = criterion == "det"

    def slope(w: float) -> tuple[float, float]:  # derivative of the criterion and its derivative
        g = h = 0.0
        for li, wi in zip(lam, weight, strict=True):
            d = 1.0 + w * li
            if d <= 0.0:  # only at w = 1 with a singular ib: C is unbounded there, the criterion rises to it
                return math.inf, math.inf
            if det:
                g -= li / d
                h += li * li / (d * d)
            else:
                g -= wi * li / (d * d)
                h += 2.0 * wi * li * li / (d * d * d)
        return g, h

    if slope(0.0)[0] >= 0.0:
        return 0.0
    if slope(1.0)[0] <= 0.0:
        return 1.0
    lo, hi, w = 0.0, 1.0, 0.5
    while hi - lo > xatol:
        g, h = slope(w)
        if g < 0.0:
            lo = w
        else:
            hi = w
        step = w - g / h if h > 0 else -1.0
        new = step if lo < step < hi else 0.5 * (lo + hi)
        if abs(new - w) <= 0.5 * xatol:
            return new
        w = new
    return 0.5 * (lo + hi)


def covariance_intersection_update(mean: ArrayLike, cov: ArrayLike, innovation: ArrayLike, h: ArrayLike,
                                   s: ArrayLike, criterion: Criterion = "det", angular: Sequence[int] = (),
                                   xatol: float = 1e-10) -> CIResult:
    """Covariance Intersection of an estimate ``(mean, cov)`` with an observation of part of it ([1]_, the
    second paper: CI as a Kalman update whose observation error is correlated with the estimate in an unknown way).

    The observation is linearized at ``mean``: ``innovation = z - h(mean)`` (m,), Jacobian ``h`` (m, n) and
    covariance ``s`` (m, m), which carries everything in the observation that is not the state (sensor noise,
    and the uncertainty of the map the observation is taken against). With ``I_z = H^T S^-1 H`` (rank m, possibly
    below n), ``C^-1 = w cov^-1 + (1 - w) I_z`` and ``c = mean + (1 - w) C H^T S^-1 innovation``; ``w`` minimises
    det(C) or trace(C) as in :func:`covariance_intersection` (``omega`` is the weight of the estimate). Whatever
    the correlation between the estimate's error and the observation's, the result is consistent.
    """
    x = np.asarray(mean, dtype=np.float64)
    n = len(x)
    hm = np.asarray(h, dtype=np.float64)
    nu = np.asarray(innovation, dtype=np.float64)
    if hm.ndim != 2 or hm.shape[1] != n or nu.shape != (hm.shape[0],) or not np.all(np.isfinite(nu)):
        raise ValueError(f"h must be (m, {n}) and innovation finite (m,), got {hm.shape} and {nu.shape}")
    ia = _information("cov", np.asarray(cov, dtype=np.float64), n)
    s_inv = _information("s", np.asarray(s, dtype=np.float64), len(nu))
    iz = hm.T @ s_inv @ hm
    iz = 0.5 * (iz + iz.T)
    # the observation's information is singular when it sees part of the state: the weight is found with the
    # estimate's (positive definite) information as the metric, and given back as the estimate's weight
    omega = 1.0 - _optimal_omega(iz, ia, criterion, xatol)
    c = np.linalg.inv(omega * ia + (1.0 - omega) * iz)
    c = 0.5 * (c + c.T)
    out = x + (1.0 - omega) * (c @ hm.T @ s_inv @ nu)
    if angular:
        out[list(angular)] = wrap_angle(out[list(angular)])
    return CIResult(mean=out, cov=c, omega=omega)
