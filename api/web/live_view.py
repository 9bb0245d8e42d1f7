"""What a running job's page shows of the run so far: its live file (``slamreplay.replay.runs.live``) as rows
and server-drawn SVGs (the trajectory so far against the ground truth seen, the position error so far), and
the live ``.rrd`` stream "Open in Rerun" follows while it runs.

The page's ``[data-live]`` block is fetched again every 2 s while the job is active, so both come back fresh.
The stream sends the run's ``.rrd`` as the run writes it, then the rest once the run has closed it: the
Rerun web viewer reads an HTTP ``.rrd`` as it arrives, so it shows the run growing and keeps all of it.
"""

from __future__ import annotations

import asyncio
import os
from collections.abc import AsyncIterator, Callable
from pathlib import Path
from typing import Any

import numpy as np

RRD_PARTIAL = ".run.rrd.partial"  # replay.runs.run writes run.rrd under this name, renamed when complete
READ_BLOCK = 1 << 16
POLL_S = 0.25


def live_ctx(run_dir: Path) -> dict[str, Any] | None:
    """The live file of the run in ``run_dir`` for ``_job.html``: steps, recording time, online metrics, the
    pipeline's series and up to two SVGs; None when there is none (not started, ended, another storage)."""
    from slamreplay.api.web.svg_plots import error_svg, trajectory_svg
    from slamreplay.replay.runs.live import read_live

    doc = read_live(run_dir)
    if doc is None:
        return None
    rows = []
    online = doc.get("online") or {}
    for name, words in (("position_error_m", "position error now (against the ground truth seen)"),
                        ("ape_rmse_m", "position error RMS so far (ape_rmse_m's formula)")):
        if online.get(name) is not None:
            rows.append({"name": name, "last": online[name], "n": None, "mean": None, "min": None, "max": None,
                         "meaning": words})
    for name, s in sorted((doc.get("series") or {}).items()):
        rows.append({"name": name, **s, "meaning": "logged by the pipeline (metrics/" + name + ")"})
    plots = []
    traj, truth, err = doc.get("trajectory"), doc.get("truth"), doc.get("error")
    est = _xy(traj)
    if est is not None:
        plots.append(trajectory_svg(est, _xy(truth)))
    if err and len(err.get("m") or []) > 1:
        t = np.asarray(err["t_s"], float)
        e = np.asarray([np.nan if v is None else v for v in err["m"]], float)
        ok = np.isfinite(t) & np.isfinite(e)
        if ok.sum() > 1:
            plots.append(error_svg(t[ok], e[ok]))
    total = doc.get("messages_total") or 0
    return {"done": doc.get("messages_done", 0), "total": total, "sensor_time_s": doc.get("sensor_time_s"),
            "rows": rows, "plots": plots, "poses": len(traj["xy"]) if traj else 0}


def _xy(curve: dict[str, Any] | None) -> np.ndarray | None:
    """A curve's (n, 2) finite points, None without any."""
    if not curve or not curve.get("xy"):
        return None
    xy = np.asarray([[np.nan if v is None else v for v in p] for p in curve["xy"]], float).reshape(-1, 2)
    xy = xy[np.isfinite(xy).all(axis=1)]
    return xy if len(xy) else None


async def follow_rrd(run_dir: Path, running: Callable[[], bool], poll_s: float = POLL_S,
                     wait_start_s: float = 600.0, prefix: bytes = b"") -> AsyncIterator[bytes]:
    """The bytes of the run's ``.rrd`` as they are written, ending once the run has ended and all is sent;
    ``prefix`` first (a running job's: the layout that follows the newest step,
    ``slamreplay.replay.engine.views.following_layout_rrd``).

    The run writes ``RRD_PARTIAL`` and renames it to ``run.rrd`` when complete: the file opened here is the
    same file after the rename, so reading it on to its end, once ``running()`` says no, sends the whole
    recording (footer included). ``running`` (a job store read) runs in a thread, off the event loop. A run
    that ends before writing any (it failed early) sends nothing; a client that goes away ends it (the server
    stops iterating).
    """
    if prefix:
        yield prefix
    partial, final = run_dir / RRD_PARTIAL, run_dir / "run.rrd"
    fd = None
    waited = 0.0
    while fd is None:
        for path in (final, partial):
            try:
                fd = os.open(path, os.O_RDONLY)
                break
            except OSError:
                continue
        if fd is None:
            if not await asyncio.to_thread(running) or waited > wait_start_s:
                return
            await asyncio.sleep(poll_s)
            waited += poll_s
    try:
        while True:
            block = os.read(fd, READ_BLOCK)
            if block:
                yield block
                continue
            if not await asyncio.to_thread(running):  # the writer is done (renamed, removed or killed): the rest
                block = os.read(fd, READ_BLOCK)
                while block:
                    yield block
                    block = os.read(fd, READ_BLOCK)
                return
            await asyncio.sleep(poll_s)
    finally:
        os.close(fd)
