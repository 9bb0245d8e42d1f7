"""A comparison as one self-contained HTML file, and as a markdown table for a CI job summary.

The HTML needs no network: CSS is inline and every plot is an inline SVG drawn here (per-seed
values of A and B on one axis, the A-B pairs joined, so a shift shared by every seed stands
out from scatter; and the estimated trajectories of A and B overlaid, per cell and seed, from
each run's ``trajectory.tum``). Regressions are red, improvements green, the rest grey. Each cell links to
its A and B run directories and, where a comparison ``.rrd`` of an A/B pair is known (``compare
--rrd-dir``, or the service, which makes one on request), to it.
"""

from __future__ import annotations

import html
import os
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from slamreplay.replay.engine.trajectory import TRUTH_TUM_ARTIFACT, TUM_ARTIFACT, paired_with_truth, read_tum
from slamreplay.replay.runs.compare import (
    REGRESSION_VERDICTS,
    VERDICT_ORDER,
    Comparison,
    MetricResult,
    fmt,
    fmt_ms,
    program_lines,
)
from slamreplay.replay.runs.run import atomic_write

COLOURS = {"regression": "#c62828", "failed": "#c62828", "improvement": "#2e7d32"}
A_COLOUR, B_COLOUR = "#7f7f7f", "#1f77b4"  # A grey (the baseline), B blue (the estimate under test)
CSS = """
body{font-family:system-ui,sans-serif;margin:2em;color:#222}
table{border-collapse:collapse;font-size:13px}td,th{padding:3px 8px;border-bottom:1px solid #ddd;text-align:right}
td.l,th.l{text-align:left}tr.regression,tr.failed,tr.lost{background:#fde0e0;color:#8b0000;font-weight:bold}
tr.improvement{background:#e3f4e3;color:#1b5e20}tr.unchanged,tr.noise,tr.changed,tr.missing{color:#777}
code{background:#f3f3f3;padding:0 3px}.legend span{margin-right:1em}td a{white-space:nowrap}
"""



def _named(metric: str, unit: str) -> str:
    """A metric's name with its unit, unless the name already ends with it (``landmark_rmse_m``, unit m)."""
    return metric if not unit or metric.endswith(f"_{unit}") else f"{metric} ({unit})"

def _strip_plot(r: MetricResult, width: int = 220, height: int = 34) -> str:
    """Per-seed values: A (grey) on the upper row, B (blue) on the lower, pairs joined."""
    vals = [*r.a, *r.b]
    if not vals or len(r.a) != len(r.b):  # a lost metric: nothing in B to pair with
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


