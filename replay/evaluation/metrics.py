"""Trajectory metrics, in float64 numpy, and the metrics.json format.

Estimates of a SLAM run with a known initial pose are compared without alignment:
the estimate starts in the ground-truth frame (ReplayContext.T_world_start), so every
error it accumulates is counted. Ground truth is interpolated at the estimate's times.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping
from typing import Any, cast

import numpy as np
from numpy.typing import NDArray

from slamreplay.algorithms.common import se2
from slamreplay.replay.metric_registry import MetricSpec

F64 = NDArray[np.float64]
METRICS_FORMAT = 1


def associate(t_est_ns: NDArray[np.int64], t_gt_ns: NDArray[np.int64]) -> NDArray[np.bool_]:
    """Mask of estimate times inside the ground truth's time span (where interpolation is valid)."""
    if len(t_gt_ns) == 0:
        return np.zeros(len(t_est_ns), bool)
    return cast(NDArray[np.bool_], (t_est_ns >= t_gt_ns[0]) & (t_est_ns <= t_gt_ns[-1]))


def time_coverage(t_est_ns: NDArray[np.int64], t_gt_ns: NDArray[np.int64]) -> tuple[float, int, int]:
    """(fraction of the ground truth's time span from the first to the last estimate time inside it, those two
    times in ns); ``(0.0, 0, 0)`` when no estimate time is inside. A truth of one instant is covered (1.0) by an
    estimate at that instant. Gaps between estimates count as covered: the rule catches a clock offset (an
    estimate beside the truth in time), not a sparse estimate."""
    t_est_ns, t_gt_ns = np.asarray(t_est_ns, np.int64), np.asarray(t_gt_ns, np.int64)
    inside = t_est_ns[associate(t_est_ns, t_gt_ns)]
    if not len(inside):
        return 0.0, 0, 0
    first, last = int(inside.min()), int(inside.max())
    span = int(t_gt_ns[-1] - t_gt_ns[0])
    return (1.0 if span == 0 else (last - first) / span), first, last


def truth_at(t_est_ns: NDArray[np.int64], t_gt_ns: NDArray[np.int64], gt: F64) -> tuple[NDArray[np.bool_], F64]:
    """(mask of estimate times inside the ground truth's span, ground-truth poses (k, 3) at those times)."""
    t_gt_ns = np.asarray(t_gt_ns, np.int64)
    mask = associate(np.asarray(t_est_ns, np.int64), t_gt_ns)
    if not mask.any():
        return mask, np.zeros((0, 3))
    t0 = t_gt_ns[0]  # relative times keep float64 interpolation exact to the ns
    ref = se2.interpolate((np.asarray(t_est_ns)[mask] - t0).astype(np.float64), (t_gt_ns - t0).astype(np.float64),
                          np.asarray(gt, np.float64))
    return mask, np.asarray(ref, np.float64)


def position_errors(t_est_ns: NDArray[np.int64], est: F64, t_gt_ns: NDArray[np.int64], gt: F64) -> tuple[F64, F64]:
    """Per-estimate position error (m) and heading error (rad) against interpolated ground truth.

    Returns errors only for estimates inside the ground truth's time span, and the mask of
    which estimates those are is ``associate(t_est_ns, t_gt_ns)``.
    """
    mask, ref = truth_at(t_est_ns, t_gt_ns, gt)
    d = np.asarray(est)[mask] - ref
    return np.hypot(d[:, 0], d[:, 1]), np.abs(se2.wrap_angle(d[:, 2]))


def rmse(x: F64) -> float:
    return float(np.sqrt(np.mean(np.square(x)))) if len(x) else math.nan


def format_metrics(pipeline: str, values: Mapping[str, float], specs: Mapping[str, MetricSpec]) -> dict[str, Any]:
    """The metrics.json document: values with their direction, unit and diff tolerance.

    ``tolerance`` (absolute floor) and ``rel_tolerance`` (relative to the baseline's value)
    are the defaults ``slamreplay.replay.runs.diff.metric_tolerance`` applies.

    A metric that does not apply to a run is absent (the pipeline leaves it out); a value
    that is not finite is an error of the pipeline.
    """
    unknown = set(values) - set(specs)
    if unknown:
        raise ValueError(f"metrics without a spec: {', '.join(sorted(unknown))}")
    bad = [k for k, v in values.items() if not math.isfinite(v)]
    if bad:
        raise ValueError(f"metrics are not finite: {', '.join(sorted(bad))}")
    return {
        "format": METRICS_FORMAT,
        "pipeline": pipeline,
        "metrics": {name: metric_entry(float(v), specs[name]) for name, v in sorted(values.items())},
    }


def metric_entry(value: float, spec: MetricSpec) -> dict[str, Any]:
    """One metric in metrics.json: its value, direction (and target value), unit and diff tolerance."""
    out: dict[str, Any] = {"value": value, "better": spec.better, "unit": spec.unit, "tolerance": spec.tolerance,
                           "rel_tolerance": spec.rel_tolerance}
    if spec.target is not None:
        out["target"] = spec.target
    return out


def dumps(doc: Mapping[str, Any]) -> str:
    """Deterministic JSON text: sorted keys, full float precision, trailing newline."""
    return json.dumps(doc, sort_keys=True, indent=2, allow_nan=False) + "\n"


_ARROW = {"lower": "lower is better", "higher": "higher is better", "none": ""}


def better_text(better: str, target: float | None = None) -> str:
    """Which way a metric is better, in words ("lower is better", "closest to 2 is better", "")."""
    if better == "target":
        return f"closest to {target:g} is better"
    return _ARROW.get(better, "")


