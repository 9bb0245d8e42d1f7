"""Plots drawn on the server as inline SVG (no chart library, nothing fetched): a run's trajectory against
ground truth, and its position error over time, each with axes, units and a legend; several runs' paths overlaid,
and their per-step curves (position error, NEES over its consistency band) on one time axis.

The palette is the project's: ground truth grey, estimate blue, dead reckoning orange.
"""

from __future__ import annotations

import html
import math
from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

TRUTH, ESTIMATE, DEAD_RECKONING = "#7f7f7f", "#1f77b4", "#ff7f0e"
BAND_OPACITY = 0.25  # a consistency band: the truth's grey, light enough that every run's curve shows over it
F64 = NDArray[np.float64]


def nice_ticks(lo: float, hi: float, most: int = 6) -> list[float]:
    """Round tick values (1, 2 or 5 times a power of ten apart) covering [lo, hi], at most about ``most``."""
    if not (math.isfinite(lo) and math.isfinite(hi)) or hi <= lo:
        return [lo]
    power = 10.0 ** math.floor(math.log10((hi - lo) / most))
    for step in (m * power * k for k in (1, 10, 100) for m in (1, 2, 5)):  # the finest that gives at most `most`
        first, last = math.ceil(lo / step - 1e-9), math.floor(hi / step + 1e-9)
        if last - first + 1 <= most:
            return [round(i * step, 12) for i in range(first, last + 1)]
    return [lo, hi]


def _fmt(v: float) -> str:
    return f"{v:.6g}"


