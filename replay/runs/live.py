"""A running run's live side channel: what it has done so far, in ``RUN_DIR/.live.json.partial``.

While a run replays, the engine calls ``LiveWriter.update`` at most every ``period_s`` seconds of wall time
(``slamreplay.replay.engine.loop.replay``'s ``live``); the writer replaces the file whole (a reader never sees
half of it): the messages replayed, the recording time reached, the estimated trajectory so far and the
ground truth seen (each thinned to at most ``MAX_POSES`` poses), the position error against that truth
(now, and as the RMS so far: ``ape_rmse_m``'s formula over the estimate so far), and each scalar the
pipeline has logged under ``metrics/`` (last value, count, mean, min, max), caught by ``MetricTap`` on
its way to the run's observer.

The file is a view, not a result: it holds a wall-clock ``updated_unix`` stamp (when it was written) and
nothing of it reaches ``metrics.json``, ``manifest.json`` or ``run.rrd`` (the tap forwards every call
unchanged). Its name is a temporary one (hidden, ``.partial``): a sweep or a retry of a killed run treats it
as the run's half-done file, and ``close`` removes it when the run ends, as the live log is: a finished
run's page draws its plots from its final files.
"""

from __future__ import annotations

import contextlib
import json
import math
import time
from pathlib import Path
from typing import Any

import numpy as np

from slamreplay.algorithms.observe import Observation, Scalar
from slamreplay.recorder.files import replacing
from slamreplay.replay.engine.pipeline import Pipeline, ReplayObserver
from slamreplay.replay.evaluation.metrics import truth_at

LIVE_FILE = ".live.json.partial"
LIVE_FORMAT = 1
MAX_POSES = 300  # per curve: enough for a plot, small enough to rewrite every second
METRICS_PREFIX = "metrics/"


def _num(v: float) -> float | None:
    """A float for JSON, 6 significant digits; None for NaN and infinities."""
    return float(f"{v:.6g}") if math.isfinite(v) else None


def thin_index(n: int, most: int = MAX_POSES) -> np.ndarray:
    """At most ``most`` evenly spread indices of ``n`` rows, the first and last kept."""
    if n <= most:
        return np.arange(n)
    return np.unique(np.linspace(0, n - 1, most).round().astype(np.int64))


class MetricTap:
    """An observer that forwards every call to ``inner`` and keeps running statistics of the scalars logged
    under ``metrics/`` (last, count, sum, min, max per path): what a live page shows of the pipeline's own
    series. Forwarding is all it does to the run's observer: the run's ``.rrd`` is the same with or without."""

    def __init__(self, inner: ReplayObserver) -> None:
        self.inner = inner
        self.step, self.sensor_time_ns = inner.step, inner.sensor_time_ns
        self.series: dict[str, list[float]] = {}  # path -> [last, n, sum, min, max]

    def set_time(self, step: int, sensor_time_ns: int) -> None:
        self.step, self.sensor_time_ns = step, sensor_time_ns
        self.inner.set_time(step, sensor_time_ns)

    def log(self, path: str, item: Observation) -> None:
        if type(item) is Scalar and path.startswith(METRICS_PREFIX):
            v = float(item.value)
            s = self.series.get(path)
            if s is None:
                self.series[path] = [v, 1.0, v, v, v]
            else:
                s[0], s[1], s[2], s[3], s[4] = v, s[1] + 1.0, s[2] + v, min(s[3], v), max(s[4], v)
        self.inner.log(path, item)

    def log_static(self, path: str, item: Observation) -> None:
        self.inner.log_static(path, item)

    def send_series(self, path: str, steps: np.ndarray, times_ns: np.ndarray, values: np.ndarray) -> None:
        self.inner.send_series(path, steps, times_ns, values)

    def __getattr__(self, name: str) -> Any:  # anything else an observer offers (send_property, ...)
        return getattr(self.inner, name)


