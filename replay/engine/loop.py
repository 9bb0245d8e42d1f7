"""The replay engine: synchronous, one message at a time, in replay order.

Each message is handed to the pipeline before the next one is read; there are no threads,
queues or clocks in the loop. The observer's time is set from the message (``step`` = its
index in replay order, ``sensor_time`` = its log_time) before the pipeline sees it.
"""

from __future__ import annotations

import itertools
import time
from collections.abc import Callable, Iterable, Iterator, Mapping
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np

from slamreplay.algorithms.common import se2
from slamreplay.algorithms.observe import Text
from slamreplay.recorder.messages import TOPIC_GROUND_TRUTH_POSE
from slamreplay.replay.engine.pipeline import Pipeline, ReplayContext, ReplayObserver, pipelines_fitting
from slamreplay.replay.engine.reader import Envelope, RecordingReader
from slamreplay.replay.engine.trajectory import trajectory_artifacts
from slamreplay.replay.errors import ReplayError

Progress = Callable[[int, int], None]


class LiveSink(Protocol):
    """What a running replay reports as it goes, for people watching it (``slamreplay.replay.runs.live``): called
    at most every ``period_s`` seconds of wall time and once at the end; it returns nothing to the replay and
    changes none of its results (the wall clock only paces it)."""

    period_s: float

    def tap(self, observer: ReplayObserver) -> ReplayObserver: ...

    def update(self, done: int, total: int, t0_ns: int, sensor_time_ns: int, pipeline: Pipeline,
               t_truth_ns: list[int], truth: list[np.ndarray]) -> None: ...


@dataclass(frozen=True, slots=True)
class ReplayStats:
    metrics: dict[str, float]
    messages: int
    step_durations_s: np.ndarray | None  # only with log_timings; one per message, in replay order
    step_times_ns: np.ndarray | None  # the log_time of each of those messages
    timings: dict[str, float] = field(default_factory=dict)  # the pipeline's own (Pipeline.timings), seconds
    artifacts: dict[str, bytes] = field(default_factory=dict)  # files for the run directory (Pipeline.artifacts)
    # the pipeline's trajectory (times ns, N x 3 poses) and the recording's ground truth seen during the replay,
    # for evaluation.score, which adds the trajectory metrics; None when there is none
    trajectory: tuple[np.ndarray, np.ndarray] | None = None
    truth: tuple[np.ndarray, np.ndarray] | None = None
    provenance: dict[str, Any] = field(default_factory=dict)  # Pipeline.provenance: manifest.json's pipeline_run


def check_topics(reader: RecordingReader, pipeline: type[Pipeline]) -> list[str]:
    """The pipeline's topics present in the recording; ReplayError when a required one is missing or unreadable."""
    present = reader.info.logical_topics()
    for topic in pipeline.required_topics:
        if topic not in present:  # the reader's error says how to map it; and which pipelines fit as it is
            try:
                reader.decoder(topic)
            except ReplayError as err:
                counts = {t: info.message_count for t, info in present.items()}
                fitting = [name for name in pipelines_fitting(counts) if name != pipeline.name]
                raise ReplayError(f"{err}; or replay it through a pipeline its topics fit: "
                                  f"{', '.join(fitting)}" if fitting else str(err)) from None
        reader.decoder(topic)  # raises with what is missing and how to map it
        if present[topic].message_count == 0:
            msg = f"{reader.path.name}: topic {topic}, which pipeline {pipeline.name} needs, has no messages"
            raise ReplayError(msg)
    optional = [t for t in pipeline.optional_topics if t in present]
    for topic in optional:
        reader.decoder(topic)
    return list(pipeline.required_topics) + optional


def start_pose(reader: RecordingReader, start_topic: str, start_ns: int | None,
               end_ns: int | None) -> tuple[int, np.ndarray | None]:
    """Log time of the first ``start_topic`` message, and the ground-truth pose then (None without).

    Ground truth is interpolated between the messages around that time, and clamped to the
    first or last one outside its span.
    """
    first = next(reader.messages([start_topic], start_ns=start_ns, end_ns=end_ns), None)
    if first is None:
        raise ReplayError(f"{reader.path.name} has no {start_topic} message in the chosen time window")
    t0 = first.log_time_ns
    if TOPIC_GROUND_TRUTH_POSE not in reader.info.logical_topics():
        return t0, None
    truth = ((env.log_time_ns, env.msg.xy_yaw) for env in  # type: ignore[union-attr]
             reader.messages([TOPIC_GROUND_TRUTH_POSE], start_ns=start_ns))
    return t0, _truth_at(t0, truth)


START_BUFFER = 10_000  # messages held while the start pose is found in the replay stream itself


