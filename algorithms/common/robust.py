"""Robust kernels for least squares, applied to squared Mahalanobis errors through IRLS weights.

Every kernel maps an edge's squared error ``u = e^T Omega e`` (its chi2) to a robust cost
``rho(u)`` and an iteratively-reweighted-least-squares weight ``w = rho'(u)``; the weighted
system uses ``w * Omega`` as the edge information, as g2o's ``RobustKernel`` does [1]_.

References
----------
.. [1] R. Kümmerle, G. Grisetti, H. Strasdat, K. Konolige, W. Burgard, "g2o: A general framework
   for graph optimization", ICRA 2011.
.. [2] P. Agarwal, G. D. Tipaldi, L. Spinello, C. Stachniss, W. Burgard, "Robust map optimization
   using dynamic covariance scaling", ICRA 2013, eq. (7)-(11).
"""

from __future__ import annotations

import enum

import numpy as np
from numpy.typing import NDArray

F64 = NDArray[np.float64]


class Kernel(enum.Enum):
    """Robust kernel applied to the squared error of an edge."""

    NONE = "none"
    DCS = "dcs"
    HUBER = "huber"
    CAUCHY = "cauchy"


DEFAULT_PARAMETER: dict[Kernel, float] = {
    Kernel.NONE: 1.0,
    Kernel.DCS: 1.0,  # Phi = 1, the value used throughout [2]
    Kernel.HUBER: 1.0,  # delta on the Mahalanobis norm sqrt(u), as g2o's default
    Kernel.CAUCHY: 1.0,
}


def weights_and_cost(kernel: Kernel, chi2: F64, parameter: float) -> tuple[F64, F64]:
    """IRLS weights ``rho'(u)`` and robust costs ``rho(u)`` of squared errors ``u``.

    Parameters
    ----------
    kernel : Kernel
    chi2 : (m,) float64, >= 0
        Squared Mahalanobis errors ``u = e^T Omega e``.
    parameter : float, > 0
        DCS: Phi [2]_; Huber: delta (threshold on ``sqrt(u)``); Cauchy: c.

    Returns
    -------
    weights, costs : (m,) float64
        DCS uses ``w = s^2`` with ``s = min(1, 2 Phi / (Phi + u))`` [2]_, whose cost is
        ``u`` for ``u <= Phi`` and ``3 Phi - 4 Phi^2 / (Phi + u)`` above (the integral of ``w``).
    """
    if parameter <= 0.0 or not np.isfinite(parameter):
        raise ValueError(f"parameter must be finite and > 0, got {parameter}")
    u = np.asarray(chi2, dtype=np.float64)
    if kernel is Kernel.NONE:
        return np.ones_like(u), u.copy()
    if kernel is Kernel.DCS:
        phi = parameter
        s = np.minimum(1.0, 2.0 * phi / (phi + u))
        cost = np.where(u <= phi, u, 3.0 * phi - 4.0 * phi * phi / (phi + u))
        return s * s, cost
    if kernel is Kernel.HUBER:
        d = parameter
        r = np.sqrt(u)
        inside = r <= d
        w = np.where(inside, 1.0, d / np.maximum(r, 1e-300))
        return w, np.where(inside, u, 2.0 * d * r - d * d)
    if kernel is Kernel.CAUCHY:
        c2 = parameter * parameter
        return 1.0 / (1.0 + u / c2), c2 * np.log1p(u / c2)
    raise ValueError(f"kernel: unknown kernel {kernel!r}")
