"""Charts across runs on the runs view, drawn on the server as SVG (no chart library, nothing fetched).

- `group_chart_svg`: a chosen metric per group, one row per group: its label above a line from minimum to
  maximum, a bar of mean ± standard deviation and a dot at the mean (``chart=METRIC`` on a grouped view).
- `scatter_svg`: the runs' value of a metric against a config key, the commit, the seed or the day it was made
  (``chart=METRIC&x=config.KEY|commit|seed|created``), a dot per run.
- `parallel_svg`: parallel coordinates (``chart=METRIC&x=parallel``): a vertical axis for each config key that
  differs among the listed runs, then each chosen metric column, then the charted metric; a line per run across
  them, linked to the run, its shade by the charted metric (darker: better by its direction).

`view_chart` draws the one a view of the runs table asks for. Every dot or row links to its runs (a run's page; a
group's filtered view) and says its values in a tooltip.
Labels sit above the marks rather than beside them, so that a chart stays readable at 390 px: the viewBox is
narrow (420 units) and scales down little. Colours are the palette's estimate blue (`slamreplay.api.web.svg_plots`);
the plot area and grid use the attribute values the page's dark mode restyles.
"""

from __future__ import annotations

import html
import math
import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

from slamreplay.api.service.runs_grammar import value_text
from slamreplay.api.service.runs_query import RunsView, metric_heading, metric_specs
from slamreplay.api.service.store_runs import RunsTableMixin
from slamreplay.api.web.svg_plots import ESTIMATE, nice_ticks

WIDTH = 420
LEFT, RIGHT = 12, 408  # the plot area of the group chart (labels above the rows, no left margin)
SPREAD = "#9ec5e8"  # min-max: a light shade of the estimate's blue
MAX_POINTS = 1000  # a scatter draws the newest runs up to this many


def _fmt(v: float) -> str:
    return f"{v:.4g}"


def _esc(text: str) -> str:
    return html.escape(text, quote=True)


def _svg(height: int, title: str, body: str, cls: str) -> str:
    # a group (not an image): its marks are links, which an image's role would hide from keyboard and reader
    return (f'<svg xmlns="http://www.w3.org/2000/svg" viewBox="0 0 {WIDTH} {height}" class="plot {cls}" role="group" '
            f'aria-label="{_esc(title)}" font-family="system-ui,sans-serif" font-size="13" fill="#333" '
            f'preserveAspectRatio="xMidYMin meet">'
            f"<title>{_esc(title)}</title>{body}</svg>")


def _span(lo: float, hi: float) -> tuple[float, float]:
    if not (math.isfinite(lo) and math.isfinite(hi)):
        return 0.0, 1.0
    if hi <= lo:
        pad = abs(lo) * 0.1 or 1.0
        return lo - pad, hi + pad
    pad = (hi - lo) * 0.05
    return lo - pad, hi + pad


@dataclass(frozen=True)
class GroupMark:
    """A group's row in a group chart: its label, link, and the metric's statistics over its runs."""

    label: str
    href: str | None
    n: int
    mean: float
    std: float | None
    lo: float
    hi: float


