"""Observers that replay hands to pipelines and algorithms: Rerun (a run's ``.rrd``) and memory (tests).

Replay sets the time (`set_time`) before each message; algorithms only ``log``. The Rerun
observer turns observations into archetypes under the entity conventions of `slamreplay.replay.engine.views`
(which owns frames, colours and timelines) and, at the end, mirrors the final state of the
map into the static ``summary/`` subtree that a run's first tab shows.

Why every row leaves as an explicit chunk (`send_columns`), never through ``log``: `rerun rrd compare`
puts each file's chunks in the order of their chunk ids, and a chunk id is minted from the wall clock
by the thread that cuts the chunk. Rows given to ``log`` are cut into chunks by the stream's batcher
thread: when a row-count threshold is hit there, at a moment set by thread scheduling (machine load),
its chunk's place among the chunks this thread sends moves; and at a flush, the rows an entity has
pending are split per set of timelines (static or not) and of datatypes in an order drawn from a hash
seeded at random per process, so two runs may emit an entity's static and temporal chunks in
either order. Chunks built here get their ids in this thread, in the order of the calls, so the
same inputs give the same chunks in the same order on any machine, at any load.
"""

from __future__ import annotations

import json
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import rerun as rr
import rerun.blueprint as rrb
from rerun.chunk import Chunk

from slamreplay.algorithms.observe import (
    Bars,
    CovarianceEllipses,
    Image,
    LineStrips,
    Markdown,
    Observation,
    Points,
    Pose,
    Scalar,
    Segments,
    State,
    Text,
)
from slamreplay.replay.engine import views
from slamreplay.replay.engine.views import role_color

GEOMETRY = (Scalar, Pose, Points, LineStrips, Segments, CovarianceEllipses)  # kinds `to_columns` builds in bulk


def deterministic_batcher() -> rr.ChunkBatcherConfig:
    """A batcher that never cuts chunks on its own (no timer, no size or row threshold): the project sends
    its data as explicit chunks (module docstring), and whatever still reaches the batcher (the recording
    name) is flushed only where this thread waits for it (``flush``, ``disconnect``)."""
    return rr.ChunkBatcherConfig.NEVER()


class _Arrow:
    """A ready Arrow array as a component batch (what `rr.ComponentColumn` partitions)."""

    __slots__ = ("array",)

    def __init__(self, array: pa.Array) -> None:
        self.array = array

    def as_arrow_array(self) -> pa.Array:
        return self.array


def row_components(archetypes: Iterable[Any]) -> dict[Any, pa.Array]:
    """One row's component arrays by descriptor, as ``log`` would send them (the first of a repeated one)."""
    out: dict[Any, pa.Array] = {}
    for arch in archetypes:
        for batch in arch.as_component_batches():
            array = batch.as_arrow_array()
            if array is not None:
                out.setdefault(batch.component_descriptor(), array)
    return out


def row_groups(rows: Sequence[dict[Any, pa.Array]]) -> list[tuple[int, int, list[rr.ComponentColumn]]]:
    """Runs ``[i, j)`` of consecutive rows holding the same components, each as one column per component."""
    groups = []
    i = 0
    while i < len(rows):
        keys = list(rows[i])
        j = i + 1
        while j < len(rows) and list(rows[j]) == keys:
            j += 1
        cols = [rr.ComponentColumn(k, _Arrow(pa.concat_arrays([r[k] for r in rows[i:j]])),
                                   lengths=[len(r[k]) for r in rows[i:j]]) for k in keys]
        groups.append((i, j, cols))
        i = j
    return groups


def send_static(stream: rr.RecordingStream, path: str, *archetypes: Any) -> None:
    """What ``stream.log(path, *archetypes, static=True)`` logs, as one explicit chunk made in this thread."""
    for _, _, cols in row_groups([row_components(archetypes)]):
        stream.send_columns(path, indexes=[], columns=cols)


def ellipse_points(mean: np.ndarray, cov: np.ndarray, n_sigma: float = 2.0, n: int = 32) -> np.ndarray:
    """Closed polyline (n + 1, 2) of the ``n_sigma`` ellipse of a 2D Gaussian."""
    w, v = np.linalg.eigh(0.5 * (cov + cov.T))
    t = np.linspace(0.0, 2.0 * np.pi, n + 1)
    circle = np.stack([np.cos(t), np.sin(t)], 1) * (n_sigma * np.sqrt(np.maximum(w, 0.0)))
    return np.asarray(mean + circle @ v.T)


