"""How runs look in Rerun: the one place that owns frames, colours, timelines and layouts.

- **Frames.** The world is right-handed, x right and y up on screen. A Rerun 2D view draws y
  down, so every map root (``world``, ``summary/world``, ``diff/world``) carries one static
  mirror transform (``MAP_FLIP``) and map views look at it from the entity tree's root.
  Camera images and POMF surfaces keep image coordinates (row down) and are never flipped.
- **Colours.** One palette for every pipeline and the diff: ground truth grey, estimate blue,
  dead reckoning (and odometry prediction) orange, accepted green, rejected red; in a multi-robot
  run each robot's estimate in its own colour (robot 1 blue; ``ROBOT_COLORS``, as its series). An
  entity's colour follows from its path (``role_color``), so names and colours cannot disagree.
- **Time.** ``step`` (the message's index in replay order) and ``sensor_time``: the message's
  log time as a duration since the recording's first message (not a date in 1970).
- **Layouts.** A pipeline's blueprint is a row of tabs, the first one ``Summary``: the final
  map as static data, the metrics table and the main error series, so that the outcome is the
  first thing shown whatever the time cursor says. Step-by-step internals sit in the other
  tabs. The time panel opens paused. Each kind of run has its own application id, so runs of
  different pipelines opened together keep their own layouts (rerun-io/rerun#5640).
"""

from __future__ import annotations

import re
import zlib
from collections.abc import Iterable, Sequence

import numpy as np
import rerun as rr
import rerun.blueprint as rrb

APP_PREFIX = "slamreplay"
STEP = "step"
SENSOR_TIME = "sensor_time"
MAP_ROOTS = ("world", "summary/world")  # every map-frame subtree of a run; the diff has its own (diff.py)

Color = tuple[int, int, int]
TRUTH: Color = (150, 150, 150)
ESTIMATE: Color = (40, 120, 230)
DEAD_RECKONING: Color = (245, 130, 48)
ACCEPTED: Color = (40, 170, 70)
REJECTED: Color = (220, 40, 40)
MEASUREMENT: Color = (150, 60, 200)
TENTATIVE: Color = (200, 200, 200)
RUN_A: Color = (0, 180, 200)
RUN_B: Color = (230, 90, 180)
NEUTRAL: Color = (200, 200, 200)
MAP_PRIOR: Color = (95, 110, 150)  # a map made earlier that a run navigates on
SERIES_CYCLE: tuple[Color, ...] = ((40, 120, 230), (245, 130, 48), (40, 170, 70), (150, 60, 200),
                                   (140, 86, 75), (0, 180, 200), (230, 90, 180), (188, 189, 34))

# First match on the entity path wins (so "robot_truth" is truth and "robot/prediction" dead reckoning).
_ROLES: tuple[tuple[str, Color], ...] = (
    ("/A/", RUN_A), ("/B/", RUN_B),
    ("band", TRUTH),
    ("truth", TRUTH),
    ("reference", TRUTH),
    ("odometry", DEAD_RECKONING), ("prediction", DEAD_RECKONING), ("dead_reckoning", DEAD_RECKONING),
    ("rejected", REJECTED), ("outlier", REJECTED), ("conflict", REJECTED), ("threshold", REJECTED),
    ("accepted", ACCEPTED), ("inlier", ACCEPTED), ("peak", ACCEPTED), ("loops", ACCEPTED), ("matched", ACCEPTED),
    ("target", ACCEPTED), ("global_path", ACCEPTED), ("route", ACCEPTED), ("local_path", MEASUREMENT),
    ("/map/", MAP_PRIOR),
    ("measurement", MEASUREMENT), ("association", MEASUREMENT), ("anchors", MEASUREMENT),
    ("tentative", TENTATIVE),
    ("estimate", ESTIMATE), ("robot", ESTIMATE), ("graph", ESTIMATE), ("nav", ESTIMATE),
)


# States of state timelines, coloured like the map: what worked green, what was refused red.
_STATE_ROLES: tuple[tuple[str, Color], ...] = (
    ("reject", REJECTED), ("ambiguous", REJECTED), ("flat", REJECTED), ("no_features", REJECTED),
    ("loop", ACCEPTED), ("accepted", ACCEPTED), ("mapped", ACCEPTED), ("ok", ACCEPTED),
    ("new", ESTIMATE), ("phase_i", ESTIMATE), ("bootstrap", MEASUREMENT),
    ("localization", DEAD_RECKONING), ("skipped", NEUTRAL), ("empty", NEUTRAL),
)


