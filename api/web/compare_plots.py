"""The comparison page's plots, drawn on the server: every compared run's estimated path over its recording's ground
truth, the position error over time, and the robot pose NEES over time over its consistency band (from each run's
``nees.json``, `slamreplay.replay.evaluation.nees_series`), one colour per run in all three
(``slamreplay.api.web.svg_plots``)."""

from __future__ import annotations

import contextlib
from dataclasses import dataclass
from pathlib import Path
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


NEES_WIDTH = 420  # a narrow viewBox: the NEES plot and its legend stay readable at 390 px (runs_charts' width)


def coloured(jobs: JobService, runs: list[Run], tags: tuple[str, ...] | None = None) -> list[tuple[str, Run, Any]]:
    """(legend label, run, its trajectory.tum as (times in s, poses)) of each run the plots draw, in colour order:
    the succeeded runs with an estimated trajectory."""
    from slamreplay.replay.engine.trajectory import TUM_ARTIFACT

    out = []
    for i, r in enumerate(runs):
        if r.job.status != "succeeded" or (est := _timed(jobs, r.job.id, TUM_ARTIFACT)) is None:
            continue
        tag = tags[i] if tags else str(i + 1)
        out.append((f"{tag}: {r.job.name or r.job.id[:8]} ({r.job.pipeline}, seed {r.job.seed})", r, est))
    return out


def overlay(jobs: JobService, runs: list[Run], tags: tuple[str, ...] | None = None,
            drawn: list[tuple[str, Run, Any]] | None = None) -> tuple[str, str]:
    """Inline SVGs of the succeeded runs, one colour each in both: their estimated paths over each recording's
    ground truth, and their position error over time (each against its own recording's truth, from the first pose
    with ground truth; empty when no run has one). ``drawn``: `coloured` of the runs, when already read."""
    import numpy as np

    from slamreplay.replay.engine.trajectory import TRUTH_TUM_ARTIFACT, paired_with_truth

    paths, truths, errors, seen = [], [], [], set()
    for label, r, est in coloured(jobs, runs, tags) if drawn is None else drawn:
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


def _why_no_nees(jobs: JobService, r: Run) -> str:
    """Why a drawn run has no NEES curve: its pipeline reports no robot pose NEES (dead reckoning keeps no
    covariance; iFMI's and the topo-metric map's are not scored as one), it had no ground truth over its scans, or
    it ran before runs kept their NEES per step."""
    from slamreplay.replay.engine.pipeline import get_pipeline
    from slamreplay.replay.errors import ReplayError

    if "robot_nees_mean" in jobs.metric_values(r.job.id):
        return "its NEES per step is only in its run.rrd (a run made before runs kept nees.json)"
    try:
        has_nees = "robot_nees_mean" in get_pipeline(r.job.pipeline).metrics
    except (ReplayError, KeyError):  # a pipeline no longer installed
        has_nees = False
    if has_nees:
        return "no ground truth over its scans, so no NEES"
    return f"{r.job.pipeline} reports no robot pose NEES (robot_nees_mean)"


@dataclass(frozen=True, slots=True)
class RobotNees:
    """A run's robot pose NEES as the plots draw it: ``t`` (s) from its first pose with ground truth (the error
    plot's origin), ``values`` the NEES of every ``stride``-th of its ``steps`` scans (nees.json's points: single
    scans' values, which the band is the band of), and its band with the band's legend text."""

    t: Any
    values: Any
    stride: int
    steps: int
    band: tuple[float, float]
    band_text: str


def ordinal(n: int) -> str:
    """``2nd``, ``3rd``, ``11th``, ``21st``."""
    return f"{n}{'th' if 10 <= n % 100 <= 20 else {1: 'st', 2: 'nd', 3: 'rd'}.get(n % 10, 'th')}"


def robot_nees(run_dir: Path) -> RobotNees | None:
    """The robot NEES series of the run in ``run_dir`` (its ``nees.json``), ready to draw; None without one."""
    from slamreplay.replay.engine.trajectory import TRUTH_TUM_ARTIFACT, read_tum
    from slamreplay.replay.evaluation.nees_series import NEES_ARTIFACT, read_nees

    try:
        robot = read_nees((run_dir / NEES_ARTIFACT).read_bytes()).get("robot")
    except (OSError, ValueError):
        return None
    if robot is None or not len(robot.nees):
        return None
    start = 0.0
    with contextlib.suppress(OSError, ValueError, IndexError):
        start = robot.t0_ns * 1e-9 - float(read_tum((run_dir / TRUTH_TUM_ARTIFACT).read_text())[0][0])
    (low, high), share = robot.band, f"{100 * robot.level:g} %"
    text = (f"consistent, {share} of chi2({robot.dof}): {low:.3g} to {high:.3g}" if low > 0
            else f"consistent, {share}: 0 to {high:.3g} (the truth is an estimate)")
    return RobotNees(start + robot.t_s, robot.nees, robot.stride, robot.steps, robot.band, text)


def nees_svg(curves: list[tuple[str, Any, Any]], series: list[RobotNees], title: str) -> str:
    """``curves`` (label, t, NEES) over the bands of ``series`` (each distinct band once, shaded grey)."""
    bands = {s.band: s.band_text for s in series}
    return curves_svg(curves, "robot pose NEES", title, width=NEES_WIDTH, height=260, legend_x=12,
                      bands=[(text, low, high) for (low, high), text in bands.items()])


def nees_plot(jobs: JobService, runs: list[Run], tags: tuple[str, ...] | None = None,
              drawn: list[tuple[str, Run, Any]] | None = None) -> tuple[str, list[str], str]:
    """An inline SVG of the robot pose NEES over time of each drawn run that has one (its ``nees.json``), in the
    trajectory overlay's colours and legend, over the consistency band shaded grey (each distinct band once); and a
    line per drawn run without one saying why; and a note naming the long runs drawn at every k-th scan.
    ``("", [], "")`` when no run has a NEES: then there is nothing to say."""
    import numpy as np

    curves, series, without, decimated = [], [], [], []
    for label, r, _ in coloured(jobs, runs, tags) if drawn is None else drawn:
        nees = robot_nees(jobs.run_dir(r.job.id))
        if nees is None:
            curves.append((label, np.zeros(0), np.zeros(0)))  # keeps the next runs' colours those of the paths
            without.append(f"{label}: {_why_no_nees(jobs, r)}")
            continue
        curves.append((label, nees.t, nees.values))
        series.append(nees)
        if nees.stride > 1:
            decimated.append(f"{label.split(':')[0]}: every {ordinal(nees.stride)} of {nees.steps:,} scans")
    if not series:
        return "", [], ""
    svg = nees_svg(curves, series, f"robot pose NEES over time of {len(series)} runs; shaded: where a consistent "
                   "filter's NEES lies")
    note = (f"Long runs are drawn at every k-th scan ({'; '.join(decimated)}), as their nees.json keeps them; each "
            "scan's NEES is in the run's run.rrd, and the metric robot_nees_mean is over all." if decimated else "")
    return svg, without, note


def plots(jobs: JobService, runs: list[Run], tags: tuple[str, ...] | None = None) -> dict[str, Any]:
    """The compare page's plots of ``runs`` (``tags``: their labels, 1, 2... by default)."""
    drawn = coloured(jobs, runs, tags)
    plot, errors = overlay(jobs, runs, tags, drawn)
    nees, no_nees, nees_note = nees_plot(jobs, runs, tags, drawn)
    return {"plot": plot, "error_plot": errors, "nees_plot": nees, "no_nees": no_nees, "nees_note": nees_note}