class RerunObserver:
    """Logs observations to one explicit ``rr.RecordingStream`` saved to a ``.rrd`` file.

    The wall-clock ``log_time`` timeline is off; timelines are ``step`` (message index in
    replay order) and ``sensor_time`` (the message's log_time). Every row is buffered per entity and
    kind and sent as columns every ``flush_rows`` rows (a Python ``rr.log`` call costs ~0.3 ms, a
    column row ~0.02 ms), images one by one (a chunk per image, as Rerun advises for large rows), static
    data at once; each as an explicit chunk, never through the batcher (module docstring). The content
    is the same as logging row by row, and the chunks depend on the rows only. 256 rows measured 8-10 %
    less CPU than 1024 on the replay benchmark: fewer buffered rows survive into the garbage collector's
    older generations, and a column of 256 rows still costs little per row.
    """

    def __init__(self, path: Path, recording_id: str, recording_name: str | None = None, flush_rows: int = 256,
                 *, kind: str = "run", time_origin_ns: int = 0) -> None:
        self.stream = rr.RecordingStream(views.app_id(kind), recording_id=recording_id, send_properties=False,
                                         batcher_config=deterministic_batcher())
        self.stream.set_log_time_enabled(False)
        self.stream.save(path)
        self.step, self.sensor_time_ns = 0, 0
        self.time_origin_ns = time_origin_ns
        self.flush_rows = flush_rows
        self._buffers: dict[tuple[str, type], list[tuple[int, int, Observation]]] = {}
        self._last: dict[str, Observation] = {}  # the latest item of each map entity (for the summary)
        self._series: set[str] = set()
        self._states: dict[str, set[str]] = {}  # state-timeline entity -> the states it entered
        if recording_name:
            # The SDK sends the name only as a row through the batcher: flushed here, while nothing else is pending.
            self.stream.send_recording_name(recording_name)
            self.stream.flush()
        for root in views.MAP_ROOTS:
            send_static(self.stream, root, views.MAP_FLIP)

    def set_time(self, step: int, sensor_time_ns: int) -> None:
        # Only stored: every row is sent with its own time columns, none with the stream's time.
        self.step, self.sensor_time_ns = step, sensor_time_ns

    def log(self, path: str, item: Observation) -> None:
        if path.startswith("world/"):
            self._last[path] = item
        kind = type(item)
        key = (path, kind)
        rows = self._buffers.get(key)
        if rows is None:
            if kind is Scalar:
                self._style_series(path)
            rows = self._buffers[key] = []
        rows.append((self.step, self.sensor_time_ns, item))
        if len(rows) >= self.flush_rows or kind is Image:
            self._flush(path, kind)

    def log_static(self, path: str, item: Observation) -> None:
        if path.startswith("world/"):
            self._last[path] = item
        send_static(self.stream, path, *to_archetypes(path, item))

    def send_series(self, path: str, steps: np.ndarray, times_ns: np.ndarray, values: np.ndarray) -> None:
        """A whole scalar time series in one call (computed after the replay)."""
        self._style_series(path)
        columns = [rr.Scalars.columns(scalars=np.asarray(values, float))]
        self._send(path, np.asarray(steps), np.asarray(times_ns), columns)

    def write_summary(self, metrics_markdown: str, skip: tuple[str, ...] = views.SUMMARY_SKIP
                      ) -> views.Bounds | None:
        """The run's outcome as static data: the last state of every map entity under ``summary/``
        (but the momentary ones in ``skip``), and the metrics table; returns the final map's bounds."""
        bounds: views.Bounds | None = None
        for path, item in sorted(self._last.items()):
            if any(s in path for s in skip) or _empty(item):
                continue
            send_static(self.stream, f"summary/{path}", *to_archetypes(path, item))
            bounds = views.extend_bounds(bounds, _points_of(item))
        send_static(self.stream, views.SUMMARY_METRICS, rr.TextDocument(metrics_markdown, media_type="text/markdown"))
        return bounds

    def send_layout(self, blueprint: rrb.Blueprint) -> None:
        """The run's blueprint, as the default and active layout of its application id."""
        self.stream.send_blueprint(blueprint, make_active=True, make_default=True)

    def _style_series(self, path: str) -> None:
        if path not in self._series:
            self._series.add(path)
            send_static(self.stream, path, rr.SeriesLines(names=views.series_label(path),
                                                          colors=views.series_color(path), widths=1.5))

    def send_property(self, name: str, values: dict[str, Any]) -> None:
        # Chunk.from_property: the chunk ``send_property`` would log, but made here, not by the batcher
        self.stream.send_chunks(Chunk.from_property(name, rr.AnyValues(**values)))

    def close(self) -> None:
        """Flush and write the footer; the file is complete after this."""
        for path, kind in list(self._buffers):
            self._flush(path, kind)
        for path, states in sorted(self._states.items()):
            values = sorted(states)
            send_static(self.stream, path, rr.StateConfiguration(values=values,
                                                                 labels=[v.replace("_", " ") for v in values],
                                                                 colors=[views.state_color(v) for v in values]))
        self.stream.disconnect()

    def _send(self, path: str, steps: np.ndarray, times_ns: np.ndarray, columns: list[Any]) -> None:
        since = (times_ns.astype(np.int64) - self.time_origin_ns).astype("timedelta64[ns]")
        indexes = [rr.TimeColumn(views.STEP, sequence=steps.astype(np.int64)),
                   rr.TimeColumn(views.SENSOR_TIME, duration=since)]
        for cols in columns:
            self.stream.send_columns(path, indexes=indexes, columns=cols)

    def _flush(self, path: str, kind: type) -> None:
        rows = self._buffers.pop((path, kind), [])
        if not rows:
            return
        steps = np.array([r[0] for r in rows])
        times = np.array([r[1] for r in rows])
        items = [r[2] for r in rows]
        if kind in GEOMETRY:
            self._send(path, steps, times, to_columns(path, items))
            return
        if kind is State:
            self._states.setdefault(path, set()).update(i.state for i in items if isinstance(i, State))
        # Text, images, bar charts, documents, states: the archetypes ``log`` would send, as columns
        for i, j, cols in row_groups([row_components(to_archetypes(path, it)) for it in items]):
            self._send(path, steps[i:j], times[i:j], [cols])