def group_chart_svg(marks: Sequence[GroupMark], metric: str, unit: str = "", better: str = "") -> str:
    """A metric per group, in the order given: min-max line, mean ± std bar and mean dot, each row a link.

    Parameters
    ----------
    marks : the groups (at most a page of them), best first when the view is sorted by this metric
    metric, unit : the axis' label
    better : how to read it ("lower is better"...), in the title
    """
    if not marks:
        return ""
    lo = min(min(m.lo, m.mean - (m.std or 0.0)) for m in marks)
    hi = max(max(m.hi, m.mean + (m.std or 0.0)) for m in marks)
    x0, x1 = _span(lo, hi)
    if lo >= 0 and x0 < 0:
        x0 = 0.0  # a non-negative metric's axis starts at 0 at most

    def px(v: float) -> float:
        return min(RIGHT, max(LEFT, LEFT + (v - x0) / (x1 - x0) * (RIGHT - LEFT)))

    row, top = 34, 8
    height = top + row * len(marks) + 34
    bottom = top + row * len(marks)
    out = [f'<rect x="{LEFT}" y="{top}" width="{RIGHT - LEFT}" height="{bottom - top}" fill="#fff" stroke="#bbb"/>']
    for t in nice_ticks(x0, x1, 5):
        out.append(f'<line x1="{px(t):.1f}" y1="{top}" x2="{px(t):.1f}" y2="{bottom}" stroke="#eee"/>'
                   f'<text x="{px(t):.1f}" y="{bottom + 14}" text-anchor="middle">{_fmt(t)}</text>')
    label = metric + (f" ({unit})" if unit and not metric.endswith(f"_{unit}") else "")
    out.append(f'<text x="{(LEFT + RIGHT) / 2:.0f}" y="{height - 4}" text-anchor="middle">'
               f"{_esc(label)}: mean ± std, line min to max</text>")
    for i, m in enumerate(marks):
        y = top + row * i
        yc = y + 24
        spread = "" if m.std is None else f"± {_fmt(m.std)} "
        tip = f"{m.label}: mean {_fmt(m.mean)} {spread}over {m.n} run{'s' if m.n != 1 else ''}; " \
              f"min {_fmt(m.lo)}, max {_fmt(m.hi)}"
        std = m.std or 0.0
        bar_x, bar_w = px(m.mean - std), max(px(m.mean + std) - px(m.mean - std), 1.0)
        mark = (f'<text x="{LEFT + 4}" y="{y + 13}">{_esc(m.label[:60])}</text>'
                f'<line x1="{px(m.lo):.1f}" y1="{yc}" x2="{px(m.hi):.1f}" y2="{yc}" stroke="{SPREAD}" '
                f'stroke-width="2"/>'
                f'<rect x="{bar_x:.1f}" y="{yc - 4}" width="{bar_w:.1f}" height="8" fill="{ESTIMATE}" opacity="0.45"/>'
                f'<circle cx="{px(m.mean):.1f}" cy="{yc}" r="4.5" fill="{ESTIMATE}"/>')
        body = f"<title>{_esc(tip)}</title>{mark}"
        out.append(f'<a href="{_esc(m.href)}" class="mark">{body}</a>' if m.href else f'<g class="mark">{body}</g>')
    title = f"{metric} per group" + (f" ({better})" if better else "")
    return _svg(height, title, "".join(out), "group-chart")


@dataclass(frozen=True)
class Point:
    """A run in a scatter: its x (a number, a day in seconds since the epoch, or a category), y, link and name."""

    x: Any
    y: float
    href: str
    name: str


def scatter_svg(points: Sequence[Point], x_label: str, y_label: str, kind: str = "number") -> str:
    """The runs' ``y`` against ``x``: ``kind`` "number" (a linear axis), "time" (days) or "category" (evenly
    spaced, in the order first given), a dot per run linking to it.

    Parameters
    ----------
    points : the runs (at most MAX_POINTS are drawn, the first ones)
    x_label, y_label : the axes' labels
    """
    pts = [p for p in points[:MAX_POINTS] if isinstance(p.y, (int, float)) and math.isfinite(p.y)]
    if not pts:
        return ""
    left, right, top, bottom, height = 52, WIDTH - 10, 10, 250, 300
    categories: list[str] = []
    if kind == "category":
        for p in pts:
            if str(p.x) not in categories:
                categories.append(str(p.x))
        x0, x1 = -0.5, len(categories) - 0.5
    else:
        xs = [float(p.x) for p in pts]
        x0, x1 = _span(min(xs), max(xs))
    ys = [float(p.y) for p in pts]
    y0, y1 = _span(min(ys), max(ys))
    if min(ys) >= 0 and y0 < 0:
        y0 = 0.0

    def px(v: float) -> float:
        return left + (v - x0) / (x1 - x0) * (right - left)

    def py(v: float) -> float:
        return bottom - (v - y0) / (y1 - y0) * (bottom - top)

    out = [f'<rect x="{left}" y="{top}" width="{right - left}" height="{bottom - top}" fill="#fff" stroke="#bbb"/>']
    for t in nice_ticks(y0, y1, 6):
        out.append(f'<line x1="{left}" y1="{py(t):.1f}" x2="{right}" y2="{py(t):.1f}" stroke="#eee"/>'
                   f'<text x="{left - 4}" y="{py(t) + 4:.1f}" text-anchor="end">{_fmt(t)}</text>')
    if kind == "category":
        step = max(1, math.ceil(len(categories) / 8))
        for i, c in enumerate(categories):
            if i % step == 0:
                out.append(f'<text x="{px(i):.1f}" y="{bottom + 14}" text-anchor="middle">{_esc(c[:10])}</text>')
    else:
        for t in nice_ticks(x0, x1, 5 if kind == "number" else 4):
            text = time.strftime("%m-%d", time.gmtime(t)) if kind == "time" else _fmt(t)
            out.append(f'<line x1="{px(t):.1f}" y1="{top}" x2="{px(t):.1f}" y2="{bottom}" stroke="#eee"/>'
                       f'<text x="{px(t):.1f}" y="{bottom + 14}" text-anchor="middle">{text}</text>')
    out.append(f'<text x="{(left + right) / 2:.0f}" y="{bottom + 32}" text-anchor="middle">{_esc(x_label)}</text>')
    out.append(f'<text transform="translate(12 {(top + bottom) / 2:.0f}) rotate(-90)" text-anchor="middle">'
               f"{_esc(y_label)}</text>")
    for p in pts:
        x = px(categories.index(str(p.x))) if kind == "category" else px(float(p.x))
        shown = time.strftime("%Y-%m-%d", time.gmtime(float(p.x))) if kind == "time" else str(p.x)
        out.append(f'<a href="{_esc(p.href)}" class="mark"><title>{_esc(p.name)}: {_esc(x_label)} {_esc(shown)}, '
                   f'{_esc(y_label)} {_fmt(p.y)}</title><circle cx="{x:.1f}" cy="{py(float(p.y)):.1f}" r="4.5" '
                   f'fill="{ESTIMATE}" fill-opacity="0.7" stroke="{ESTIMATE}"/></a>')
    more = f" (the newest {MAX_POINTS})" if len(points) > MAX_POINTS else ""
    return _svg(height, f"{y_label} against {x_label}, {len(pts)} runs{more}", "".join(out), "scatter")