def metrics_markdown(title: str, values: Mapping[str, float], specs: Mapping[str, MetricSpec]) -> str:
    """The metrics of a run as a markdown table (value, unit, which way is better, meaning)."""
    lines = [f"### {title}", "", "Map: ground truth grey, estimate blue (several robots: each in its series' "
             "colour), dead reckoning orange, accepted green, rejected red; ellipses at 2 sigma.", "",
             "| metric | value | unit | better | meaning |", "|---|---:|---|---|---|"]
    for name, value in sorted(values.items()):
        spec = specs[name]
        shown = f"{value:,.0f}" if float(value).is_integer() and abs(value) < 1e15 else f"{value:.4g}"
        better = better_text(spec.better, spec.target)
        lines.append(f"| `{name}` | {shown} | {spec.unit} | {better} | {spec.description} |")
    if not values:
        lines.append("| (no metric applies to this run) | | | | |")
    return "\n".join(lines) + "\n"


def marginal_blocks(joint_cov: F64) -> F64:
    """The k marginal (2, 2) blocks on the diagonal of a joint covariance (2k, 2k) of k landmarks."""
    k = len(joint_cov) // 2
    return np.asarray(joint_cov.reshape(k, 2, k, 2)[np.arange(k), :, np.arange(k), :], np.float64)


def mean_nees_band(joint_cov: F64, level: float = 0.95, reference_cov: F64 | None = None) -> tuple[float, float]:
    """The central ``level`` band of the mean of k landmark NEES values when the estimate is consistent.

    ``joint_cov`` (2k, 2k) is the estimate's joint covariance of its k landmarks. The mean of their
    marginal NEES values is ``e^T B e / k`` with ``B = blockdiag(P_ii^-1)``: for errors of covariance
    ``E = L L^T`` a sum of chi2(1) terms weighted by the eigenvalues of ``L^T B L / k``. Against ground
    truth ``E = P``: of mean 2 and variance ``2 sum(lambda^2)``; landmarks that share an error (a map's
    common translation or rotation) widen it far beyond the chi2(2k)/k of independent ones, which it
    equals when P is block diagonal. The band is that of Pearson's shifted, scaled chi-square with the
    same first three cumulants (``kappa_r = 2^(r-1) (r-1)! sum(lambda^r)``): on map-like covariances (a
    shared translation plus independent parts) its upper end is within 1 % of the sampled quantile and
    its lower end up to 0.15 above it.

    ``reference_cov``: the landmarks are scored against a reference that is itself an estimate from the same
    measurements, the batch optimum, with this joint covariance. The optimum is efficient (it reaches the
    Cramer-Rao bound, to first order), so its error is uncorrelated with the difference of any other
    unbiased estimate from it, and a consistent estimate's error from it has covariance ``E = P - P_ref``:
    the NEES is then lower than against the truth (mean ``2 - tr(P_ii^-1 P_ref,ii)`` per landmark). ValueError
    when ``P - P_ref`` has a negative eigenvalue (beyond rounding): the estimate then claims less uncertainty
    than the best estimate from the same data has, which no consistent estimate can, and no band applies.
    """
    k = len(joint_cov) // 2
    if joint_cov.shape != (2 * k, 2 * k) or k == 0:
        raise ValueError(f"joint_cov must be (2k, 2k) with k >= 1, got {joint_cov.shape}")
    p = 0.5 * (joint_cov + joint_cov.T)
    if reference_cov is None:
        factor = np.linalg.cholesky(p)
    else:
        if reference_cov.shape != p.shape:
            raise ValueError(f"reference_cov must be {p.shape} as joint_cov, got {reference_cov.shape}")
        w, v = np.linalg.eigh(p - 0.5 * (reference_cov + reference_cov.T))
        if w.min() < -1e-9 * max(float(np.abs(w).max()), 1e-300):
            below = int(np.sum(w < 0))
            raise ValueError(f"the estimate's covariance is below the reference's in {below} of {2 * k} directions "
                             f"(most: {-w.min():.3g} m^2): it claims less uncertainty than the batch optimum of the "
                             "same measurements has, so it cannot be consistent and no NEES band applies")
        factor = v * np.sqrt(np.maximum(w, 0.0))
    b = np.zeros_like(p)
    inv = np.linalg.inv(marginal_blocks(p))
    for i in range(k):
        b[2 * i:2 * i + 2, 2 * i:2 * i + 2] = inv[i]
    lam = np.linalg.eigvalsh(factor.T @ b @ factor) / k
    return pearson_band(float(np.sum(lam)), float(2 * np.sum(lam**2)), float(8 * np.sum(lam**3)), level)


def pearson_band(k1: float, k2: float, k3: float, level: float = 0.95) -> tuple[float, float]:
    """The central ``level`` band of ``c + a chi2(nu)`` with cumulants ``k1, k2, k3`` (Pearson's approximation of
    a weighted sum of chi-squares)."""
    from scipy.stats import chi2

    nu = 8 * k2**3 / k3**2
    a = k3 / (4 * k2)
    c = k1 - a * nu
    return (float(c + a * chi2.ppf((1 - level) / 2, nu)), float(c + a * chi2.ppf((1 + level) / 2, nu)))


def satterthwaite(mean: float, var: float, level: float = 0.95) -> tuple[float, float]:
    """The central ``level`` band of the scaled chi-square ``a chi2(nu)`` with this mean and variance."""
    from scipy.stats import chi2

    scale, dof = var / (2 * mean), 2 * mean**2 / var
    return (float(scale * chi2.ppf((1 - level) / 2, dof)), float(scale * chi2.ppf((1 + level) / 2, dof)))