def thin(rows: F64, most: int = 600) -> F64:
    """At most about ``most`` evenly spaced rows, the last one kept (an SVG of a long run stays small)."""
    step = max(1, len(rows) // most)
    return rows if step == 1 else np.vstack([rows[::step], rows[-1:]])


class _Frame:
    """Data (x, y) to pixels inside a plot area with margins for the axes' labels."""

    def __init__(self, x: tuple[float, float], y: tuple[float, float], width: int, height: int,
                 left: int = 56, right: int = 12, top: int = 12, bottom: int = 40) -> None:
        self.x0, self.x1 = x
        self.y0, self.y1 = y
        self.w, self.h = width, height
        self.left, self.right, self.top, self.bottom = left, width - right, top, height - bottom

    def px(self, x: float) -> float:
        return self.left + (x - self.x0) / ((self.x1 - self.x0) or 1.0) * (self.right - self.left)

    def py(self, y: float) -> float:
        return self.bottom - (y - self.y0) / ((self.y1 - self.y0) or 1.0) * (self.bottom - self.top)

    def line(self, xy: F64, colour: str, width: float = 1.6, dash: str = "") -> str:
        pts = " ".join(f"{self.px(float(x)):.1f},{self.py(float(y)):.1f}" for x, y in xy)
        extra = f' stroke-dasharray="{dash}"' if dash else ""
        return f'<polyline points="{pts}" fill="none" stroke="{colour}" stroke-width="{width}"{extra}/>'

    def axes(self, x_label: str, y_label: str) -> str:
        out = [f'<rect x="{self.left}" y="{self.top}" width="{self.right - self.left}" '
               f'height="{self.bottom - self.top}" fill="#fff" stroke="#bbb"/>']
        for t in nice_ticks(self.x0, self.x1):
            x = self.px(t)
            out.append(f'<line x1="{x:.1f}" y1="{self.top}" x2="{x:.1f}" y2="{self.bottom}" stroke="#eee"/>'
                       f'<text x="{x:.1f}" y="{self.bottom + 14}" text-anchor="middle">{_fmt(t)}</text>')
        for t in nice_ticks(self.y0, self.y1):
            y = self.py(t)
            out.append(f'<line x1="{self.left}" y1="{y:.1f}" x2="{self.right}" y2="{y:.1f}" stroke="#eee"/>'
                       f'<text x="{self.left - 5}" y="{y + 4:.1f}" text-anchor="end">{_fmt(t)}</text>')
        out.append(f'<text x="{(self.left + self.right) / 2:.0f}" y="{self.h - 6}" text-anchor="middle">'
                   f"{html.escape(x_label)}</text>")
        out.append(f'<text transform="translate(12 {(self.top + self.bottom) / 2:.0f}) rotate(-90)" '
                   f'text-anchor="middle">{html.escape(y_label)}</text>')
        return "".join(out)


def _legend(entries: Sequence[tuple[str, str]], x: float, y: float, shaded: int = 0) -> str:
    """A line of ``colour`` and its label per entry, one below another; the first ``shaded`` entries are areas
    (a band), drawn as a filled square."""
    out = []
    for i, (label, colour) in enumerate(entries):
        yy = y + i * 16
        if i < shaded:
            mark = f'<rect x="{x}" y="{yy - 6}" width="18" height="12" fill="{colour}" fill-opacity="{BAND_OPACITY}"/>'
        else:
            mark = f'<line x1="{x}" y1="{yy}" x2="{x + 18}" y2="{yy}" stroke="{colour}" stroke-width="3"/>'
        out.append(f'{mark}<text x="{x + 23}" y="{yy + 4}">{html.escape(label)}</text>')
    return f'<g class="legend">{"".join(out)}</g>'


def _svg(width: int, height: int, title: str, body: str) -> str:
    return (f'<svg xmlns="http://www.w3.org/2000/svg" viewBox="0 0 {width} {height}" class="plot" role="img" '
            f'font-family="system-ui,sans-serif" font-size="11" fill="#333" preserveAspectRatio="xMidYMid meet">'
            f"<title>{html.escape(title)}</title>{body}</svg>")


def _equal_axes(paths: Sequence[F64], width: int, height: int) -> _Frame:
    """A frame holding every (n, 2) path on equal scales (a metre as long across as up): the range that fits the
    plot area less tightly is widened, about the paths' centre."""
    both = np.vstack(paths)
    lo, hi = both.min(axis=0), both.max(axis=0)
    frame = _Frame((0, 1), (0, 1), width, height)
    dx, dy = (max(float(v), 1e-3) * 1.1 for v in hi - lo)
    scale = min((frame.right - frame.left) / dx, (frame.bottom - frame.top) / dy)
    half_x, half_y = (frame.right - frame.left) / scale / 2, (frame.bottom - frame.top) / scale / 2
    cx, cy = (lo + hi) / 2
    return _Frame((cx - half_x, cx + half_x), (cy - half_y, cy + half_y), width, height)


def trajectory_svg(estimate: F64, truth: F64 | None, dead_reckoning: F64 | None = None,
                   width: int = 480, height: int = 420) -> str:
    """The estimated path (blue) over ground truth (grey) and dead reckoning (orange), on equal axes.

    Parameters
    ----------
    estimate, truth, dead_reckoning : (n, 2) float64, x and y in the world frame (m); truth and dead
        reckoning may be None
    """
    curves = [(a, label, colour) for a, label, colour in ((truth, "ground truth", TRUTH),
                                                          (dead_reckoning, "dead reckoning", DEAD_RECKONING),
                                                          (estimate, "estimate", ESTIMATE)) if a is not None and len(a)]
    frame = _equal_axes([a for a, _, _ in curves], width, height)
    body = frame.axes("x (m)", "y (m)")
    # Truth wide and under the rest, so an estimate that follows it closely still shows both.
    body += "".join(frame.line(thin(a), colour, 4.5 if colour == TRUTH else 1.6,
                               "5 3" if colour == DEAD_RECKONING else "") for a, _, colour in curves)
    start = curves[-1][0][0]
    body += f'<circle cx="{frame.px(float(start[0])):.1f}" cy="{frame.py(float(start[1])):.1f}" r="3.5" fill="#333"/>'
    body += _legend([(label, colour) for _, label, colour in curves], frame.left + 10, frame.top + 14)
    return _svg(width, height, "trajectory against ground truth (world frame, m); the dot is the start", body)


def error_svg(t_s: F64, error_m: F64, width: int = 480, height: int = 260) -> str:
    """Position error (m) against time since the first pose with ground truth (s), blue, from 0.

    Parameters
    ----------
    t_s, error_m : (n,) float64
    """
    rows = thin(np.column_stack([t_s, error_m]))
    t_max = float(rows[-1, 0]) if len(rows) else 1.0
    e_max = float(rows[:, 1].max()) if len(rows) else 1.0
    frame = _Frame((0.0, t_max or 1.0), (0.0, (e_max or 1.0) * 1.08), width, height)
    body = frame.axes("time since the first pose with ground truth (s)", "position error (m)")
    body += frame.line(rows, ESTIMATE)
    body += _legend([("estimate − ground truth", ESTIMATE)], frame.left + 10, frame.top + 14)
    return _svg(width, height, f"position error over time: max {e_max:.4g} m", body)


# Distinct colours for overlaid runs (none of them the truth's grey), repeated past ten runs.
RUN_COLOURS = ("#1f77b4", "#d62728", "#2ca02c", "#ff7f0e", "#9467bd", "#8c564b", "#e377c2", "#17becf", "#bcbd22",
               "#393b79")


def overlay_svg(runs: Sequence[tuple[str, F64]], truths: Sequence[tuple[str, F64]] = (),
                width: int = 640, height: int = 480) -> str:
    """Several runs' estimated paths on equal axes, one colour each, over ground truth (grey), with a legend.

    Parameters
    ----------
    runs : (label, (n, 2) float64 x and y in the world frame, m), in legend order; empty paths are left out
    truths : (label, (n, 2) float64) ground truth per recording, drawn grey under the runs
    """
    curves = [(xy, label, TRUTH) for label, xy in truths if len(xy)]
    curves += [(xy, label, RUN_COLOURS[i % len(RUN_COLOURS)]) for i, (label, xy) in enumerate(runs) if len(xy)]
    if not curves:
        return ""
    legend_h = 16 * len(curves) + 8  # the legend sits below the plot, so it never hides a path
    plot_h = height
    frame = _equal_axes([a for a, _, _ in curves], width, plot_h)
    body = frame.axes("x (m)", "y (m)")
    body += "".join(frame.line(thin(a), colour, 4.5 if colour == TRUTH else 1.6) for a, _, colour in curves)
    body += _legend([(label, colour) for _, label, colour in curves], frame.left, plot_h + 10)
    return _svg(width, plot_h + legend_h, f"{len(runs)} trajectories overlaid on ground truth (world frame, m)",
                body)


def curves_svg(curves: Sequence[tuple[str, F64, F64]], y_label: str, title: str, width: int = 640,
               height: int = 300, bands: Sequence[tuple[str, float, float]] = (), legend_x: int | None = None) -> str:
    """Several runs' per-step curves on one time axis from 0, one colour each in ``RUN_COLOURS`` order (the
    trajectory overlay's, so the legends agree), with the legend below the plot.

    Parameters
    ----------
    curves : (label, (n,) float64 time since the run's first pose with ground truth (s), (n,) float64 value), in
        legend order; empty curves keep their colour but are not drawn; NaN values are left out
    bands : (label, low, high): value ranges shaded grey across the plot under the curves (a NEES's consistency
        band), first in the legend
    legend_x : where the legend's marks start (default: the plot area's left edge)
    """
    drawn = [(label, rows[np.isfinite(rows).all(axis=1)], RUN_COLOURS[i % len(RUN_COLOURS)])
             for i, (label, t, y) in enumerate(curves) if len(t) for rows in [np.column_stack([t, y])]]
    drawn = [d for d in drawn if len(d[1])]
    if not drawn:
        return ""
    both = np.vstack([rows for _, rows, _ in drawn])
    t_max = float(both[:, 0].max()) or 1.0
    y_max = max([float(both[:, 1].max()), *(high for _, _, high in bands)]) or 1.0
    frame = _Frame((0.0, t_max), (0.0, y_max * 1.08), width, height)
    body = frame.axes("time since the first pose with ground truth (s)", y_label)
    for _, low, high in bands:
        top, bottom = frame.py(high), frame.py(max(low, 0.0))
        body += (f'<rect class="band" x="{frame.left}" y="{top:.1f}" width="{frame.right - frame.left}" '
                 f'height="{bottom - top:.1f}" fill="{TRUTH}" fill-opacity="{BAND_OPACITY}"/>')
    body += "".join(frame.line(thin(rows), colour) for _, rows, colour in drawn)
    entries = [(label, TRUTH) for label, _, _ in bands] + [(label, colour) for label, _, colour in drawn]
    body += _legend(entries, frame.left if legend_x is None else legend_x, height + 10, shaded=len(bands))
    return _svg(width, height + 16 * len(entries) + 8, title, body)