def view_chart(store: RunsTableMixin, view: RunsView, where: str, args: list[Any],
               groups: list[dict[str, Any]] | None) -> str:
    """The view's chart as SVG ("" when it asks for none or has nothing to draw): its metric per group on a grouped
    view, or against ``x`` (a scatter of the listed runs)."""
    if not view.chart:
        return ""
    head = metric_heading(view.chart)
    y_label = view.chart + (f" ({head['unit']})" if head["unit"] else "")
    if not view.x:
        if groups is None:
            return ""
        marks = [GroupMark(e["g"].label, e["link"], s.n, s.mean, s.std, s.lo, s.hi)
                 for e in groups if (s := e["g"].stats.get(view.chart)) is not None]
        return group_chart_svg(marks, view.chart, head["unit"], head["title"].rsplit("; ", 1)[-1])
    if view.x == "parallel":
        return parallel_chart(store, view, where, args)
    rows = store.chart_points(where, args, view.chart, view.x)
    if view.x == "commit":
        rows.reverse()  # commits from the oldest, left, to the newest
    kind = {"seed": "number", "created": "time", "commit": "category"}.get(view.x, "number")
    if view.x.startswith("config.") and not all(isinstance(r[3], (int, float)) and not isinstance(r[3], bool)
                                                for r in rows):
        kind = "category"

    def x_of(value: Any) -> Any:
        if view.x == "commit":
            return (value or "unknown")[:7]
        if kind == "category":
            return value_text(value, view.x) if not isinstance(value, (list, dict)) else str(value)
        return value

    points = [Point(x_of(x), y, f"/ui/jobs/{i}", name or f"{i[:8]} seed {seed}") for i, name, seed, x, y in rows]
    return scatter_svg(points, view.x, y_label, kind)


@dataclass(frozen=True)
class Line:
    """A run in parallel coordinates: its values by axis (a number, or a category), link and name."""

    values: dict[str, Any]
    href: str
    name: str


def _axis_of(values: list[Any]) -> tuple[str, list[Any], float, float]:
    """How an axis places its values: ("number", [], lo, hi) or ("category", the categories in order, 0, n - 1)."""
    present = [v for v in values if v is not None]
    if present and all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in present):
        lo, hi = min(present), max(present)
        return "number", [], float(lo), float(hi) if hi > lo else float(lo) + 1.0
    cats = sorted({value_text(v, "") if not isinstance(v, (list, dict)) else str(v) for v in present})
    return "category", cats, 0.0, float(max(len(cats) - 1, 1))