def start_from_stream(reader: RecordingReader, stream: Iterator[Envelope], topics: list[str], start_topic: str,
                      start_ns: int | None, end_ns: int | None) -> tuple[int, np.ndarray | None, list[Envelope]]:
    """``start_pose``, found in the replay stream: (t0, pose, the messages read to find it).

    The replay stream holds the first ``start_topic`` message and, when the pipeline reads ground
    truth, the ground truth around it: reading them there, and replaying the messages held, saves
    two more passes over the start of the file (a chunk each). When the answer is not in the
    stream's first START_BUFFER messages (ground truth that starts late, or ends before t0 within
    the window), ``start_pose`` reads the file again, with the same result.
    """
    has_truth = TOPIC_GROUND_TRUTH_POSE in reader.info.logical_topics()
    held: list[Envelope] = []
    t0: int | None = None
    if not has_truth or TOPIC_GROUND_TRUTH_POSE in topics:
        for env in stream:
            held.append(env)
            if t0 is None and env.topic == start_topic:
                t0 = env.log_time_ns
                if not has_truth:
                    return t0, None, held
            if t0 is not None and env.topic == TOPIC_GROUND_TRUTH_POSE and env.log_time_ns >= t0:
                truth = [(e.log_time_ns, e.msg.xy_yaw) for e in held  # type: ignore[union-attr]
                         if e.topic == TOPIC_GROUND_TRUTH_POSE]
                return t0, _truth_at(t0, truth), held
            if len(held) >= START_BUFFER:
                break
    t0, pose = start_pose(reader, start_topic, start_ns, end_ns)
    return t0, pose, held


def _truth_at(t0: int, truth: Iterable[tuple[int, np.ndarray]]) -> np.ndarray | None:
    """The ground-truth pose at t0 from (log_time, pose) in replay order: interpolated between the messages
    around t0, the first one when none is before it, the last one when none is at or after it."""
    before: tuple[int, np.ndarray] | None = None
    for t, pose in truth:
        if t >= t0:
            if before is None or t == t0:
                return pose
            tb, pb = before
            return np.asarray(se2.interpolate([float(t0 - tb)], [0.0, float(t - tb)], np.stack([pb, pose]))[0])
        before = (t, pose)
    return None if before is None else before[1]


def replay(reader: RecordingReader, pipeline_cls: type[Pipeline], config: Any, observer: ReplayObserver, *,
           seed: int, start_ns: int | None = None, end_ns: int | None = None, log: Callable[[str], None],
           progress: Progress | None = None, log_timings: bool = False,
           config_sources: Mapping[str, str] | None = None, live: LiveSink | None = None) -> ReplayStats:
    """Run one pipeline over a recording: its own metrics, its trajectory and the ground truth seen.

    The trajectory metrics (APE, RPE) are evaluation's: ``slamreplay.replay.evaluation.score.score(stats, cls)``.
    ``live``: told what the replay has done so far, about every ``live.period_s`` seconds (`LiveSink`).
"""
    if live is not None:
        observer = live.tap(observer)
    topics = check_topics(reader, pipeline_cls)
    stream = reader.messages(topics, start_ns=start_ns, end_ns=end_ns)
    t0, T_world_start, held = start_from_stream(reader, stream, topics, pipeline_cls.start_topic, start_ns, end_ns)
    total = sum(t.message_count for t in reader.info.topics if t.logical_topic in topics)
    ctx = ReplayContext(reader.info, seed, np.random.default_rng(seed), observer, T_world_start, t0, log,
                        dict(config_sources or {}))
    observer.set_time(0, t0)
    if T_world_start is None and not pipeline_cls.multi_robot:  # a multi-robot pipeline finds each robot's start
        log("no ground truth at the start: the estimate starts at the origin")
    pipeline = pipeline_cls(config, ctx)
    durations: list[float] = []
    times: list[int] = []
    n = 0
    every = max(1, total // 200)
    t_gt: list[int] = []
    gt: list[np.ndarray] = []
    live_next = 0.0
    for env in itertools.chain(held, stream):
        observer.set_time(env.index, env.log_time_ns)
        if env.topic == TOPIC_GROUND_TRUTH_POSE:  # kept for the trajectory metrics
            t_gt.append(env.log_time_ns)
            gt.append(env.msg.xy_yaw)  # type: ignore[union-attr]
        if log_timings:
            tic = time.perf_counter()
            pipeline.step(env)
            durations.append(time.perf_counter() - tic)
            times.append(env.log_time_ns)
        else:
            pipeline.step(env)
        n += 1
        if progress is not None and n % every == 0:
            progress(n, total)
        if live is not None and time.monotonic() >= live_next:
            live.update(n, total, t0, env.log_time_ns, pipeline, t_gt, gt)
            live_next = time.monotonic() + live.period_s
    if live is not None:
        live.update(n, total, t0, observer.sensor_time_ns, pipeline, t_gt, gt)
    if progress is not None:
        progress(n, n)
    metrics = pipeline.finish()
    unknown = set(metrics) - set(pipeline_cls.metrics)
    if unknown:
        raise RuntimeError(f"pipeline {pipeline_cls.name} returned metrics without a spec: {sorted(unknown)}")
    trajectory = pipeline.trajectory()
    truth = (np.asarray(t_gt, np.int64), np.stack(gt).astype(np.float64)) if t_gt else None
    return ReplayStats(metrics, n, np.asarray(durations) if log_timings else None,
                       np.asarray(times, np.int64) if log_timings else None, pipeline.timings(),
                       {**trajectory_artifacts(trajectory), **pipeline.artifacts()}, trajectory, truth,
                       pipeline.provenance())


def text_logger(observer: ReplayObserver, lines: list[str]) -> Callable[[str], None]:
    """A ``log(text)`` that writes to the run's log lines and the ``log`` entity, stamped with replay time."""

    def log(text: str) -> None:
        lines.append(f"[step {observer.step} | sensor_time {observer.sensor_time_ns} ns] {text}")
        observer.log("log", Text(text))

    return log
