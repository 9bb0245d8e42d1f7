"""A comparison as one self-contained HTML file, and as a markdown table for a CI job summary.

The HTML needs no network: CSS is inline and every plot is an inline SVG drawn here (per-seed
values of A and B on one axis, the A-B pairs joined, so a shift shared by every seed stands
out from scatter; and the estimated trajectories of A and B overlaid, per cell and seed, from
each run's ``trajectory.tum``). Regressions are red, improvements green, the rest grey. Each cell links to
its A and B run directories.
"""

from __future__ import annotations

import html
import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from replay.compare import Comparison, MetricResult, fmt, fmt_ms
from replay.run import atomic_write
from replay.trajectory import TUM_ARTIFACT, read_tum

COLOURS = {"regression": "#c62828", "failed": "#c62828", "improvement": "#2e7d32"}
A_COLOUR, B_COLOUR = "#7f7f7f", "#1f77b4"  # A grey (the baseline), B blue (the estimate under test)
CSS = """
body{font-family:system-ui,sans-serif;margin:2em;color:#222}
table{border-collapse:collapse;font-size:13px}td,th{padding:3px 8px;border-bottom:1px solid #ddd;text-align:right}
td.l,th.l{text-align:left}tr.regression,tr.failed{background:#fde0e0;color:#8b0000;font-weight:bold}
tr.improvement{background:#e3f4e3;color:#1b5e20}tr.unchanged,tr.noise,tr.changed,tr.missing{color:#777}
code{background:#f3f3f3;padding:0 3px}.legend span{margin-right:1em}
"""


def _strip_plot(r: MetricResult, width: int = 220, height: int = 34) -> str:
    """Per-seed values: A (grey) on the upper row, B (blue) on the lower, pairs joined."""
    vals = [*r.a, *r.b]
    if not vals:
        return ""
    lo, hi = min(vals), max(vals)
    span = (hi - lo) or (abs(hi) or 1.0)
    lo, hi = lo - 0.05 * span, hi + 0.05 * span

    def x(v: float) -> float:
        return 8 + (v - lo) / (hi - lo) * (width - 16)

    ya, yb = 10, height - 10
    parts = [f'<svg xmlns="http://www.w3.org/2000/svg" width="{width}" height="{height}" role="img">',
             f"<title>{html.escape(r.metric)}: A {', '.join(f'{v:.4g}' for v in r.a)}; "
             f"B {', '.join(f'{v:.4g}' for v in r.b)}</title>"]
    for va, vb in zip(r.a, r.b, strict=True):
        parts.append(f'<line x1="{x(va):.1f}" y1="{ya}" x2="{x(vb):.1f}" y2="{yb}" stroke="#bbb"/>')
    parts += [f'<circle cx="{x(v):.1f}" cy="{ya}" r="3.5" fill="{A_COLOUR}"/>' for v in r.a]
    parts += [f'<circle cx="{x(v):.1f}" cy="{yb}" r="3.5" fill="{B_COLOUR}"/>' for v in r.b]
    parts.append("</svg>")
    return "".join(parts)


