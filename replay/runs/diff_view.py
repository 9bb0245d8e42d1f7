"""The comparison ``.rrd`` of two runs: what a person opens to see how B differs from A.

Both runs are copied whole under ``runs/A/...`` and ``runs/B/...`` (every step, every
internal), then drawn so they can be told apart: run A in `views.RUN_A`, run B in
`views.RUN_B`, ground truth grey in both. The map colours are static overrides of each
entity's ``colors`` (a static component value hides the temporal ones), so the copied data
is not rewritten. Tabs:

1. ``Summary``: both final maps overlaid on the same axes; a markdown table of metric
   deltas with regressions marked (each judged as `diff` judges it, a NEES by its distance from
   its consistent value), the runs named relative to the working directory (`run_name`), what
   changed between the runs (configuration keys, code version, recording) and the first step at
   which their logged content diverges.
2. ``Metrics A vs B``: each metric series of A and B in one plot.
3. ``A over time`` and ``B over time``: each run's map step by step, on one time cursor.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
from collections import defaultdict
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import rerun as rr
import rerun.blueprint as rrb
from rerun.chunk import Chunk, RrdReader

from slamreplay.recorder.files import replacing
from slamreplay.replay.engine import views
from slamreplay.replay.engine.observer import deterministic_batcher, send_static
from slamreplay.replay.errors import ReplayError
from slamreplay.replay.runs.diff import RunDiff, diff_runs, formatted, verdict_text

COLOR_COLUMNS = {"Points2D:colors": rr.Points2D, "LineStrips2D:colors": rr.LineStrips2D,
                 "Arrows2D:colors": rr.Arrows2D}
POINT_COLUMNS = ("Points2D:positions", "LineStrips2D:strips", "Arrows2D:origins")
IGNORED = ("rerun.controls.RowId", views.STEP, views.SENSOR_TIME)


class _RunContent:
    """What the comparison needs from one run's ``.rrd``, read in one pass over its chunks."""

    def __init__(self) -> None:
        self.colored: dict[str, set[str]] = defaultdict(set)  # map entity -> its colour columns
        self.series: set[str] = set()  # metric series entities
        self.bounds: views.Bounds | None = None  # of the final (summary) map
        self.digests: dict[tuple[int, str], Any] = {}  # (step, entity) -> hash of what was logged then

    def see(self, ch: Chunk) -> None:
        path = str(ch.entity_path)
        rb = ch.to_record_batch()
        names = rb.schema.names
        if path.startswith(("/world/", "/summary/world/")):
            self.colored[path].update(n for n in names if n in COLOR_COLUMNS)
        if path.startswith("/metrics/") and any(n.startswith("Scalars:") for n in names):
            self.series.add(path)
        if ch.is_static:
            if path.startswith("/summary/world/"):
                for col in POINT_COLUMNS:
                    if col in names:
                        self.bounds = views.extend_bounds(self.bounds, _points(rb.column(col)))
            return
        if views.STEP not in names or path.startswith(("/summary", "/log")) or "TextLog:text" in names:
            return
        steps = rb.column(views.STEP).to_pylist()
        values = [rb.column(n).to_pylist() for n in names if n not in IGNORED and not n.endswith(":colors")]
        for i, step in enumerate(steps):
            key = (int(step), path)
            h = self.digests.get(key) or hashlib.sha256()
            h.update(repr([v[i] for v in values]).encode())
            self.digests[key] = h


def _points(column: pa.Array) -> np.ndarray:
    """Every 2D point in a column of positions, strips or origins (any list nesting)."""
    arr = column
    while pa.types.is_list(arr.type) or pa.types.is_large_list(arr.type) or pa.types.is_fixed_size_list(arr.type):
        arr = arr.flatten()
    return np.asarray(arr.to_numpy(zero_copy_only=False), dtype=np.float64).reshape(-1, 2)


def first_divergence(a: _RunContent, b: _RunContent) -> tuple[int, str] | None:
    """The first step (and an entity) at which A and B logged different content; None if none."""
    keys = sorted(set(a.digests) | set(b.digests))
    for key in keys:
        ha, hb = a.digests.get(key), b.digests.get(key)
        if ha is None or hb is None or ha.digest() != hb.digest():
            return key
    return None


def _copy(rec: rr.RecordingStream, run_dir: Path, label: str) -> _RunContent:
    content = _RunContent()

    def relabel(ch: Chunk) -> Chunk:
        content.see(ch)
        return ch.with_entity_path(f"/runs/{label}{ch.entity_path}")

    rec.send_chunks(RrdReader(run_dir / "run.rrd").stream().map(relabel))
    color = views.RUN_A if label == "A" else views.RUN_B
    for path, columns in sorted(content.colored.items()):
        if views.role_color(path) == views.TRUTH:
            continue
        for col in sorted(columns):
            send_static(rec, f"/runs/{label}{path}", COLOR_COLUMNS[col].from_fields(colors=color))
    for path in sorted(content.series):
        name = f"{label}: {views.series_label(path)}"
        send_static(rec, f"/runs/{label}{path}", rr.SeriesLines(names=name, colors=color, widths=1.5))
    return content