def _thin(rows: np.ndarray, most: int = 400) -> np.ndarray:
    """At most about ``most`` evenly spaced rows, the last one kept."""
    step = max(1, len(rows) // most)
    return np.vstack([rows[::step], rows[-1:]])


def _curves(path: str | None) -> tuple[np.ndarray | None, np.ndarray | None]:
    """From a run's trajectory.tum (read once) and truth.tum: its (n, 2) positions, and (n, 2) seconds since the
    first pose with truth against position error (m), each thinned to about 400 points; None where a file is
    missing or unreadable."""
    if not path:
        return None, None
    try:
        t, est = read_tum((Path(path) / TUM_ARTIFACT).read_text())
    except (OSError, ValueError):
        return None, None
    if not len(est):
        return None, None
    xy = _thin(est[:, :2])
    try:
        t_truth, truth = read_tum((Path(path) / TRUTH_TUM_ARTIFACT).read_text())
    except (OSError, ValueError):
        return xy, None
    paired = paired_with_truth(t, est, t_truth)
    if paired is None or not len(t_truth):
        return xy, None
    return xy, _thin(np.column_stack([t_truth - t_truth[0], np.hypot(*(paired[:, :2] - truth[:, :2]).T)]))


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


def _error_plot(a: np.ndarray, b: np.ndarray, title: str, width: int = 360, height: int = 260) -> str:
    """A's and B's position error against time, on shared axes from 0."""
    t_max = float(max(a[-1, 0], b[-1, 0])) or 1.0
    e_max = float(max(a[:, 1].max(), b[:, 1].max())) or 1.0

    def pts(te: np.ndarray) -> str:
        return " ".join(f"{40 + t / t_max * (width - 50):.1f},{height - 25 - e / e_max * (height - 40):.1f}"
                        for t, e in te)

    axes = (f'<line x1="40" y1="{height - 25}" x2="{width - 10}" y2="{height - 25}" stroke="#999"/>'
            f'<line x1="40" y1="15" x2="40" y2="{height - 25}" stroke="#999"/>'
            f'<text x="36" y="19" font-size="10" text-anchor="end">{e_max:.3g}</text>'
            f'<text x="36" y="{height - 25}" font-size="10" text-anchor="end">0</text>'
            f'<text x="{width - 10}" y="{height - 10}" font-size="10" text-anchor="end">{t_max:.4g} s</text>')
    return (f'<figure style="display:inline-block;margin:4px"><svg xmlns="http://www.w3.org/2000/svg" '
            f'width="{width}" height="{height}" style="border:1px solid #ddd"><title>{html.escape(title)}</title>'
            f'{axes}<polyline points="{pts(a)}" fill="none" stroke="{A_COLOUR}" stroke-width="1.5"/>'
            f'<polyline points="{pts(b)}" fill="none" stroke="{B_COLOUR}" stroke-width="1.2"/></svg>'
            f"<figcaption>{html.escape(title)}: position error (m) over time</figcaption></figure>")


def _trajectories(c: Comparison) -> list[str]:
    """One overlay per cell and seed pair where both runs exported trajectory.tum, and their position error over
    time where both have truth.tum."""
    out = []
    index = {s: {(r["recording"], r["pipeline"], r["variant"], r.get("recording_seed"), r.get("seed")): r
                 for r in side.rows} for s, side in (("A", c.a), ("B", c.b))}
    for key, ra in index["A"].items():
        rb = index["B"].get(key)
        if rb is None:
            continue
        (ta, ea), (tb, eb) = _curves(ra.get("run_dir")), _curves(rb.get("run_dir"))
        if ta is not None and tb is not None:
            rs = "" if key[3] is None else f" recording seed {key[3]},"
            out.append(_trajectory_plot(ta, tb, f"{key[0]}/{key[1]}/{key[2]}{rs} seed {key[4]}"))
            if ea is not None and eb is not None:
                out.append(_error_plot(ea, eb, f"{key[0]}/{key[1]}/{key[2]}{rs} seed {key[4]}"))
    return out


Row = Mapping[str, Any]


@dataclass(frozen=True)
class Links:
    """Where the report's links point: a run (by its results row) and an A/B pair's comparison .rrd.

    The defaults suit a report file: run directories relative to the report's folder, and no
    pair links. The service links its own pages instead; ``compare --rrd-dir`` adds pair files.
    """

    run: Callable[[Row], str | None] | None = None
    pair: Callable[[Row, Row], str | None] | None = None


def _href(path: str, base: Path) -> str:
    try:
        return os.path.relpath(path, base)
    except ValueError:
        return path


def _inside(href: str | None) -> str | None:
    """``href`` when it stays inside the report's folder; None for ``../...`` (a run in the user's cache, say):
    in a CI job summary such a link is dead wherever it is read."""
    if href is None or href == ".." or href.startswith("../") or href.startswith("/") or ":" in href:
        return None
    return href


def _run_href(row: Row, base: Path, links: Links) -> str | None:
    if links.run is not None:
        return links.run(row)
    path = row.get("run_dir")
    return _href(str(path), base) if path else None


def _link(href: str | None, text: str, title: str = "") -> str:
    if not href:
        return ""
    tip = f' title="{html.escape(title)}"' if title else ""
    return f'<a href="{html.escape(href)}"{tip}>{html.escape(text)}</a>'


def _group_rows(c: Comparison, r: MetricResult, side: str) -> list[Row]:
    rows = (c.a if side == "A" else c.b).rows
    return [x for x in rows if (x["recording"], x["pipeline"], x["variant"]) == (r.recording, r.pipeline, r.variant)]


def seed_pairs(c: Comparison, r: MetricResult) -> list[tuple[Row, Row]]:
    """The A and B rows of ``r``'s cell with the same seeds (recording seed, run seed), in seed order."""
    def seeds(x: Row) -> tuple[int, int]:
        rs = x.get("recording_seed")
        return (-1 if rs is None else int(rs), int(x.get("seed") or 0))

    b = {seeds(x): x for x in _group_rows(c, r, "B")}
    a = {seeds(x): x for x in _group_rows(c, r, "A")}
    if len(a) == 1 and len(b) == 1 and c.a.kind == "run" and c.b.kind == "run":
        return [(next(iter(a.values())), next(iter(b.values())))]  # two lone runs are one pair, whatever their seeds
    return [(a[s], b[s]) for s in sorted(set(a) & set(b))]


def _links_here(r: MetricResult, shown: set[tuple[str, str, str]]) -> bool:
    """A cell's links go on its first row and on each of its regressions, not on every metric's row."""
    key = (r.recording, r.pipeline, r.variant)
    first = key not in shown
    shown.add(key)
    return first or r.verdict in REGRESSION_VERDICTS


def _pair_label(ra: Row) -> str:
    rs = ra.get("recording_seed")
    return f"A/B {'' if rs is None else f'r{rs}'}s{ra.get('seed', 0)}"


def _cell_links(c: Comparison, r: MetricResult, base: Path, links: Links) -> str:
    out = [_link(_run_href(x, base, links), f"{side}{i + 1}") for side in ("A", "B")
           for i, x in enumerate(_group_rows(c, r, side))]
    if links.pair is not None:
        for ra, rb in seed_pairs(c, r):
            rs = "" if ra.get("recording_seed") is None else f"recording seed {ra.get('recording_seed')}, "
            out.append(_link(links.pair(ra, rb), _pair_label(ra),
                             f"{rs}seed {ra.get('seed', 0)}: both runs in one .rrd"))
    return " ".join(x for x in out if x)


def write_pair_rrds(c: Comparison, rrd_dir: Path, write: Callable[[Path, Path, Path], None]
                    ) -> dict[tuple[str, str], Path]:
    """One comparison .rrd per A/B pair of succeeded runs in ``rrd_dir`` (``write(a_dir, b_dir, out)``);
    (A run dir, B run dir) -> file. A file already there is reused (its name holds both run directories')."""
    made: dict[tuple[str, str], Path] = {}
    for r in c.results:
        for ra, rb in seed_pairs(c, r):
            key = (str(ra.get("run_dir")), str(rb.get("run_dir")))
            if key in made or ra.get("status") != "succeeded" or rb.get("status") != "succeeded":
                continue
            out = rrd_dir / f"{Path(key[0]).name}--{Path(key[1]).name}.rrd"
            if not out.is_file():
                rrd_dir.mkdir(parents=True, exist_ok=True)
                write(Path(key[0]), Path(key[1]), out)
            made[key] = out
    return made


def pair_file_links(files: Mapping[tuple[str, str], Path]) -> Callable[[Path], Links]:
    """``write_reports``'s ``pair_links`` for files ``write_pair_rrds`` made: relative to each report."""
    def links(base: Path) -> Links:
        def pair(ra: Row, rb: Row) -> str | None:
            f = files.get((str(ra.get("run_dir")), str(rb.get("run_dir"))))
            return None if f is None else _href(str(f), base)
        return Links(pair=pair)
    return links


def render_html(c: Comparison, base: Path, links: Links | None = None) -> str:
    """The report; links are relative to ``base`` (the report's folder) unless ``links`` says otherwise."""
    links = links or Links()
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
    if c.programs:
        out.append("<ul>" + "".join(f"<li>{e(line)}</li>" for line in program_lines(c)) + "</ul>")
    if not c.commits and not c.changes:
        out.append("<p>No configuration, library or program change; code versions as above.</p>")
    out += ["<h2>Metrics</h2>",
            "<p class='legend'>Verdict: a <b>regression</b> is worse beyond tolerance and significant "
            "(paired t-test over seeds, p &lt; 0.05; one seed: tolerance only). Plots: per-seed values, "
            f"<span style='color:{A_COLOUR}'>&#9679; A</span><span style='color:{B_COLOUR}'>&#9679; B</span>"
            "pairs joined by a line.</p>",
            "<table><tr><th class='l'>cell</th><th class='l'>metric</th><th>better</th><th>A mean ± sd</th>"
            "<th>B mean ± sd</th><th>B - A</th><th>tolerance</th><th>p</th><th class='l'>test</th>"
            "<th class='l'>verdict</th><th class='l'>seeds</th><th class='l'>runs</th></tr>"]
    shown: set[tuple[str, str, str]] = set()
    for r in ranked(c.results):
        cell_links = _cell_links(c, r, base, links) if _links_here(r, shown) else ""
        out.append(f"<tr class='{r.verdict}'><td class='l'>{e(r.recording)}/{e(r.pipeline)}/{e(r.variant)}</td>"
                   f"<td class='l'>{e(_named(r.metric, r.unit))}</td><td>{e(r.direction)}</td>"
                   f"<td>{e(fmt_ms(r.a_mean, r.a_sd))}</td><td>{e(fmt_ms(r.b_mean, r.b_sd))}</td>"
                   f"<td>{e(fmt(r.delta, signed=True))}</td><td>{e(fmt(r.tolerance))}</td>"
                   f"<td>{e(fmt(r.p_value, 3))}</td><td class='l'>{e(r.test)}</td>"
                   f"<td class='l'>{e(r.verdict)}</td><td class='l'>{_strip_plot(r)}</td>"
                   f"<td class='l'>{cell_links}</td></tr>")
    out.append("</table>")
    plots = _trajectories(c)
    if plots:
        out.append("<h2>Estimated trajectories and their error over time</h2><p>Each run's trajectory.tum, and "
                   "its distance to truth.tum (the ground truth at the same times) where the run has one: "
                   f"<span style='color:{A_COLOUR}'>A</span>, <span style='color:{B_COLOUR}'>B</span>.</p>")
        out += plots
    if c.failures:
        out.append("<h2>Failed runs</h2><ul>" + "".join(
            f"<li>{e(f['side'])}: {e(f['cell'])} seeds {e(str(f['seeds']))}: {e(str(f['error']))} "
            f"{_link(_run_href(f, base, links), 'run')}</li>" for f in c.failures) + "</ul>")
    if c.only_a or c.only_b:
        out.append(f"<p>Not compared: only in A: {e(', '.join(c.only_a) or '-')}; "
                   f"only in B: {e(', '.join(c.only_b) or '-')}</p>")
    out.append("</body></html>\n")
    return "\n".join(out)


FOLDED = ("unchanged", "noise")  # rows a CI summary folds away: nothing to act on


def ranked(results: Sequence[MetricResult]) -> list[MetricResult]:
    """Results in the order a reader acts on them: regressions and failures first (VERDICT_ORDER); stable, so
    each verdict's rows keep their cells' order."""
    order = {v: i for i, v in enumerate(VERDICT_ORDER)}
    return sorted(results, key=lambda r: order.get(r.verdict, len(order)))


def render_markdown(c: Comparison, base: Path, links: Links | None = None, base_url: str | None = None) -> str:
    """The same table in GitHub-flavoured markdown, for a CI job summary: regressions (red circle) and failures
    first, then improvements and changes; unchanged and noise rows folded into a closed ``<details>``.

    Links are relative to the summary's folder ``base``, or ``base_url`` + that relative path (where CI
    publishes that folder); files outside ``base`` are not linked."""
    links = links or Links()
    prefix = base_url.rstrip("/") + "/" if base_url else ""
    inner = links

    def run(row: Row) -> str | None:
        href = _inside(_run_href(row, base, inner))
        return None if href is None else prefix + href

    def pair(ra: Row, rb: Row) -> str | None:
        href = _inside(inner.pair(ra, rb) if inner.pair is not None else None)
        return None if href is None else prefix + href

    links = Links(run=run, pair=pair if inner.pair is not None else None)
    mark = {"regression": "🔴 **regression**", "failed": "🔴 **failed**", "lost": "🔴 **lost** (missing in B)",
            "improvement": "🟢 improvement"}
    reg = c.regressions
    lines = [f"### slamreplay compare: {len(reg)} regression(s)", "",
             f"A: `{c.a.label}` ({', '.join(c.a.code_versions)})  ",
             f"B: `{c.b.label}` ({', '.join(c.b.code_versions)})",
             ""]
    if c.commits:
        lines += [f"Commits A..B: {len(c.commits)}", "", *[f"- `{x}`" for x in c.commits[:30]], ""]
    for ch in c.changes:
        lines.append(f"- changed `{ch['field']}`: `{ch['a']!r}` → `{ch['b']!r}`")
    lines += [f"- {line}" for line in program_lines(c)]
    head = ["| cell | metric | A mean ± sd | B mean ± sd | B - A | p | verdict | runs |",
            "| --- | --- | ---: | ---: | ---: | ---: | --- | --- |"]
    rows = ranked(c.results)
    quiet = [r for r in rows if r.verdict in FOLDED]
    loud = [r for r in rows if r.verdict not in FOLDED]
    lines += ["", *head]
    shown: set[tuple[str, str, str]] = set()
    for r in loud + quiet:
        if r is (quiet[0] if quiet else None):
            what = ", ".join(f"{n} {v}" for v, n in verdict_counts(quiet).items())
            lines += ["", f"<details><summary>{len(quiet)} more rows: {what}</summary>", "", *head]
        here = _links_here(r, shown)
        runs = " ".join(f"[{s}{i + 1}]({href})" for s in ("A", "B")
                        for i, x in enumerate(_group_rows(c, r, s)) if here and (href := _run_href(x, base, links)))
        if links.pair is not None and here:
            runs += "".join(f" [{_pair_label(ra)}]({href})" for ra, rb in seed_pairs(c, r)
                            if (href := links.pair(ra, rb)))
        lines.append(f"| {r.recording}/{r.pipeline}/{r.variant} | {r.metric} | {fmt_ms(r.a_mean, r.a_sd)} | "
                     f"{fmt_ms(r.b_mean, r.b_sd)} | {fmt(r.delta, signed=True)} | {fmt(r.p_value, 3)} | "
                     f"{mark.get(r.verdict, r.verdict)} | {runs} |")
    if quiet:
        lines += ["", "</details>"]
    for f in c.failures:
        lines.append(f"\n- failed in {f['side']}: {f['cell']} seeds {f['seeds']}: {f['error']}")
    return "\n".join(lines) + "\n"


def write_reports(c: Comparison, html_path: str | Path | None, md_path: str | Path | None,
                  pair_links: Callable[[Path], Links] | None = None, base_url: str | None = None) -> None:
    """Write the requested files, each whole or not at all; ``pair_links(base)`` adds comparison .rrd links;
    ``base_url``: where CI publishes the markdown summary's folder (its links then start with it)."""
    if html_path is not None:
        p = Path(html_path)
        base = p.resolve().parent
        atomic_write(p, render_html(c, base, pair_links(base) if pair_links else None))
    if md_path is not None:
        p = Path(md_path)
        base = p.resolve().parent
        atomic_write(p, render_markdown(c, base, pair_links(base) if pair_links else None, base_url))


def verdict_counts(results: Sequence[MetricResult]) -> dict[str, int]:
    out: dict[str, int] = {}
    for r in results:
        out[r.verdict] = out.get(r.verdict, 0) + 1
    return out
