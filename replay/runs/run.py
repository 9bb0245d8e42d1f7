"""A run: one recording through one pipeline into a run directory.

``RUN_DIR/`` holds ``run.rrd`` (with the pipeline's blueprint), ``metrics.json`` (only
deterministic values: two runs give byte-identical files), ``manifest.json`` (what ran,
on what, with which code, how it ended, timings) and ``log.txt``. Every file is written
under a temporary name and renamed when complete; the manifest is written last. A failed
run leaves a manifest with ``status: failed`` and the reason, never a metrics.json; a retry
into the same directory replaces it (``prepare_run_dir``), a succeeded run is never replaced.
"""

from __future__ import annotations

import contextlib
import errno
import hashlib
import json
import os
import platform
import re
import resource
import time
import traceback
import uuid
from collections.abc import Mapping
from dataclasses import dataclass
from datetime import datetime, timezone
from importlib import metadata
from pathlib import Path
from typing import Any

import numpy as np

from slamreplay.recorder.errors import RecorderError
from slamreplay.recorder.files import atomic_write
from slamreplay.recorder.version import git_commit, version
from slamreplay.replay.engine.loop import Progress, replay, text_logger
from slamreplay.replay.engine.observer import RerunObserver
from slamreplay.replay.engine.pipeline import (
    Pipeline,
    all_robots_topic_map,
    config_dict,
    config_hash,
    get_pipeline,
    pipeline_origin,
    recording_sensor_model,
    resolve_layers,
    robot_topic_map,
    robots_in,
)
from slamreplay.replay.engine.reader import RecordingReader
from slamreplay.replay.engine.recording_file import check_recording
from slamreplay.replay.errors import ReplayError
from slamreplay.replay.evaluation import metrics as metrics_mod
from slamreplay.replay.evaluation.score import metric_specs, score
from slamreplay.replay.runs.live import LIVE_FILE, LiveWriter

MANIFEST_FORMAT = 1
LIBRARIES = ("rerun-sdk", "numpy", "scipy", "opencv-contrib-python-headless", "mcap", "protobuf")


@dataclass(frozen=True, slots=True)
class RunResult:
    run_dir: Path
    run_id: str
    status: str
    metrics: dict[str, float]
    manifest: dict[str, Any]



