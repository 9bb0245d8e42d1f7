"""The metric registry: every metric of the built-in pipelines, defined once.

A metric is a name, a unit, a direction (``lower`` or ``higher`` is better, a ``target``
value such as a NEES equal to its degrees of freedom, or ``none`` for a count that only
describes the run), a meaning and a diff tolerance (:class:`MetricSpec`). Pipelines take
their specs from here by name (:func:`specs`), and ``pipelines``, ``diff``, ``compare``,
the web page, the viewer's metric table and the README's metric section read them through
the metrics.json each run writes. A plugin may define metrics of its own (its
``Pipeline.metrics``); it should reuse these names where it means the same thing.

One number, one name: the trajectory metrics use evo's vocabulary (APE with a stated
alignment, RPE per step and per metre, :mod:`slamreplay.replay.evaluation.evaluate`). Runs start at the
true pose, so the APE without alignment is the ATE every earlier name stood for, and evo's
``--align_origin`` would be the same number: runs do not report it (``slamreplay trajectory``
still prints it for estimates made elsewhere). Older names stay readable: :data:`RENAMED`
maps them onto the current ones when old runs and results are read (:func:`normalize`).

Consistency metrics are judged by their distance from the consistent value on a log scale,
``|ln(value / target)|`` (:func:`target_distance`): a NEES is a ratio of squared errors to
a stated variance, so a filter twice too confident (NEES 4 for a target of 2) and one twice
too cautious (NEES 1) are equally far off, and both directions are worse than consistent.
"""

from __future__ import annotations

import math
import re
from collections.abc import Mapping
from dataclasses import dataclass, replace
from typing import Any, Literal

# Default diff tolerance of a measured (floating-point) metric: a change within
# max(MEASURED_ABS_TOLERANCE, MEASURED_REL_TOLERANCE * |A|) is "same" (replay.diff.metric_tolerance).
# Why these values: the same recording, code and seed on another Python/numpy/scipy/BLAS sums in
# another order, and iterative solvers (Gauss-Newton, PCG) that stop at a relative decrease of
# 1e-6 then stop at slightly different points: differences of 1e-7..1e-5 relative were seen
# (chi2_final +6.2e-6 on 22.2 between Python 3.11 and 3.12). 0.1 % is 100x above that and 10x
# below a 1 % change, which a diff must still call worse (an ATE of 0.400 m -> 0.404 m is WORSE).
# The absolute floor (1e-6 of the unit: 1 um, 1e-6 px or degree) covers values near zero,
# where a relative tolerance vanishes.
MEASURED_REL_TOLERANCE = 1e-3
MEASURED_ABS_TOLERANCE = 1e-6


@dataclass(frozen=True, slots=True)
class MetricSpec:
    """How to read a metric: which direction is better, its unit, and the default diff tolerance.

    ``better``: ``lower`` or ``higher``; ``target``, with the consistent value in ``target`` (a
    NEES equal to its degrees of freedom: further from it on a log scale, either way, is worse;
    ``slamreplay.replay.metric_registry.target_distance``); ``none`` for a figure that only
    describes the run (a count of images). A change of at most ``max(tolerance, rel_tolerance *
    |A|)`` is "same". Counts keep the defaults (0, 0): any change of a count is reported.
    ``MetricSpec.measured`` gives the tolerance of floating-point measurements (see
    MEASURED_REL_TOLERANCE). The built-in metrics are defined once, in
    ``slamreplay.replay.metric_registry``.
    """

    better: Literal["lower", "higher", "target", "none"]
    unit: str
    description: str
    tolerance: float = 0.0  # absolute floor
    rel_tolerance: float = 0.0  # relative to run A's value
    target: float | None = None  # the consistent value, with better="target"
    optional: str = ""  # why a run may leave it out (see LOST); "" : a run that had it and lost it got worse
    minimum: float | None = None  # the least value it can take (an error, a count: 0): plots' axes stop there
    maximum: float | None = None  # the greatest (a fraction: 1); None: unbounded

    def __post_init__(self) -> None:
        if (self.better == "target") != (self.target is not None):
            raise ValueError(f"a metric with a target value has better='target' and only then: {self}")
        if self.target is not None and not self.target > 0:
            raise ValueError(f"a metric's target value must be > 0 (it is judged on a log scale): {self}")
        if self.minimum is not None and self.maximum is not None and not self.minimum < self.maximum:
            raise ValueError(f"a metric's minimum must be below its maximum: {self}")

    @classmethod
    def measured(cls, better: Literal["lower", "higher", "target", "none"], unit: str, description: str,
                 target: float | None = None, optional: str = "", minimum: float | None = None,
                 maximum: float | None = None) -> MetricSpec:
        """A floating-point metric: numerical noise between environments is "same", a 1 % change is not."""
        return cls(better, unit, description, MEASURED_ABS_TOLERANCE, MEASURED_REL_TOLERANCE, target, optional,
                   minimum, maximum)