def to_columns(path: str, items: list[Any]) -> list[Any]:
    """Column batches (one row per item) drawing a list of same-typed observations."""
    color = role_color(path) or views.NEUTRAL
    first = items[0]
    if isinstance(first, Scalar):
        return [rr.Scalars.columns(scalars=np.array([i.value for i in items], float))]
    if isinstance(first, Pose):
        p = np.array([i.pose for i in items], float).reshape(-1, 3)
        n = len(p)
        labels = [i.label or "" for i in items] if any(i.label for i in items) else None
        heading = 0.5 * np.column_stack([np.cos(p[:, 2]), np.sin(p[:, 2])])
        return [rr.Points2D.columns(positions=p[:, :2], radii=np.full(n, 0.12), colors=np.tile(color, (n, 1)),
                                    labels=labels),
                rr.Arrows2D.columns(origins=p[:, :2], vectors=heading, colors=np.tile(color, (n, 1)))]
    if isinstance(first, Points):
        lengths = np.array([len(i.positions) for i in items])
        pos = np.concatenate([np.asarray(i.positions, float).reshape(-1, 2) for i in items])
        radii = np.concatenate([np.full(len(i.positions), 0.08 if i.radius is None else i.radius) for i in items])
        labels = None
        if any(i.labels for i in items):
            labels = [lb for i in items for lb in (i.labels or [""] * len(i.positions))]
        cols = rr.Points2D.columns(positions=pos, radii=radii, colors=np.tile(color, (len(pos), 1)), labels=labels)
        return [cols.partition(lengths)]
    strips_per_row = [_strips(i) for i in items]
    lengths = np.array([len(s) for s in strips_per_row])
    strips = [s for row in strips_per_row for s in row]
    radius = 0.03 if isinstance(first, LineStrips) else 0.015
    cols = rr.LineStrips2D.columns(strips=_strips_arrow(strips), colors=np.tile(color, (len(strips), 1)),
                                   radii=np.full(len(strips), radius))
    return [cols.partition(lengths)]


def _strips_arrow(strips: list[np.ndarray]) -> pa.Array:
    """Polylines as one Arrow list array of the LineStrip2D component: the array the SDK builds (float32
    points, one list per strip), made with one concatenation instead of an Arrow array per strip."""
    dtype = rr.components.LineStrip2DBatch._ARROW_DATATYPE
    counts = np.array([len(s) for s in strips], np.int32)
    offsets = np.concatenate([[0], np.cumsum(counts)]).astype(np.int32)
    # float64 -> float32 once over all points: the same values as the SDK's conversion strip by strip
    flat = (np.concatenate([np.asarray(s).reshape(-1, 2) for s in strips]).astype(np.float32).reshape(-1)
            if strips else np.empty(0, np.float32))
    points = pa.FixedSizeListArray.from_arrays(pa.array(flat, pa.float32()), type=dtype.value_type)
    return pa.ListArray.from_arrays(pa.array(offsets, pa.int32()), points, type=dtype)


def _strips(item: Any) -> list[np.ndarray]:
    if isinstance(item, LineStrips):
        return [np.asarray(s, float) for s in item.strips]
    if isinstance(item, Segments):
        return [np.stack([a, b]) for a, b in zip(np.asarray(item.starts, float), np.asarray(item.ends, float),
                                                 strict=True)]
    if isinstance(item, CovarianceEllipses):
        return [ellipse_points(m, c, item.n_sigma) for m, c in zip(item.means, item.covariances, strict=True)]
    raise TypeError(f"unknown observation type {type(item).__name__}")