def state_color(state: str) -> Color:
    return next((c for key, c in _STATE_ROLES if key in state), series_color(state))


_ROBOT_ENTITY = re.compile(r"/robot(\d+)/")  # robot N of a multi-robot run: world/robots/robotN, .../robotN/estimate


def role_color(path: str) -> Color | None:
    """The palette colour of an entity, from its path (None: no role). What a multi-robot run estimates of
    robot N (its pose, ellipse, trajectory) takes robot N's colour (ROBOT_COLORS, as its series do);
    its truth and dead reckoning keep their roles' colours."""
    padded = f"/{path.strip('/')}/"
    color = next((c for key, c in _ROLES if key in padded), None)
    if color == ESTIMATE and (m := _ROBOT_ENTITY.search(padded)):
        return ROBOT_COLORS[(int(m.group(1)) - 1) % len(ROBOT_COLORS)]
    return color


_ROBOT_SERIES = re.compile(r"^metrics/robot(\d+)_")  # one series per robot of a multi-robot run
# robot 1 the estimate's blue, then colours that no role of a run's map uses (no orange, grey, red, green or
# the measurements' purple, which comes last); cyan and pink are the diff view's runs, never in the same view
ROBOT_COLORS: tuple[Color, ...] = (ESTIMATE, (0, 180, 200), (230, 90, 180), (140, 86, 75), (188, 189, 34),
                                   (150, 60, 200))


def series_color(path: str) -> Color:
    """A scalar series' colour: one per robot for a multi-robot run's per-robot series (robot N: the cycle's Nth
    colour of ROBOT_COLORS), else its role's, else a fixed colour picked by the path (stable across runs)."""
    if m := _ROBOT_SERIES.match(path):
        return ROBOT_COLORS[(int(m.group(1)) - 1) % len(ROBOT_COLORS)]
    return role_color(path) or SERIES_CYCLE[zlib.crc32(path.encode()) % len(SERIES_CYCLE)]


def series_label(path: str) -> str:
    """The legend name of a series: its last path element, in words."""
    return path.rstrip("/").rsplit("/", 1)[-1].replace("_", " ")


def app_id(kind: str) -> str:
    """The Rerun application id of a kind of run (a pipeline name, or ``diff``)."""
    return f"{APP_PREFIX}-{kind}"


# Entities whose last value is a moment, not the outcome: not mirrored into the summary.
SUMMARY_SKIP = ("/tail", "associations", "observed", "anchors", "prediction", "measurement", "tentative",
                "information", "/nav/local_path", "/nav/target", "matched_node")

MAP_FLIP = rr.Transform3D(scale=[1.0, -1.0, 1.0])  # world y up on a y-down 2D canvas

Bounds = tuple[float, float, float, float]  # world frame: x_min, x_max, y_min, y_max (metres)


def extend_bounds(bounds: Bounds | None, xy: np.ndarray) -> Bounds | None:
    """``bounds`` grown to hold the finite points ``xy`` (n, 2)."""
    xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    xy = xy[np.all(np.isfinite(xy), axis=1)]
    if not len(xy):
        return bounds
    lo, hi = xy.min(axis=0), xy.max(axis=0)
    if bounds is not None:
        lo = np.minimum(lo, (bounds[0], bounds[2]))
        hi = np.maximum(hi, (bounds[1], bounds[3]))
    return float(lo[0]), float(hi[0]), float(lo[1]), float(hi[1])


def visual_bounds(bounds: Bounds | None, margin: float = 0.06) -> rrb.VisualBounds2D | None:
    """The 2D view bounds showing a world box with a margin (through MAP_FLIP: y negated).

    Rerun fits a 2D view tightly to its content and cuts off what is near the edges, so map
    views are given their bounds explicitly, computed from the run's final map."""
    if bounds is None:
        return None
    x0, x1, y0, y1 = bounds
    pad = margin * max(x1 - x0, y1 - y0, 1.0)
    return rrb.VisualBounds2D(x_range=[x0 - pad, x1 + pad], y_range=[-y1 - pad, -y0 + pad])


# ---------------------------------------------------------------------------------------
# Views


def map_view(name: str, root: str = "world", bounds: Bounds | None = None,
             exclude: Iterable[str] = ()) -> rrb.Spatial2DView:
    """A right-handed top-down view of a map root (one of MAP_ROOTS or the diff's)."""
    contents = [f"+ /{root}/**"] + [f"- /{root}/{e}" for e in exclude]
    return rrb.Spatial2DView(name=name, origin="/", contents=contents, visual_bounds=visual_bounds(bounds))