def _trajectory(path: str | None) -> np.ndarray | None:
    """(n, 2) positions from a run's trajectory.tum, thinned to at most 400 points; None without one."""
    if not path:
        return None
    try:
        _, poses = read_tum((Path(path) / TUM_ARTIFACT).read_text())
    except (OSError, ValueError):
        return None
    if not len(poses):
        return None
    step = max(1, len(poses) // 400)
    return np.vstack([poses[::step, :2], poses[-1:, :2]])


def _trajectory_plot(a: np.ndarray, b: np.ndarray, title: str, size: int = 260) -> str:
    """A and B estimated trajectories on equal axes (world frame, y up)."""
    both = np.vstack([a, b])
    lo, hi = both.min(axis=0), both.max(axis=0)
    span = float(max(hi - lo)) or 1.0
    scale = (size - 20) / span

    def pts(xy: np.ndarray) -> str:
        return " ".join(f"{10 + (x - lo[0]) * scale:.1f},{size - 10 - (y - lo[1]) * scale:.1f}" for x, y in xy)

    return (f'<figure style="display:inline-block;margin:4px"><svg xmlns="http://www.w3.org/2000/svg" '
            f'width="{size}" height="{size}" style="border:1px solid #ddd"><title>{html.escape(title)}</title>'
            f'<polyline points="{pts(a)}" fill="none" stroke="{A_COLOUR}" stroke-width="1.5"/>'
            f'<polyline points="{pts(b)}" fill="none" stroke="{B_COLOUR}" stroke-width="1.2"/></svg>'
            f"<figcaption>{html.escape(title)} ({span:.3g} m across)</figcaption></figure>")


def _trajectories(c: Comparison) -> list[str]:
    """One overlay per cell and seed pair where both runs exported trajectory.tum."""
    out = []
    index = {s: {(r["recording"], r["pipeline"], r["variant"], r.get("recording_seed"), r.get("seed")): r
                 for r in side.rows} for s, side in (("A", c.a), ("B", c.b))}
    for key, ra in index["A"].items():
        rb = index["B"].get(key)
        if rb is None:
            continue
        ta, tb = _trajectory(ra.get("run_dir")), _trajectory(rb.get("run_dir"))
        if ta is not None and tb is not None:
            rs = "" if key[3] is None else f" recording seed {key[3]},"
            out.append(_trajectory_plot(ta, tb, f"{key[0]}/{key[1]}/{key[2]}{rs} seed {key[4]}"))
    return out


def _link(path: str | None, base: Path, text: str) -> str:
    if not path:
        return ""
    try:
        href = os.path.relpath(path, base)
    except ValueError:
        href = path
    return f'<a href="{html.escape(href)}">{html.escape(text)}</a>'


def _runs(c: Comparison, r: MetricResult, side: str) -> list[str]:
    rows = (c.a if side == "A" else c.b).rows
    return [str(x.get("run_dir")) for x in rows
            if (x["recording"], x["pipeline"], x["variant"]) == (r.recording, r.pipeline, r.variant)]


def render_html(c: Comparison, base: Path) -> str:
    """The report; links are relative to ``base`` (the report's folder)."""
    e = html.escape
    reg = c.regressions
    out = ["<!doctype html><html><head><meta charset='utf-8'><title>slamreplay compare</title>",
           f"<style>{CSS}</style></head><body>", "<h1>slamreplay compare</h1>",
           f"<p><b>A</b> {e(c.a.label)} &mdash; code {e(', '.join(c.a.code_versions))}<br>"
           f"<b>B</b> {e(c.b.label)} &mdash; code {e(', '.join(c.b.code_versions))}</p>",
           f"<p><b>{len(reg)} regression(s)</b>" + (": " + e(", ".join(
               f"{r.recording}/{r.pipeline}/{r.variant} {r.metric}" for r in reg)) if reg else "") + "</p>",
           "<h2>What changed</h2>"]
    if c.commits:
        out.append(f"<p>Commits A..B ({len(c.commits)}):</p><pre>" + e("\n".join(c.commits)) + "</pre>")
    if c.changes:
        out.append("<ul>" + "".join(f"<li><code>{e(ch['field'])}</code>: {e(repr(ch['a']))} &rarr; "
                                    f"{e(repr(ch['b']))}</li>" for ch in c.changes) + "</ul>")
    if not c.commits and not c.changes:
        out.append("<p>No configuration or library change; code versions as above.</p>")
    out += ["<h2>Metrics</h2>",
            "<p class='legend'>Verdict: a <b>regression</b> is worse beyond tolerance and significant "
            "(paired t-test over seeds, p &lt; 0.05; one seed: tolerance only). Plots: per-seed values, "
            f"<span style='color:{A_COLOUR}'>&#9679; A</span><span style='color:{B_COLOUR}'>&#9679; B</span>"
            "pairs joined by a line.</p>",
            "<table><tr><th class='l'>cell</th><th class='l'>metric</th><th>better</th><th>A mean ± sd</th>"
            "<th>B mean ± sd</th><th>B - A</th><th>tolerance</th><th>p</th><th class='l'>test</th>"
            "<th class='l'>verdict</th><th class='l'>seeds</th><th class='l'>runs</th></tr>"]
    for r in c.results:
        a_links = " ".join(_link(p, base, f"A{i + 1}") for i, p in enumerate(_runs(c, r, "A")))
        b_links = " ".join(_link(p, base, f"B{i + 1}") for i, p in enumerate(_runs(c, r, "B")))
        out.append(f"<tr class='{r.verdict}'><td class='l'>{e(r.recording)}/{e(r.pipeline)}/{e(r.variant)}</td>"
                   f"<td class='l'>{e(r.metric)} {e(r.unit)}</td><td>{e(r.better)}</td>"
                   f"<td>{e(fmt_ms(r.a_mean, r.a_sd))}</td><td>{e(fmt_ms(r.b_mean, r.b_sd))}</td>"
                   f"<td>{e(fmt(r.delta, signed=True))}</td><td>{e(fmt(r.tolerance))}</td>"
                   f"<td>{e(fmt(r.p_value, 3))}</td><td class='l'>{e(r.test)}</td>"
                   f"<td class='l'>{e(r.verdict)}</td><td class='l'>{_strip_plot(r)}</td>"
                   f"<td class='l'>{a_links} {b_links}</td></tr>")
    out.append("</table>")
    plots = _trajectories(c)
    if plots:
        out.append("<h2>Estimated trajectories</h2><p>Each run's trajectory.tum: "
                   f"<span style='color:{A_COLOUR}'>A</span>, <span style='color:{B_COLOUR}'>B</span>.</p>")
        out += plots
    if c.failures:
        out.append("<h2>Failed runs</h2><ul>" + "".join(
            f"<li>{e(f['side'])}: {e(f['cell'])} seeds {e(str(f['seeds']))}: {e(str(f['error']))} "
            f"{_link(f.get('run_dir'), base, 'run')}</li>" for f in c.failures) + "</ul>")
    if c.only_a or c.only_b:
        out.append(f"<p>Not compared: only in A: {e(', '.join(c.only_a) or '-')}; "
                   f"only in B: {e(', '.join(c.only_b) or '-')}</p>")
    out.append("</body></html>\n")
    return "\n".join(out)


def render_markdown(c: Comparison, base: Path) -> str:
    """The same table in GitHub-flavoured markdown (regressions marked with a red circle)."""
    mark = {"regression": "🔴 **regression**", "failed": "🔴 **failed**", "improvement": "🟢 improvement"}
    reg = c.regressions
    lines = [f"### slamreplay compare: {len(reg)} regression(s)", "",
             f"A: `{c.a.label}` ({', '.join(c.a.code_versions)})  ",
             f"B: `{c.b.label}` ({', '.join(c.b.code_versions)})",
             ""]
    if c.commits:
        lines += [f"Commits A..B: {len(c.commits)}", "", *[f"- `{x}`" for x in c.commits[:30]], ""]
    for ch in c.changes:
        lines.append(f"- changed `{ch['field']}`: `{ch['a']!r}` → `{ch['b']!r}`")
    lines += ["", "| cell | metric | A mean ± sd | B mean ± sd | B - A | p | verdict | runs |",
              "| --- | --- | ---: | ---: | ---: | ---: | --- | --- |"]
    for r in c.results:
        runs = " ".join(f"[{s}{i + 1}]({os.path.relpath(p, base)})" for s in ("A", "B")
                        for i, p in enumerate(_runs(c, r, s)))
        lines.append(f"| {r.recording}/{r.pipeline}/{r.variant} | {r.metric} | {fmt_ms(r.a_mean, r.a_sd)} | "
                     f"{fmt_ms(r.b_mean, r.b_sd)} | {fmt(r.delta, signed=True)} | {fmt(r.p_value, 3)} | "
                     f"{mark.get(r.verdict, r.verdict)} | {runs} |")
    for f in c.failures:
        lines.append(f"\n- failed in {f['side']}: {f['cell']} seeds {f['seeds']}: {f['error']}")
    return "\n".join(lines) + "\n"


def write_reports(c: Comparison, html_path: str | Path | None, md_path: str | Path | None) -> None:
    """Write the requested files, each whole or not at all."""
    for path, render in ((html_path, render_html), (md_path, render_markdown)):
        if path is None:
            continue
        p = Path(path)
        atomic_write(p, render(c, p.resolve().parent))


def verdict_counts(results: Sequence[MetricResult]) -> dict[str, int]:
    out: dict[str, int] = {}
    for r in results:
        out[r.verdict] = out.get(r.verdict, 0) + 1
    return out
