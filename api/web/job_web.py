"""A job's page: status (with percent, elapsed time and ETA while it runs, the whole error when it failed),
its resolved config with each value's source, metrics with unit, direction and meaning, plots drawn
on the server, its files (downloadable, from inside its run directory only) and the tail of its log.
"""

from __future__ import annotations

import contextlib
import json
import re
import time
from pathlib import Path
from typing import Annotated, Any

import numpy as np
from fastapi import APIRouter, Depends, Request
from fastapi import Path as PathParam
from fastapi.responses import FileResponse

from slamreplay.api.service.audit import job_people
from slamreplay.api.service.auth import link_secret
from slamreplay.api.service.deps import JobsDep, viewer_href
from slamreplay.api.service.errors import NotFoundError
from slamreplay.api.service.jobs import JobService
from slamreplay.api.service.models import JOB_ID
from slamreplay.api.service.store import ACTIVE
from slamreplay.api.web.pages import duration_text

JobPath = Annotated[str, PathParam(pattern=JOB_ID)]
FileName = Annotated[str, PathParam(pattern=r"^[A-Za-z0-9][A-Za-z0-9._-]{0,99}$")]
FILE_ORDER = ("trajectory.tum", "truth.tum", "metrics.json", "manifest.json", "log.txt", "run.rrd")
TEXT_TYPES = {".tum": "text/plain; charset=utf-8", ".txt": "text/plain; charset=utf-8", ".json": "application/json",
              ".csv": "text/csv; charset=utf-8"}
LOG_TAIL_LINES = 40
router = APIRouter(include_in_schema=False)


def _direction(better: str, target: float | None) -> str:
    if better == "target" and target is not None:
        return f"closest to {target:g}"
    return {"lower": "lower is better", "higher": "higher is better"}.get(better, "describes the run")


def metric_rows(run_dir: Path, pipeline: str) -> list[dict[str, Any]]:
    """A succeeded run's metrics: value, unit and direction (from metrics.json) and meaning (the metric's spec)."""
    from slamreplay.api.service.runs_query import metric_specs
    from slamreplay.replay.metric_registry import normalize

    try:
        doc = json.loads((run_dir / "metrics.json").read_text())
    except (OSError, json.JSONDecodeError):
        return []
    specs = metric_specs()
    out = []
    for name, m in sorted(normalize(doc.get("metrics", {})).items()):  # an older run's names are the current ones
        spec = specs.get(name)
        target = m.get("target", getattr(spec, "target", None))
        out.append({"name": name, "value": m.get("value"), "unit": m.get("unit") or "",
                    "direction": _direction(str(m.get("better", "none")), target),
                    "meaning": spec.description if spec is not None else ""})
    return out


def config_rows(manifest: dict[str, Any] | None, submitted: dict[str, Any]) -> list[dict[str, Any]]:
    """Every resolved config key with its value and source (default, recording, preset, user); before the run has
    a manifest, the submitted keys only."""
    if manifest and isinstance(manifest.get("config"), dict):
        sources = manifest.get("config_sources") or {}
        return [{"key": k, "value": v, "source": sources.get(k, "")} for k, v in sorted(manifest["config"].items())]
    return [{"key": k, "value": v, "source": "user"} for k, v in sorted(submitted.items())]


def run_files(run_dir: Path) -> list[dict[str, Any]]:
    """The files a run has (not hidden, not partial), the usual ones first."""
    if not run_dir.is_dir():
        return []
    found = [p for p in run_dir.iterdir() if p.is_file() and not p.name.startswith(".") and not p.is_symlink()]
    rank = {n: i for i, n in enumerate(FILE_ORDER)}
    found.sort(key=lambda p: (rank.get(p.name, len(rank)), p.name))
    return [{"name": p.name, "size": p.stat().st_size} for p in found]


def log_tail(run_dir: Path, lines: int = LOG_TAIL_LINES) -> str:
    """The last ``lines`` lines of the run's log (read from its last 64 KiB): log.txt once the run has ended, the
    live copy the run appends to while it runs (``replay.run.LIVE_LOG``) before."""
    from slamreplay.replay.runs.run import LIVE_LOG

    path = run_dir / "log.txt"
    if not path.exists():
        path = run_dir / LIVE_LOG
    try:
        with path.open("rb") as f:
            f.seek(max(path.stat().st_size - 65536, 0))
            text = f.read().decode("utf-8", "replace")
    except OSError:
        return ""
    return "\n".join(text.splitlines()[-lines:])