def parallel_svg(lines: Sequence[Line], axes: Sequence[str], shade_by: str, better: str = "") -> str:
    """Parallel coordinates: an axis per name in ``axes`` (left to right), a polyline per run through its values
    (a gap where it has none), each a link to its run; the lines' shade follows ``shade_by`` (darker: better by
    ``better``, "lower" or "higher"; one shade without a direction).

    Parameters
    ----------
    lines : the runs (at most MAX_POINTS, the first ones)
    axes : config keys (``config.KEY``) and metric names, at least two
    """
    given, lines = len(lines), list(lines[:MAX_POINTS])
    if len(axes) < 2 or not lines:
        return ""
    left, right, top, bottom = 16, WIDTH - 16, 30, 250
    step = (right - left) / (len(axes) - 1)
    scales = {a: _axis_of([ln.values.get(a) for ln in lines]) for a in axes}

    def py(axis: str, v: Any) -> float | None:
        kind, cats, lo, hi = scales[axis]
        if v is None:
            return None
        if kind == "number":
            pos = (float(v) - lo) / (hi - lo)
        else:
            text = value_text(v, "") if not isinstance(v, (list, dict)) else str(v)
            pos = cats.index(text) / hi if text in cats else 0.0
        return bottom - pos * (bottom - top)

    out = []
    for i, a in enumerate(axes):
        x = left + i * step
        kind, cats, lo, hi = scales[a]
        label = a.removeprefix("config.")
        anchor = "start" if i == 0 else "end" if i == len(axes) - 1 else "middle"
        out.append(f'<line x1="{x:.1f}" y1="{top}" x2="{x:.1f}" y2="{bottom}" stroke="#999"/>'
                   f'<text x="{x:.1f}" y="{top - 16}" text-anchor="{anchor}">{_esc(label[:18])}</text>')
        ends = (_fmt(hi), _fmt(lo)) if kind == "number" else (cats[-1][:10] if cats else "", cats[0][:10] if cats
                                                                                    else "")
        out.append(f'<text x="{x:.1f}" y="{top - 3}" text-anchor="{anchor}" font-size="10">{_esc(ends[0])}</text>'
                   f'<text x="{x:.1f}" y="{bottom + 13}" text-anchor="{anchor}" font-size="10">{_esc(ends[1])}</text>')
    shade_values = [v for ln in lines if isinstance(v := ln.values.get(shade_by), (int, float)) and math.isfinite(v)]
    lo_s, hi_s = (min(shade_values), max(shade_values)) if shade_values else (0.0, 1.0)
    for ln in lines:
        v = ln.values.get(shade_by)
        rank = 0.5 if not isinstance(v, (int, float)) or hi_s <= lo_s else (float(v) - lo_s) / (hi_s - lo_s)
        goodness = {"lower": 1 - rank, "higher": rank}.get(better, 0.5)
        points = [(left + i * step, y) for i, a in enumerate(axes) if (y := py(a, ln.values.get(a))) is not None]
        if len(points) < 2:
            continue
        said = ", ".join(f"{a.removeprefix('config.')} {_fmt(x) if isinstance(x, float) else x}"
                         for a in axes if (x := ln.values.get(a)) is not None)
        out.append(f'<a href="{_esc(ln.href)}" class="mark"><title>{_esc(ln.name)}: {_esc(said)}</title>'
                   f'<polyline points="{" ".join(f"{x:.1f},{y:.1f}" for x, y in points)}" fill="none" '
                   f'stroke="{ESTIMATE}" stroke-width="1.6" stroke-opacity="{0.25 + 0.7 * goodness:.2f}"/></a>')
    more = f" (the newest {MAX_POINTS})" if given > MAX_POINTS else ""
    return _svg(bottom + 24, f"parallel coordinates of {len(lines)} runs over {', '.join(axes)}{more}",
                "".join(out), "parallel")


def parallel_chart(store: RunsTableMixin, view: RunsView, where: str, args: list[Any]) -> str:
    """The listed runs in parallel coordinates: config keys that differ among them, the view's metric columns, and
    the charted metric last (its direction shades the lines)."""
    rows, _ = store.select_runs(where, args, "j.seq DESC", MAX_POINTS)
    runs = [r.job for r in rows]
    keys = sorted({k for j in runs for k in j.config})
    differ = [k for k in keys if len({repr(j.config.get(k)) for j in runs}) > 1][:6]
    metrics = [m for m in (*view.cols, view.chart) if any(m in (j.metrics or {}) for j in runs)]
    axes = [*(f"config.{k}" for k in differ), *dict.fromkeys(metrics)]
    lines = [Line({**{f"config.{k}": j.config.get(k) for k in differ}, **(j.metrics or {})}, f"/ui/jobs/{j.id}",
                  j.name or f"{j.id[:8]} {j.pipeline} seed {j.seed}") for j in runs]
    spec = metric_specs().get(view.chart)
    return parallel_svg(lines, axes, view.chart, spec.better if spec is not None else "")