def _m(better: Literal["lower", "higher", "target", "none"], unit: str, description: str, optional: str = "",
       minimum: float | None = 0.0, maximum: float | None = None) -> MetricSpec:
    """A built-in measured metric: never negative unless ``minimum`` says otherwise."""
    return MetricSpec.measured(better, unit, description, optional=optional, minimum=minimum, maximum=maximum)


def _count(better: str, description: str, optional: str = "", maximum: float | None = None) -> MetricSpec:
    return MetricSpec(better, "", description, optional=optional, minimum=0.0, maximum=maximum)  # type: ignore[arg-type]


def _nees(description: str, dof: int) -> MetricSpec:
    return MetricSpec.measured("target", "", f"{description} ({dof} when consistent, lower when conservative, "
                                             "higher when overconfident)", target=float(dof), minimum=0.0)


_NO_EDGE_IN_TRUTH = "undefined when no accepted edge joins two images inside the ground truth's time span"
RPE_METRE_DELTA_M = 1.0  # the per-distance RPE of every run: segments of 1 m of the estimate's path (evo_rpe
# --delta 1 --delta_unit m)

METRICS: dict[str, MetricSpec] = {
    # trajectory (every pipeline with an estimated trajectory in metres and ground truth; replay.evaluate)
    "ape_rmse_m": _m("lower", "m", "absolute position error RMSE, no alignment (the estimate starts at the true "
                                   "pose, so every error counts): the ATE; several robots: pooled"),
    "ape_se2_rmse_m": _m("lower", "m", "absolute position error RMSE after the best rigid alignment (evo --align)"),
    "ape_rot_rmse_deg": _m("lower", "deg", "absolute heading error RMSE, no alignment"),
    "rpe_step_trans_rmse_m": _m("lower", "m", "relative pose error between consecutive poses, translation RMSE"),
    "rpe_step_rot_rmse_deg": _m("lower", "deg", "relative pose error between consecutive poses, rotation RMSE"),
    "rpe_m_trans_rmse_m": _m("lower", "m", f"relative pose error over each {RPE_METRE_DELTA_M:g} m of the "
                                           "estimate's path (evo_rpe --delta_unit m), translation RMSE"),
    "rpe_m_rot_rmse_deg": _m("lower", "deg", f"relative pose error over each {RPE_METRE_DELTA_M:g} m of the "
                                             "estimate's path (evo_rpe --delta_unit m), rotation angle RMSE"),
    "robot_final_error_m": _m("lower", "m", "robot position error at the last scored estimate"),
    "robot_max_error_m": _m("lower", "m", "largest robot position error"),
    "path_length_m": _m("none", "m", "length of the estimated path"),
    "poses_scored": _count("none", "estimates inside the ground truth's time span"),
    # landmark SLAM (dslam, ekfslam, dslam-multi)
    "landmark_rmse_m": _m("lower", "m", "RMS error of the matched landmarks (world frame, known start)"),
    "landmark_nees_mean": _nees("mean landmark position NEES", 2),
    "robot_nees_mean": _nees("mean robot pose NEES at scans (several robots: all of them)", 3),
    "landmarks_mapped": _count("higher", "features in the final map"),
    "landmarks_true": _count("none", "landmarks in the ground-truth map"),
    "false_landmarks": _count("lower", "mapped features matching no true landmark"),
    "data_association_errors": _count("lower", "unknown ids: observations given the wrong feature"),
    "steps": _count("none", "scans processed"),
    "info_nnz_blocks": _count("none", "nonzero 2x2 blocks of the final information matrix"),
    "info_nnz_blocks_per_landmark": _m("none", "", "nonzero blocks of the information matrix per mapped feature"),
    "robots": _count("none", "robots replayed"),
    "local_maps": _count("none", "local maps joined into the global map (slsjf)"),
    # topo-metric mapping and navigation
    "images": _count("none", "images the pipeline processed"),
    "locations": _count("none", "locations (graph nodes)"),
    "loop_closures": _count("none", "accepted loop closures"),
    "loop_closures_rejected": _count("none", "validated loop closures the robust relaxation rejected "
                                             "(only with relax_robust)", optional="reported only with relax_robust"),
    "loop_closure_precision": _m("higher", "", "correct / accepted loop closures (truth rule in "
                                               "replay/pipelines/topometric.py)",
                                 optional="undefined when no loop closure is accepted (loop_closures then says 0)",
                                 maximum=1.0),
    "loop_closure_recall": _m("higher", "", "images that closed a loop / images that should have", maximum=1.0),
    "odometry_ate_rmse_m": _m("lower", "m", "RMS position error of odometry at the same images: the baseline "
                                            "the relaxed map is measured against"),
    "goal_reached": _count("higher", "1 when the navigator stopped at the goal and the true position is within "
                                     "goal_radius_m of the goal node", maximum=1.0),
    "goal_distance_m": _m("lower", "m", "true final position to the goal node's true pose (its map pose when the "
                                        "map has no ground truth; the log says which)"),
    "cross_track_error_m_mean": _m("lower", "m", "mean distance of the true position to the true path (route "
                                                 "nodes at their mapping ground-truth poses; the map path when "
                                                 "the map has none, as the log says)"),
    "cross_track_error_m_max": _m("lower", "m", "largest distance of the true position to the true path (map "
                                                "path fallback, as for the mean)"),
    "cross_track_error_m_final": _m("lower", "m", "distance of the true final position to the true path (map "
                                                  "path fallback, as for the mean)"),
    "visual_corrections": _count("none", "loop closures that reset the position (section IV-B)"),
    "loop_closure_rate": _m("higher", "", "images with a loop closure / images", maximum=1.0),
    "route_length_m": _m("none", "m", "length of the planned route through the map's nodes"),
    "estimate_error_m_mean": _m("lower", "m", "mean position error of the estimate at the images"),
    "replay_mismatches": _count("lower", "recorded localizations and commands the replay did not reproduce "
                                         "exactly"),
    "code_matches_recording": _count("none", "1 when this replay runs the navigation code that made the "
                                             "recording (same fingerprint), else 0", maximum=1.0),
    # iFMI photo-mapping (mosaic pixels)
    "registrations": _count("none", "registrations tried (consecutive and loop candidates)"),
    "registrations_accepted": _count("higher", "registrations with PNR >= min_pnr"),
    "pnr_median": _m("higher", "", "median PNR (eq. 13) of all registrations"),
    "chi2_initial": _m("none", "", "squared Mahalanobis sum over all edges before optimization"),
    "chi2_final": _m("lower", "", "squared Mahalanobis sum over all edges after optimization"),
    "chi2_per_dof": MetricSpec.measured("target", "", "chi2 after optimization over the edges the optimizer kept, "
                                                      "per degree of freedom (3 per kept edge - 3 per free node): "
                                                      "1 when the edge covariances are calibrated", target=1.0,
                                      optional="undefined when the kept edges leave no degree of freedom",
                                      minimum=0.0),
    "mosaic_ncc": _m("higher", "", "mean NCC of the image pairs overlapping by 30 % or more at the optimized "
                                   "poses (illumination flattened): the mosaic's agreement with itself",
                     minimum=-1.0, maximum=1.0),
    "edges_rejected": _count("none", "edges the optimizer's chi2 gate left out (covariance=calibrated)"),
    "ate_rmse_px_initial": _m("lower", "px", "node position RMSE before optimization (similarity-aligned)"),
    "ate_rmse_px": _m("lower", "px", "node position RMSE after optimization (similarity-aligned)"),
    "rotation_error_deg_median": _m("lower", "deg", "median |rotation error| of accepted edges",
                                    optional=_NO_EDGE_IN_TRUTH),
    "translation_error_px_median": _m("lower", "px", "median translation error of accepted edges (scaled by the "
                                                     "ATE alignment)", optional=_NO_EDGE_IN_TRUTH),
}