def plots(run_dir: Path) -> list[str]:
    """Inline SVGs: the trajectory against ground truth, the position error and the robot NEES over time (where the
    files are)."""
    from slamreplay.api.web.svg_plots import error_svg, trajectory_svg
    from slamreplay.replay.engine.trajectory import TRUTH_TUM_ARTIFACT, TUM_ARTIFACT, paired_with_truth, read_tum

    try:
        t, est = read_tum((run_dir / TUM_ARTIFACT).read_text())
    except (OSError, ValueError):
        return []
    if not len(est):
        return []
    truth = t_truth = None
    with contextlib.suppress(OSError, ValueError):
        t_truth, truth = read_tum((run_dir / TRUTH_TUM_ARTIFACT).read_text())
    dead = None
    with contextlib.suppress(OSError, ValueError):
        dead = read_tum((run_dir / "odometry.tum").read_text())[1][:, :2]
    out = [trajectory_svg(est[:, :2], None if truth is None else truth[:, :2], dead)]
    if truth is not None and t_truth is not None and len(t_truth):
        paired = paired_with_truth(t, est, t_truth)
        if paired is not None:
            out.append(error_svg(t_truth - t_truth[0], np.hypot(*(paired[:, :2] - truth[:, :2]).T)))
    from slamreplay.api.web.compare_plots import nees_svg, ordinal, robot_nees

    if (nees := robot_nees(run_dir)) is not None:  # its NEES over time, as the compare page draws it
        every = f" (every {ordinal(nees.stride)} of {nees.steps:,} scans)" if nees.stride > 1 else ""
        out.append(nees_svg([("estimate", nees.t, nees.values)], [nees],
                            f"robot pose NEES over time{every}; shaded: where a consistent filter's NEES lies"))
    return out


def _timing(job: Any) -> dict[str, str]:
    """Percent, elapsed time and an estimate of the time left (from the progress so far) of a running job."""
    if job.started is None:
        return {"percent": f"{100 * job.progress:.0f}", "elapsed": "", "eta": ""}
    elapsed = time.time() - job.started
    eta = elapsed * (1 - job.progress) / job.progress if job.progress > 0.01 else None
    return {"percent": f"{100 * job.progress:.0f}", "elapsed": duration_text(elapsed),
            "eta": "" if eta is None else duration_text(eta)}


def job_ctx(request: Request, jobs: JobService, job_id: str) -> dict[str, Any]:
    """Everything ``_job.html`` draws of job ``job_id`` (NotFoundError when unknown)."""
    job = jobs.get(job_id)
    run_dir = jobs.run_dir(job_id)
    rec = jobs.store.get_recording(job.recording_id)
    ctx: dict[str, Any] = {"job": job, "active": job.status in ACTIVE, "metrics": [], "manifest": None,
                           "plots": [], "recording_name": rec.filename if rec is not None else "",
                           "timing": _timing(job)}
    with contextlib.suppress(OSError, json.JSONDecodeError):
        ctx["manifest"] = json.loads((run_dir / "manifest.json").read_text())
    if job.status == "running":  # the run so far (its live file), and the viewer following its .rrd as it grows
        from slamreplay.api.web.live_view import live_ctx

        ctx["live"] = live_ctx(run_dir)
        ctx["rerun"] = viewer_href(str(request.base_url), link_secret(request), f"/jobs/{job_id}/live.rrd")
        ctx["rerun_live"] = True
    if job.status == "succeeded":
        ctx["metrics"] = metric_rows(run_dir, job.pipeline)
        ctx["rerun"] = viewer_href(str(request.base_url), link_secret(request), f"/jobs/{job_id}/run.rrd")
        ctx["plots"] = plots(run_dir)
    ctx["config"] = config_rows(ctx["manifest"], job.config)
    ctx["files"] = run_files(run_dir)
    ctx["log"] = log_tail(run_dir)
    ctx["people"] = job_people(jobs.store, job_id)
    return ctx


def install_job_files(dependencies: list[Any]) -> APIRouter:
    """The route serving a run's files to the page (behind ``dependencies``: the page's session check)."""
    files = APIRouter(dependencies=[Depends(d) for d in dependencies], include_in_schema=False)

    @files.get("/ui/jobs/{job_id}/files/{name}")
    def job_file(job_id: JobPath, name: FileName, jobs: JobsDep) -> FileResponse:
        """One file of the run directory: the name is one plain file name, and it must resolve inside the
        directory (no path, no link out of it)."""
        jobs.get(job_id)
        run_dir = jobs.run_dir(job_id).resolve()
        path = (run_dir / name).resolve()
        if path.parent != run_dir or not path.is_file() or re.fullmatch(r"\.+", name):
            raise NotFoundError(f"job {job_id} has no file {name}")
        media = TEXT_TYPES.get(path.suffix, "application/octet-stream")
        return FileResponse(path, media_type=media, filename=name,
                            content_disposition_type="inline" if path.suffix in TEXT_TYPES else "attachment")

    return files