def image_view(name: str, origin: str, contents: Sequence[str] | None = None) -> rrb.Spatial2DView:
    """A view in image coordinates (row down): camera images, surfaces, mosaics."""
    if contents is None:
        return rrb.Spatial2DView(name=name, origin=origin)
    return rrb.Spatial2DView(name=name, origin=origin, contents=list(contents))


def whole_run(*timelines: str) -> list[rrb.VisibleTimeRange]:
    """Visible ranges that show a series over the whole run, whatever the time cursor."""
    every = rrb.TimeRangeBoundary.infinite()
    return [rrb.VisibleTimeRange(t, start=every, end=every) for t in (timelines or (STEP, SENSOR_TIME))]


def series_view(name: str, *paths: str) -> rrb.TimeSeriesView:
    """A plot of the series under ``paths`` (each a path or a ``path/**`` pattern), with a legend."""
    contents = [p if p.startswith(("+", "-")) else f"+ /{p.strip('/')}" for p in paths]
    every = rrb.TimeRangeBoundary.infinite()
    return rrb.TimeSeriesView(name=name, origin="/", contents=contents, plot_legend=rrb.PlotLegend(visible=True),
                              time_ranges=whole_run(),
                              axis_x=rrb.TimeAxis(view_range=rrb.TimeRange(start=every, end=every)))


def log_view(name: str = "Log", *paths: str) -> rrb.TextLogView:
    return rrb.TextLogView(name=name, origin="/", contents=[f"+ /{p.strip('/')}/**" for p in (paths or ("log",))])


def state_view(name: str, *paths: str) -> rrb.StateTimelineView:
    """Lanes of discrete states over the whole run (scan status, loop closures, accept/reject)."""
    return rrb.StateTimelineView(name=name, origin="/", contents=[f"+ /{p.strip('/')}" for p in paths],
                                 time_ranges=whole_run())


def data_view(name: str = "Per-step metrics", origin: str = "/metrics") -> rrb.DataframeView:
    """A table of every series under ``origin``, one row per step."""
    return rrb.DataframeView(name=name, origin=origin)


def markdown_view(name: str, path: str) -> rrb.TextDocumentView:
    return rrb.TextDocumentView(name=name, origin=f"/{path.strip('/')}")


SUMMARY_METRICS = "summary/metrics"
SUMMARY_MAP = "summary/world"


def summary_tab(bounds: Bounds | None, main_series: Sequence[str] = (), series_name: str = "Error over time",
                side: rrb.View | rrb.Container | None = None) -> rrb.Container:
    """The first tab: final map (static), metrics table (static) and the run's main series."""
    right: list[rrb.View | rrb.Container] = [markdown_view("Metrics", SUMMARY_METRICS)]
    if main_series:
        right.append(series_view(series_name, *main_series))
    if side is not None:
        right.append(side)
    return rrb.Horizontal(map_view("Final map", SUMMARY_MAP, bounds), rrb.Vertical(*right), column_shares=[3, 2],
                          name="Summary")


def tab(name: str, *parts: rrb.View | rrb.Container, columns: Sequence[float] | None = None) -> rrb.Container:
    """A tab holding its parts side by side."""
    return rrb.Horizontal(*parts, column_shares=list(columns) if columns else None, name=name)


def following_layout_rrd(kind: str, recording_id: str) -> bytes:
    """A blueprint alone, as ``.rrd`` bytes, for the run ``recording_id`` of ``kind`` watched while it runs: the
    viewer's own layout of what has arrived, the time cursor following the newest step (the run's own layout is
    sent when it ends: its bounds come from the whole run). Sent ahead of the growing ``run.rrd``: Rerun's decoder
    reads concatenated streams, and the run's layout, active when it arrives, replaces this one. The run's
    recording id, so that the stream's store is the run's (another id would list an empty recording)."""
    stream = rr.RecordingStream(app_id(kind), recording_id=recording_id, send_properties=False)
    memory = stream.memory_recording()
    stream.send_blueprint(rrb.Blueprint(rrb.TimePanel(timeline=STEP, play_state="following"), auto_layout=True,
                                        auto_views=True), make_active=True, make_default=False)
    return bytes(memory.drain_as_bytes())


def layout(*tabs: rrb.Container) -> rrb.Blueprint:
    """A run's blueprint: its tabs, the first one active; panels collapsed, time paused on ``step``."""
    return rrb.Blueprint(rrb.Tabs(*tabs, active_tab=0), rrb.TimePanel(state="collapsed", timeline=STEP,
                                                                      play_state="paused"),
                         collapse_panels=True)