# Per-robot metrics of multi-robot runs: robot{k}_<name>, k = 1, 2, ...
PER_ROBOT: dict[str, MetricSpec] = {
    "ape_rmse_m": _m("lower", "m", "absolute position error RMSE of this robot's estimates against its ground "
                                   "truth, no alignment"),
    "nees_mean": _nees("mean pose NEES of this robot at its scans", 3),
    "scans": _count("none", "scans this robot processed"),
}
_PER_ROBOT = re.compile(r"^robot(\d+)_(.+)$")

# Names of earlier versions -> the name that now holds the same number ({k}: a robot number).
RENAMED: dict[str, str] = {
    "robot_ate_rmse_m": "ape_rmse_m",  # landmark pipelines, odometry, plugins: equal to the APE without alignment
    "robot_heading_rmse_deg": "ape_rot_rmse_deg",  # odometry: the same heading RMSE
    "trajectory_ate_rmse_m": "ape_rmse_m",  # topometric: the relaxed locations are its trajectory
    "robot{k}_ate_rmse_m": "robot{k}_ape_rmse_m",  # dslam-multi
}
# Names runs no longer report because another metric of the same run is always the same number.
RETIRED: dict[str, str] = {
    "ape_origin_rmse_m": "ape_rmse_m",  # runs start at the true pose: aligning the first poses changes nothing
}