def sha256_file(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def library_versions() -> dict[str, str]:
    out = {"python": platform.python_version()}
    for name in LIBRARIES:
        try:
            out[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            out[name] = "not installed"
    return out


RUN_FILES = frozenset({"run.rrd", "metrics.json", "manifest.json", "log.txt"})
LIVE_LOG = ".log.txt.partial"  # the log as it is written, for a live tail (the service's job page); gone at the end


class LiveLog(list[str]):
    """The run's log lines; each is also appended to ``LIVE_LOG`` as it comes, so that a running job's log can be
    followed. ``log.txt`` is still written whole at the end, and the live copy removed."""

    def __init__(self, path: Path, first: str) -> None:
        super().__init__()
        self.path = path
        self._file: Any = None
        self.append(first)

    def append(self, line: str) -> None:
        super().append(line)
        try:
            if self._file is None:
                self._file = open(self.path, "a", encoding="utf-8")  # noqa: SIM115 (kept open: a line per call)
            self._file.write(line + "\n")
            self._file.flush()
        except OSError:
            pass  # the live copy is a convenience: log.txt is written at the end whatever happens to it

    def close(self) -> None:
        """Stop the live copy and remove it."""
        if self._file is not None:
            self._file.close()
            self._file = None
        self.path.unlink(missing_ok=True)
ARTIFACT_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]{0,127}")


def write_artifacts(out_dir: Path, artifacts: Mapping[str, bytes]) -> dict[str, dict[str, Any]]:
    """Write a pipeline's extra files atomically; their names, sizes and sha256 for the manifest."""
    listed: dict[str, dict[str, Any]] = {}
    for name, data in sorted(artifacts.items()):
        if not ARTIFACT_NAME.fullmatch(name) or name in RUN_FILES or name.endswith(".partial"):
            raise ValueError(f"pipeline artifact name {name!r} is not a plain file name of its own")
        atomic_write(out_dir / name, data)
        listed[name] = {"bytes": len(data), "sha256": hashlib.sha256(data).hexdigest()}
    return listed


def _failed_run_files(out_dir: Path, manifest: Mapping[str, Any]) -> list[Path]:
    """The files a failed run wrote in ``out_dir`` (its own files, listed artifacts, temporary names);
    ReplayError naming any other file, which is not the run's to delete."""
    artifacts = manifest.get("artifacts")
    own = set(RUN_FILES) | (set(artifacts) if isinstance(artifacts, Mapping) else set())
    ours, foreign = [], []
    for entry in sorted(out_dir.iterdir()):
        name = entry.name
        temporary = name.startswith(".") and (name.endswith(".tmp") or name.endswith(".partial"))
        if entry.is_file() and not entry.is_symlink() and (name in own or temporary):
            ours.append(entry)
        else:
            foreign.append(name)
    if foreign:
        raise ReplayError(f"{out_dir} holds a failed run and files it did not write ({', '.join(foreign[:5])}); "
                          f"move them away to retry into it, or choose a new --out")
    return ours


def _what_is_there(out_dir: Path, manifest: Any) -> str:
    if isinstance(manifest, dict):
        return f"a run with status {manifest.get('status')!r}"
    if all(p.name.startswith(".") and p.name.endswith((".partial", ".tmp")) for p in out_dir.iterdir()):
        return "an unfinished run (no manifest.json: running now, or killed; delete it if nothing writes it)"
    return "files that are not a run (no manifest.json)"


DISK_FULL = (errno.ENOSPC, errno.EDQUOT)


def _disk_full(out_dir: Path) -> str:
    return (f"no space left on the device while writing {out_dir}: the run did not finish and is not listed as "
            f"finished; free space and run it again into a new --out")


def prepare_run_dir(out_dir: Path) -> None:
    """Create ``out_dir`` (and its parents) for a new run.

    A run never overwrites another: ReplayError when ``out_dir`` holds a succeeded or running run,
    or anything that is not a run. A failed or interrupted run (manifest ``status: failed`` or
    ``interrupted``) never blocks its retry: its files are removed and the directory reused, so the
    same ``--out`` works once the cause is fixed.
    """
    if out_dir.exists() and not out_dir.is_dir():
        raise ReplayError(f"{out_dir} exists and is not a directory: choose a new --out")
    if out_dir.is_dir() and any(out_dir.iterdir()):
        try:
            manifest = json.loads((out_dir / "manifest.json").read_text())
        except (OSError, ValueError):
            manifest = None
        if not isinstance(manifest, dict) or manifest.get("status") not in ("failed", "interrupted"):
            raise ReplayError(f"{out_dir} already exists and holds {_what_is_there(out_dir, manifest)}; a run never "
                              f"overwrites another: choose a new --out")
        for path in _failed_run_files(out_dir, manifest):
            path.unlink()
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise ReplayError(f"cannot create the run directory {out_dir}: {err.strerror}") from err


def _check_robot_chosen(reader: RecordingReader, pipeline_cls: type[Pipeline], robot: str | None) -> None:
    """A multi-robot recording replayed without --robot: say which robots there are instead of "no /odom"."""
    present = reader.info.logical_topics()
    robots = robots_in(reader.info)
    if (robot is None and robots and not pipeline_cls.multi_robot
            and any(t not in present for t in pipeline_cls.required_topics)):
        raise ReplayError(f"{reader.path.name} holds {len(robots)} robots (topics under /robotN/: "
                          f"{', '.join(robots)}); pipeline {pipeline_cls.name} replays one: choose it with --robot N")


def run_recording(recording: str | Path, pipeline: str | type[Pipeline], out_dir: str | Path, *, seed: int = 0,
                  config: Mapping[str, Any] | None = None, topic_map: Mapping[str, str] | None = None,
                  start_ns: int | None = None, end_ns: int | None = None, log_timings: bool = False,
                  progress: Progress | None = None, run_id: str | None = None,
                  preset: str | None = None, robot: str | None = None) -> RunResult:
    """Replay ``recording`` through ``pipeline`` into ``out_dir``.

    Config values come in layers (`slamreplay.replay.engine.pipeline.resolve_layers`): ``config`` (the user's) wins,
    then the ``preset``, then the recording's sensor model, then the pipeline's defaults; the
    manifest records each value's origin under ``config_sources``. ``robot``: which robot of a
    multi-robot recording (topics under ``/robotN/``) to replay, with that robot's sensor model.

    Raises
    ------
    ReplayError
        For bad input. When the pipeline name, config or output directory is wrong, or the
        recording is missing, empty, not an MCAP file or truncated, nothing is written; once
        the run directory exists, a failed run still writes its manifest (``status: failed``,
        ``error``) and log before the error is raised.
    """
    recording, out_dir = Path(recording), Path(out_dir)
    # a class: a pipeline made for this run (`slamreplay evaluate`), its origin in its ``declared_origin``
    pipeline_cls = pipeline if isinstance(pipeline, type) else get_pipeline(pipeline)
    pipeline = pipeline_cls.name
    origin = getattr(pipeline_cls, "declared_origin", None) or pipeline_origin(pipeline)
    resolve_layers(pipeline_cls, config, preset=preset)  # bad keys, values and presets fail before anything is written
    check_recording(recording)  # so does an input that is missing or not a recording: no failed run dir for a typo
    prepare_run_dir(out_dir)
    run_id = run_id or uuid.uuid4().hex
    started = datetime.now(timezone.utc)
    t_wall, t_cpu = time.perf_counter(), time.process_time()
    timings: dict[str, float] = {}
    manifest: dict[str, Any] = {
        "format": MANIFEST_FORMAT, "run_id": run_id, "status": "running", "error": None,
        "recording": {"path": str(recording.resolve()), "sha256": None, "topic_map": dict(topic_map or {})},
        "pipeline": pipeline, "pipeline_origin": dict(origin),
        "config": None, "config_hash": None, "config_sources": None, "preset": preset,
        "seed": seed,
        "window_ns": {"start": start_ns, "end": end_ns},
        "slamreplay": {"version": version(), "git_commit": git_commit()}, "libraries": library_versions(),
        "host": {"platform": platform.platform(), "cpus": os.cpu_count()},
    }
    lines = LiveLog(out_dir / LIVE_LOG, f"slamreplay {version()} ({git_commit()}): {pipeline} on {recording}, "
                                        f"seed {seed}")
    rrd_tmp, rrd = out_dir / ".run.rrd.partial", out_dir / "run.rrd"
    observer: RerunObserver | None = None
    live = LiveWriter(out_dir / LIVE_FILE)  # what a running job's page shows; removed at the end
    values: dict[str, float] = {}
    kept: dict[str, Any] = {}  # artifacts a failed run keeps (an external program's output)
    try:
        tic = time.perf_counter()
        if pipeline_cls.multi_robot:
            if robot is not None:
                raise ReplayError(f"pipeline {pipeline} replays every robot of the recording at once: drop --robot")
            topic_map = {**all_robots_topic_map(RecordingReader(recording).info), **(topic_map or {})}
            manifest["recording"].update(topic_map=dict(topic_map), robot="all")
        elif robot is not None:
            topic_map = {**robot_topic_map(RecordingReader(recording).info, str(robot)), **(topic_map or {})}
            manifest["recording"].update(topic_map=dict(topic_map), robot=str(robot))
        reader = RecordingReader(recording, topic_map)
        _check_robot_chosen(reader, pipeline_cls, robot)
        manifest["recording"]["sha256"] = sha256_file(reader.path)
        manifest["recording"]["messages"] = reader.info.message_count
        manifest["recording"]["metadata"] = reader.info.metadata
        resolved = resolve_layers(pipeline_cls, config, sensor_model=recording_sensor_model(reader.info, robot),
                                 preset=preset)
        cfg = resolved.config
        manifest.update(config=config_dict(cfg), config_hash=config_hash(cfg), config_sources=resolved.sources)
        timings["open_s"] = time.perf_counter() - tic
        observer = RerunObserver(rrd_tmp, run_id, f"{pipeline} on {reader.path.name}", kind=pipeline,
                                 time_origin_ns=reader.info.start_ns)
        observer.set_time(0, reader.info.start_ns)
        observer.send_property("replay", {"pipeline": pipeline, "seed": seed, "config_hash": manifest["config_hash"],
                                          "recording_sha256": manifest["recording"]["sha256"]})
        tic = time.perf_counter()
        log = text_logger(observer, lines)
        log(f"{pipeline} on {reader.path.name} ({reader.info.message_count:,} messages), seed {seed}, "
            f"config {manifest['config_hash'][:12]}")
        stats = score(replay(reader, pipeline_cls, cfg, observer, seed=seed, start_ns=start_ns, end_ns=end_ns, log=log,
                             progress=progress, log_timings=log_timings, config_sources=resolved.sources,
                             live=live), pipeline_cls)
        timings["replay_s"] = time.perf_counter() - tic
        values = stats.metrics
        timings.update({f"pipeline_{k}": v for k, v in stats.timings.items()})
        if stats.step_durations_s is not None and stats.step_times_ns is not None and len(stats.step_durations_s):
            observer.send_series("timings/step_ms", np.arange(len(stats.step_durations_s)), stats.step_times_ns,
                                 stats.step_durations_s * 1e3)
        manifest["messages_replayed"] = stats.messages
        if stats.provenance:
            manifest["pipeline_run"] = stats.provenance
        log(f"finished: {stats.messages:,} messages replayed; " + (", ".join(
            f"{k} {v:.4g}" for k, v in sorted(values.items())) or "no metric applies"))
        specs = metric_specs(pipeline_cls)
        bounds = observer.write_summary(metrics_mod.metrics_markdown(f"{pipeline} on {reader.path.name}", values,
                                                                     specs), pipeline_cls.summary_skip)
        observer.send_layout(pipeline_cls.blueprint(bounds))
        tic = time.perf_counter()
        observer.close()
        observer = None
        os.replace(rrd_tmp, rrd)
        doc = metrics_mod.format_metrics(pipeline, values, specs)
        manifest["artifacts"] = write_artifacts(out_dir, stats.artifacts)
        atomic_write(out_dir / "metrics.json", metrics_mod.dumps(doc))
        timings["write_s"] = time.perf_counter() - tic
        manifest["status"] = "succeeded"
    except (ReplayError, RecorderError) as err:
        manifest.update(status="failed", error=str(err))
        lines.append(f"FAILED: {err}")
        keep = getattr(err, "artifacts", None)  # files a failed pipeline keeps (an external program's output)
        if keep:
            with contextlib.suppress(OSError):  # the error is the run's story; a full disk must not hide it
                manifest["artifacts"] = kept = write_artifacts(out_dir, keep)
        raise ReplayError(str(err)) from err
    except KeyboardInterrupt:  # the user's Ctrl-C: not a fault of slamreplay's (the CLI exits 130)
        manifest.update(status="interrupted", error="interrupted by the user (Ctrl-C)")
        lines.append("INTERRUPTED: by the user (Ctrl-C)")
        raise
    except BaseException as err:
        if isinstance(err, OSError) and err.errno in DISK_FULL:
            msg = _disk_full(out_dir)
            manifest.update(status="failed", error=msg)
            lines.append(f"FAILED: {msg}")
            raise ReplayError(msg) from err
        manifest.update(status="failed", error=f"internal error: {type(err).__name__}: {err}")
        lines.append(f"FAILED: internal error\n{traceback.format_exc()}")
        raise
    finally:
        live.close()
        if observer is not None:
            observer.close()
        if manifest["status"] != "succeeded":  # the directory was empty: what is in it is this run's, half done
            for name in (rrd_tmp.name, rrd.name, "metrics.json", *manifest.get("artifacts", {})):
                if name not in kept:
                    (out_dir / name).unlink(missing_ok=True)
        usage = resource.getrusage(resource.RUSAGE_SELF)
        timings.update(wall_s=time.perf_counter() - t_wall, cpu_s=time.process_time() - t_cpu,
                       max_rss_mib=usage.ru_maxrss / 1024.0)
        manifest["timings"] = {"started_at": started.isoformat(), "finished_at": datetime.now(timezone.utc).isoformat(),
                               **{k: round(v, 6) for k, v in timings.items()}}
        try:
            atomic_write(out_dir / "log.txt", "\n".join(lines) + "\n")
            lines.close()
            atomic_write(out_dir / "manifest.json", json.dumps(manifest, indent=2, sort_keys=True, default=str) + "\n")
        except OSError as err:  # no manifest: diff and compare read the run as unfinished, which it is
            lines.close()
            if err.errno not in DISK_FULL:
                raise
            for name in (rrd.name, "metrics.json", *manifest.get("artifacts", {})):
                (out_dir / name).unlink(missing_ok=True)
            raise ReplayError(_disk_full(out_dir)) from err
    return RunResult(out_dir, run_id, "succeeded", values, manifest)
