"""The comparison page's plots, drawn on the server: every compared run's estimated path over its recording's ground
truth, and the position error over time, one colour per run in both (``slamreplay.api.web.svg_plots``)."""

from __future__ import annotations

import contextlib
from typing import Any

from slamreplay.api.service.compare_runs import Run
from slamreplay.api.service.jobs import JobService
from slamreplay.api.web.svg_plots import curves_svg, overlay_svg


def _timed(jobs: JobService, job_id: str, name: str) -> tuple[Any, Any] | None:
    """A run's TUM file as (times in s, poses), or None."""
    from slamreplay.replay.engine.trajectory import read_tum

    with contextlib.suppress(OSError, ValueError):
        t, poses = read_tum((jobs.run_dir(job_id) / name).read_text())
        return (t, poses) if len(t) else None
    return None


def overlay(jobs: JobService, runs: list[Run], tags: tuple[str, ...] | None = None) -> tuple[str, str]:
    """Inline SVGs of the succeeded runs, one colour each in both: their estimated paths over each recording's
    ground truth, and their position error over time (each against its own recording's truth, from the first pose
    with ground truth; empty when no run has one)."""
    import numpy as np

    from slamreplay.replay.engine.trajectory import TRUTH_TUM_ARTIFACT, TUM_ARTIFACT, paired_with_truth

    paths, truths, errors, seen = [], [], [], set()
    for i, r in enumerate(runs):
        if r.job.status != "succeeded" or (est := _timed(jobs, r.job.id, TUM_ARTIFACT)) is None:
            continue
        tag = tags[i] if tags else str(i + 1)
        label = f"{tag}: {r.job.name or r.job.id[:8]} ({r.job.pipeline}, seed {r.job.seed})"
        paths.append((label, est[1][:, :2]))
        truth = _timed(jobs, r.job.id, TRUTH_TUM_ARTIFACT)
        paired = None if truth is None else paired_with_truth(est[0], est[1], truth[0])
        if truth is None or paired is None:
            errors.append((label, np.zeros(0), np.zeros(0)))  # keeps the next runs' colours those of the paths
        else:
            errors.append((label, truth[0] - truth[0][0], np.hypot(*(paired[:, :2] - truth[1][:, :2]).T)))
        if truth is not None and r.job.recording_id not in seen:
            seen.add(r.job.recording_id)
            truths.append((f"ground truth of {r.recording}", truth[1][:, :2]))
    if not paths:
        return "", ""
    return overlay_svg(paths, truths), curves_svg(errors, "position error (m)",
                                                  f"position error over time of {len(paths)} runs")


def plots(jobs: JobService, runs: list[Run], tags: tuple[str, ...] | None = None) -> dict[str, str]:
    """The compare page's plots of ``runs`` (``tags``: their labels, 1, 2... by default)."""
    plot, errors = overlay(jobs, runs, tags)
    return {"plot": plot, "error_plot": errors}