class LiveWriter:
    """Writes ``path`` (``RUN_DIR/LIVE_FILE``) as the run goes; see the module docstring."""

    def __init__(self, path: Path, period_s: float = 1.0) -> None:
        self.path = path
        self.period_s = period_s
        self.tapped: MetricTap | None = None
        self.failed = False

    def tap(self, observer: ReplayObserver) -> ReplayObserver:
        """``observer`` with its ``metrics/`` scalars counted for the live file."""
        self.tapped = MetricTap(observer)
        return self.tapped

    def update(self, done: int, total: int, t0_ns: int, sensor_time_ns: int, pipeline: Pipeline,
               t_truth_ns: list[int], truth: list[np.ndarray]) -> None:
        """Rewrite the file: ``done`` of ``total`` messages replayed, at ``sensor_time_ns`` (the replay started
        at ``t0_ns``); the pipeline's trajectory so far, and the ground truth seen so far (lists the engine
        keeps, read here, never changed). A live view never fails a run: an error here stops the live file."""
        if self.failed:
            return
        try:
            doc = self._doc(done, total, t0_ns, sensor_time_ns, pipeline, t_truth_ns, truth)
            with replacing(self.path, sync=False) as tmp:  # no fsync: a view, rewritten every second
                tmp.write_text(json.dumps(doc, separators=(",", ":"), allow_nan=False))
        except Exception:  # noqa: BLE001 -- a half-built pipeline's trajectory, a full disk: the run goes on
            self.failed = True
            with contextlib.suppress(OSError):
                self.path.unlink(missing_ok=True)

    def close(self) -> None:
        """The run has ended: remove the file (the run's own files say the rest)."""
        with contextlib.suppress(OSError):
            self.path.unlink(missing_ok=True)

    def _doc(self, done: int, total: int, t0_ns: int, sensor_time_ns: int, pipeline: Pipeline,
             t_truth_ns: list[int], truth: list[np.ndarray]) -> dict[str, Any]:
        doc: dict[str, Any] = {
            "format": LIVE_FORMAT, "updated_unix": round(time.time(), 3),  # when written: not a result
            "pipeline": pipeline.name, "messages_done": done, "messages_total": total,
            "sensor_time_s": _num((sensor_time_ns - t0_ns) / 1e9), "trajectory": None, "truth": None,
            "error": None, "online": {}, "series": {}}
        k = len(t_truth_ns)  # the engine appends as it goes: read a prefix of a fixed length
        t_gt = np.asarray(t_truth_ns[:k], np.int64)
        gt = np.stack(truth[:k]).astype(np.float64) if k else np.zeros((0, 3))
        if k:
            i = thin_index(k)
            doc["truth"] = {"t_s": [_num((t - t0_ns) / 1e9) for t in t_gt[i]],
                            "xy": [[_num(x), _num(y)] for x, y in gt[i, :2]]}
        traj = pipeline.trajectory()
        if traj is not None and len(traj[0]):
            t_est, est = np.asarray(traj[0], np.int64), np.asarray(traj[1], np.float64).reshape(-1, 3)
            i = thin_index(len(t_est))
            doc["trajectory"] = {"t_s": [_num((t - t0_ns) / 1e9) for t in t_est[i]],
                                 "xy": [[_num(x), _num(y)] for x, y in est[i, :2]]}
            if k:
                mask, ref = truth_at(t_est, t_gt, gt)
                if len(ref):
                    err = np.hypot(*(est[mask, :2] - ref[:, :2]).T)
                    t_err = t_est[mask]
                    doc["online"] = {"position_error_m": _num(float(err[-1])),
                                     "ape_rmse_m": _num(float(np.sqrt(np.mean(err ** 2))))}
                    j = thin_index(len(err))
                    doc["error"] = {"t_s": [_num((t - t_err[0]) / 1e9) for t in t_err[j]],
                                    "m": [_num(float(e)) for e in err[j]]}
        if self.tapped is not None:
            doc["series"] = {path[len(METRICS_PREFIX):]: {"last": _num(s[0]), "n": int(s[1]),
                                                          "mean": _num(s[2] / s[1]), "min": _num(s[3]),
                                                          "max": _num(s[4])}
                             for path, s in sorted(self.tapped.series.items())}
        return doc


def read_live(run_dir: Path) -> dict[str, Any] | None:
    """The live file of a running run in ``run_dir``, or None (none yet, ended, unreadable, other format)."""
    try:
        doc = json.loads((run_dir / LIVE_FILE).read_text())
    except (OSError, ValueError):
        return None
    return doc if isinstance(doc, dict) and doc.get("format") == LIVE_FORMAT else None