def to_archetypes(path: str, item: Observation) -> list[Any]:
    """The Rerun archetypes that draw an observation."""
    color = role_color(path) or views.NEUTRAL
    if isinstance(item, Points):
        return [rr.Points2D(item.positions, labels=list(item.labels) if item.labels else None,
                            radii=item.radius if item.radius is not None else 0.08, colors=color)]
    if isinstance(item, Pose):
        x, y, th = (float(v) for v in item.pose)
        return [rr.Points2D([[x, y]], radii=0.12, colors=color, labels=[item.label] if item.label else None),
                rr.Arrows2D(origins=[[x, y]], vectors=[[0.5 * np.cos(th), 0.5 * np.sin(th)]], colors=color)]
    if isinstance(item, (LineStrips, Segments, CovarianceEllipses)):
        return [rr.LineStrips2D(_strips(item), colors=color, radii=0.03 if isinstance(item, LineStrips) else 0.015)]
    if isinstance(item, Scalar):
        return [rr.Scalars(float(item.value))]
    if isinstance(item, Text):
        return [rr.TextLog(item.text, level=item.level)]
    if isinstance(item, Image):
        return [rr.Image(item.pixels)]
    if isinstance(item, Bars):
        return [rr.BarChart(np.asarray(item.values, float), color=role_color(path) or views.ESTIMATE)]
    if isinstance(item, Markdown):
        return [rr.TextDocument(item.text, media_type="text/markdown")]
    if isinstance(item, State):
        return [rr.StateChange(state=item.state)]
    raise TypeError(f"unknown observation type {type(item).__name__}")


def _points_of(item: Observation) -> np.ndarray:
    """Every 2D point an observation draws (for bounds), (n, 2)."""
    if isinstance(item, Points):
        return np.asarray(item.positions, float).reshape(-1, 2)
    if isinstance(item, Pose):
        return np.asarray(item.pose, float)[None, :2]
    if isinstance(item, (LineStrips, Segments, CovarianceEllipses)):
        strips = _strips(item)
        return np.concatenate(strips).reshape(-1, 2) if strips else np.empty((0, 2))
    return np.empty((0, 2))


def _empty(item: Observation) -> bool:
    if isinstance(item, LineStrips):
        return not item.strips
    if isinstance(item, (Points, Segments)):
        return not len(item.positions if isinstance(item, Points) else item.starts)
    if isinstance(item, CovarianceEllipses):
        return not len(item.means)
    return False


@dataclass
class MemoryObserver:
    """Keeps every event in memory: for tests and golden files."""

    events: list[tuple[int, int, str, Observation]] = field(default_factory=list)
    step: int = -1
    sensor_time_ns: int = -1

    def set_time(self, step: int, sensor_time_ns: int) -> None:
        self.step, self.sensor_time_ns = step, sensor_time_ns

    def log(self, path: str, item: Observation) -> None:
        self.events.append((self.step, self.sensor_time_ns, path, item))

    def log_static(self, path: str, item: Observation) -> None:
        self.events.append((-1, -1, path, item))

    def send_series(self, path: str, steps: np.ndarray, times_ns: np.ndarray, values: np.ndarray) -> None:
        for s, t, v in zip(steps, times_ns, values, strict=True):
            self.events.append((int(s), int(t), path, Scalar(float(v))))

    def send_property(self, name: str, values: dict[str, Any]) -> None:
        self.events.append((-1, -1, f"__properties/{name}", Text(json.dumps(values, sort_keys=True))))

    def close(self) -> None:
        return None

    def paths(self) -> set[str]:
        return {e[2] for e in self.events}

    def of(self, path: str) -> list[Observation]:
        return [e[3] for e in self.events if e[2] == path]

    def to_jsonable(self, decimals: int = 9) -> list[Any]:
        """Events as rounded, sorted JSON-friendly rows (for golden files)."""
        rows = []
        for step, t, path, item in self.events:
            payload = {k: _round(getattr(item, k), decimals) for k in item.__slots__}
            rows.append([step, t, path, type(item).__name__, payload])
        return sorted(rows, key=lambda r: (r[0], r[1], r[2], json.dumps(r[4], sort_keys=True)))


def _round(value: Any, decimals: int) -> Any:
    if isinstance(value, np.ndarray):
        return np.round(value.astype(np.float64), decimals).tolist()
    if isinstance(value, float):
        return round(value, decimals)
    if isinstance(value, tuple):
        return [_round(v, decimals) for v in value]
    return value