def run_name(run_dir: str | Path) -> str:
    """A run as its title names it: relative to the working directory when inside it, else its parent folder and
    its own (``demo/sim-landmarks--dslam``), never the absolute path of the machine that drew it."""
    path = Path(run_dir)
    if not path.is_absolute():
        return path.as_posix()
    with contextlib.suppress(ValueError):
        return path.relative_to(Path.cwd()).as_posix()
    return "/".join(path.parts[-2:])


def _markdown(diff: RunDiff, a: _RunContent, b: _RunContent) -> str:
    lines = [f"### A: `{run_name(diff.a)}`  vs  B: `{run_name(diff.b)}`", "",
             "Map: **A** teal, **B** magenta, ground truth grey.", "",
             "| metric | A | B | B - A | better | verdict |", "|---|---:|---:|---:|---|---|"]
    for m in diff.metrics:
        fa, fb, fd = formatted(m)
        verdict = verdict_text(m).replace("WORSE", "**WORSE**")
        lines.append(f"| `{m.name}` | {fa} | {fb} | {fd} | {m.direction} | {verdict} |")
    lines += ["", f"**{len(diff.worse)} metric(s) worse**" + (f": {', '.join(diff.worse)}" if diff.worse else ""),
              "", "#### What changed"]
    if diff.changes:
        lines += [f"- `{c['field']}`: {json.dumps(c['a'])} → {json.dumps(c['b'])}" for c in diff.changes]
    else:
        lines.append("- nothing: same recording, pipeline, configuration, seed and code")
    where = first_divergence(a, b)
    lines += ["", "#### First divergence",
              "- none: the two runs logged the same content at every step" if where is None
              else f"- step {where[0]}, entity `{where[1]}`"]
    return "\n".join(lines) + "\n"


def _blueprint(a: _RunContent, b: _RunContent, a_name: str, b_name: str) -> rrb.Blueprint:
    bounds = a.bounds
    if b.bounds is not None:
        bounds = views.extend_bounds(bounds, np.array([b.bounds[:2], b.bounds[2:]]).T)
    overlay = rrb.Spatial2DView(name="Final maps: A (teal) and B (magenta)", origin="/",
                                contents=["+ /runs/A/summary/world/**", "+ /runs/B/summary/world/**"],
                                visual_bounds=views.visual_bounds(bounds))
    summary = rrb.Horizontal(overlay, views.markdown_view("Metric deltas", "diff/summary"), column_shares=[3, 2],
                             name="Summary")
    series = sorted(a.series | b.series)
    plots = [views.series_view(views.series_label(p), f"runs/A{p}", f"runs/B{p}") for p in series]
    tabs = [summary]
    if plots:
        tabs.append(rrb.Grid(*plots, name="Metrics A vs B"))
    for label, name in (("A", a_name), ("B", b_name)):
        tabs.append(rrb.Horizontal(views.map_view(f"{label}: {name}", f"runs/{label}/world", bounds),
                                   name=f"{label} over time"))
    return views.layout(*tabs)


def write_comparison_rrd(a_dir: str | Path, b_dir: str | Path, out: str | Path, diff: RunDiff | None = None) -> None:
    """One ``.rrd`` comparing run B with run A (see the module docstring); temp file, then renamed."""

    a_dir, b_dir, out = Path(a_dir), Path(b_dir), Path(out)
    if out.exists():
        raise ReplayError(f"{out} already exists; choose another --rrd")
    for d in (a_dir, b_dir):
        if not (d / "run.rrd").is_file():
            raise ReplayError(f"{d} has no run.rrd")
    diff = diff if diff is not None else diff_runs(a_dir, b_dir, compare_rrd=False)
    rec = rr.RecordingStream(views.app_id("diff"), recording_id=f"diff-{a_dir.name}-{b_dir.name}",
                             send_properties=False, batcher_config=deterministic_batcher())
    rec.set_log_time_enabled(False)
    with replacing(out) as tmp:
        rec.save(tmp)
        try:
            a = _copy(rec, a_dir, "A")
            b = _copy(rec, b_dir, "B")
            send_static(rec, "diff/summary", rr.TextDocument(_markdown(diff, a, b), media_type="text/markdown"))
            rec.send_blueprint(_blueprint(a, b, a_dir.name, b_dir.name), make_active=True, make_default=True)
        finally:
            rec.disconnect()
