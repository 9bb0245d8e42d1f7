"""A replay scored: the trajectory metrics (APE, RPE: ``evaluate``) added to the pipeline's own metrics.

The engine keeps the pipeline's trajectory and the ground truth it passed over (``ReplayStats.trajectory``,
``.truth``); scoring them is evaluation's, so that the engine never judges what it produced.
"""

from __future__ import annotations

import dataclasses

from slamreplay.replay.engine.loop import ReplayStats
from slamreplay.replay.engine.pipeline import Pipeline
from slamreplay.replay.engine.trajectory import TRUTH_TUM_ARTIFACT, to_tum
from slamreplay.replay.evaluation.evaluate import TRAJECTORY_METRICS, trajectory_metrics
from slamreplay.replay.evaluation.metrics import truth_at
from slamreplay.replay.metric_registry import MetricSpec


def metric_specs(pipeline: type[Pipeline]) -> dict[str, MetricSpec]:
    """Every metric a run of ``pipeline`` may report: its own, and the trajectory metrics ``score`` adds when it
    exports a trajectory (``Pipeline.trajectory_metrics``) and the recording has ground truth; a pipeline's own
    spec of the same name wins."""
    return {**(TRAJECTORY_METRICS if pipeline.trajectory_metrics else {}), **pipeline.metrics}


def score(stats: ReplayStats, pipeline: type[Pipeline]) -> ReplayStats:
    """``stats`` with the trajectory metrics added (the pipeline's own of the same name win) and the truth at the
    estimate's times as an artifact (both TUM files pair line by line, as evo and KITTI tools expect); unchanged
    when the pipeline exports no trajectory or the recording has no ground truth over it."""
    if stats.trajectory is None or stats.truth is None or not len(stats.trajectory[0]):
        return stats
    (t_est, est), (t_gt, gt) = stats.trajectory, stats.truth
    mask, ref = truth_at(t_est, t_gt, gt)
    if not len(ref):
        return stats
    metrics = {**trajectory_metrics(est[mask], ref), **stats.metrics}
    artifacts = {**stats.artifacts, TRUTH_TUM_ARTIFACT: to_tum(t_est[mask], ref)}
    return dataclasses.replace(stats, metrics=metrics, artifacts=artifacts)