def spec(name: str) -> MetricSpec:
    """The registered spec of ``name`` (a per-robot name ``robot3_nees_mean`` included); KeyError if unknown."""
    if name in METRICS:
        return METRICS[name]
    m = _PER_ROBOT.match(name)
    if m and m.group(2) in PER_ROBOT:
        base = PER_ROBOT[m.group(2)]
        return replace(base, description=f"robot {m.group(1)}: {base.description}")
    raise KeyError(name)


def specs(*names: str) -> dict[str, MetricSpec]:
    """``{name: spec}`` of registered metrics, in the order given (a pipeline's ``metrics``)."""
    return {name: spec(name) for name in names}


def current_name(name: str) -> str:
    """The name a metric has now (``robot_ate_rmse_m`` -> ``ape_rmse_m``); unknown names are kept."""
    if name in RENAMED:
        return RENAMED[name]
    m = _PER_ROBOT.match(name)
    if m and f"robot{{k}}_{m.group(2)}" in RENAMED:
        return RENAMED[f"robot{{k}}_{m.group(2)}"].replace("{k}", m.group(1))
    return name


LOST = "lost"  # the verdict of a metric run A reported and run B did not: worse, whatever its direction


def optional_reason(name: str, entry: Mapping[str, Any] | None = None) -> str:
    """Why a run may leave out metric ``name`` ("" when it may not: losing it is a regression).

    A metric that disappears is the loudest regression there is (an estimate that lost its time overlap
    reports no APE at all), so ``diff``, ``compare``, ``history`` and the service judge a metric present in
    A and absent in B as ``LOST``, unless it is declared optional here (``MetricSpec.optional``, the reason)
    or in the run's own metrics.json entry (a plugin's spec)."""
    if isinstance(entry, Mapping) and entry.get("optional"):
        return str(entry["optional"])
    try:
        return spec(current_name(name)).optional
    except KeyError:
        return ""


def axis_bounds(name: str) -> tuple[float | None, float | None]:
    """The (least, greatest) values registered metric ``name`` (under any of its names) can take, for a plot's axis;
    (None, None) for a metric the registry does not know."""
    try:
        s = spec(current_name(name))
    except KeyError:
        return None, None
    return s.minimum, s.maximum


def direction_label(better: str, target: float | None = None) -> str:
    """A metric's direction in a table: ``lower``, ``higher``, ``~2`` (closest to 2 is better) or ``none``."""
    return f"~{target:g}" if better == "target" and target is not None else better


def target_distance(value: float, target: float) -> float:
    """How far ``value`` is from its consistent ``target``: ``|ln(value / target)|``; inf when ``value <= 0``."""
    if not value > 0 or not target > 0:
        return math.inf
    return abs(math.log(value / target))


def normalize(entries: Mapping[str, Any]) -> dict[str, Any]:
    """A run's metrics (name -> entry, or name -> value) under the current names.

    A renamed metric takes its new name unless the run also holds the new one (then the old
    copy, the same number, is dropped); a retired metric is dropped when the metric it
    duplicates is there. An entry (a metrics.json dict) of a registered metric without a
    ``target`` gets the registry's direction and target, so old runs' NEES are judged by their
    distance from the consistent value as new ones are.
    """
    out: dict[str, Any] = {}
    for name, entry in entries.items():
        new = current_name(name)
        if new != name and new in entries:
            continue
        if name in RETIRED and RETIRED[name] in entries:
            continue
        if isinstance(entry, Mapping) and "target" not in entry:
            try:
                s = spec(new)
            except KeyError:
                pass
            else:
                if s.better == "target":
                    entry = {**entry, "better": "target", "target": s.target}
        out[new] = entry
    return out
