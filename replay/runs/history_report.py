"""A history's report: ``DIR/index.html`` (self-contained), the changes as markdown, and as plain text.

``index.html`` holds everything inline (CSS, SVG; no script, nothing fetched): the changes found,
then a grid of the cell groups x metrics, each a small plot of the per-commit mean (line) and the
seeds' spread (a whisker from the lowest to the highest seed) over the commits, each change a
dashed line coloured by its verdict. Each point links to its commit's row in the commits table,
which lists that commit's runs (their ``run.rrd``) and the compare report against the previous
commit with results (``DIR/compare/<a>-<b>-<hash>.html``, made by ``report.py`` once per pair of
commits and cells). A history over days (``history_dates``) makes ``DIR/by-date.html`` the same way,
its points days, without compare reports. Each plot's y axis stops at the metric's registered range
(:func:`y_range`).
"""

from __future__ import annotations

import hashlib
import html
import json
import os
import warnings
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from slamreplay.recorder.files import atomic_write
from slamreplay.replay.metric_registry import axis_bounds
from slamreplay.replay.runs.changepoints import Change
from slamreplay.replay.runs.compare import compare, fmt, side_of_rows
from slamreplay.replay.runs.history import History, series
from slamreplay.replay.runs.history_dates import ALL_RECORDINGS
from slamreplay.replay.runs.report import write_reports

REPORT = {"commit": "index.html", "date": "by-date.html"}
CHANGES = {"commit": "changes.json", "date": "changes-by-date.json"}
COLOURS = {"regression": "#c62828", "lost": "#c62828", "improvement": "#2e7d32", "changed": "#757575"}
CSS = """body{font:14px system-ui,sans-serif;margin:1.2em;color:#222}table{border-collapse:collapse}
td,th{padding:2px 8px;border-bottom:1px solid #ddd;text-align:left;vertical-align:top}
.grid td{border:none;padding:4px}.regression,.lost{color:#c62828}.improvement{color:#2e7d32}
tr:target{background:#fff3c4}svg{background:#fafafa;border:1px solid #e0e0e0}code{font-size:90%}
.failed{color:#c62828}.small{color:#666;font-size:90%}"""


def _pair_report(history: History, a: str, b: str, out: Path) -> str | None:
    """The compare report of commit ``a`` against ``b`` in ``out/compare/`` (made once); its path relative to out."""
    ra, rb = history.cells(a), history.cells(b)
    if not ra or not rb:
        return None
    keys = hashlib.sha256("\n".join(sorted(str(r.get("key")) for r in (*ra, *rb))).encode()).hexdigest()[:8]
    rel = f"compare/{a[:10]}-{b[:10]}-{keys}.html"
    if not (out / rel).is_file():
        from slamreplay.replay.errors import ReplayError
        try:
            with warnings.catch_warnings():  # seeds that differ equally up to rounding: p is ~0 all the same
                warnings.simplefilter("ignore", RuntimeWarning)
                c = compare(side_of_rows(f"commit {a[:10]}", ra, "rev", a),
                            side_of_rows(f"commit {b[:10]}", rb, "rev", b))
        except ReplayError:
            return None
        (out / "compare").mkdir(parents=True, exist_ok=True)
        write_reports(c, out / rel, None)
    return rel


def pair_reports(history: History, changes: Sequence[Change], out: Path) -> tuple[dict[str, str], list[Change]]:
    """Compare reports of each commit with data against the one before it: {later sha: path}, and the changes
    with their report."""
    reports: dict[str, str] = {}
    prev = None
    for c in history.commits:
        if not any(r["status"] == "succeeded" for r in history.cells(c.sha)):
            continue
        if prev is not None and (rel := _pair_report(history, prev, c.sha, out)) is not None:
            reports[c.sha] = rel
        prev = c.sha
    linked = []
    for ch in changes:
        rel = reports.get(ch.commit) or _pair_report(history, ch.previous, ch.commit, out)
        linked.append(Change(**{**ch.to_json(), "report": rel}))
    return reports, linked


def y_range(lo: float, hi: float, bounds: tuple[float | None, float | None] = (None, None)) -> tuple[float, float]:
    """The y axis of data from ``lo`` to ``hi``: 8 % of their span on each side, never past the metric's registered
    (least, greatest) values (``metric_registry.axis_bounds``) unless the data are."""
    span = (hi - lo) or (abs(hi) * 0.1 or 1.0)
    low, high = lo - 0.08 * span, hi + 0.08 * span
    least, greatest = bounds
    if least is not None and lo >= least:
        low = max(low, least)
    if greatest is not None and hi <= greatest:
        high = min(high, greatest)
    return low, high


def plot_svg(values: Sequence[dict[int, float]], marks: Sequence[Change], width: int = 240, height: int = 90,
             label: str = "a metric over commits", bounds: tuple[float | None, float | None] = (None, None)) -> str:
    """One series as inline SVG: the mean line, the seeds' range as whiskers, changes as dashed lines; point k
    links to ``#c<k>`` (its commit's row), a commit without a succeeded run is a red cross. ``bounds``: the
    metric's (least, greatest) values, where the y axis stops (:func:`y_range`)."""
    n = len(values)
    have = [k for k, v in enumerate(values) if v]
    if not have:
        return "<svg width='240' height='90'></svg>"
    lo, hi = y_range(min(min(values[k].values()) for k in have), max(max(values[k].values()) for k in have),
                     bounds)

    def x(k: float) -> float:
        return 8 + (width - 16) * (k / max(n - 1, 1))

    def y(v: float) -> float:
        return height - 6 - (height - 12) * (v - lo) / (hi - lo)

    # its points are links: a named group, not an image (which may hold no interactive control)
    parts = [f"<svg width='{width}' height='{height}' role='group' aria-label='{html.escape(label, quote=True)}'>"]
    for ch in marks:
        xm = (x(ch.index) + x(ch.index - 1)) / 2 if ch.index > 0 else x(0)
        parts.append(f"<line x1='{xm:.1f}' x2='{xm:.1f}' y1='2' y2='{height - 2}' stroke='{COLOURS[ch.verdict]}' "
                     f"stroke-dasharray='4 3'><title>{html.escape(ch.verdict)}: {fmt(ch.mean_before)} &#8594; "
                     f"{fmt(ch.mean_after)} at {ch.commit[:10]}</title></line>")
    means = [(k, float(np.mean(list(values[k].values())))) for k in have]
    parts.append("<polyline fill='none' stroke='#1565c0' stroke-width='1.5' points='"
                 + " ".join(f"{x(k):.1f},{y(v):.1f}" for k, v in means) + "'/>")
    for k, v in means:
        vs = values[k].values()
        parts.append(f"<line x1='{x(k):.1f}' x2='{x(k):.1f}' y1='{y(min(vs)):.1f}' y2='{y(max(vs)):.1f}' "
                     f"stroke='#90a4ae'/><a href='#c{k}'><circle cx='{x(k):.1f}' cy='{y(v):.1f}' r='3' "
                     f"fill='#1565c0'><title>commit {k + 1}: mean {fmt(v)} over {len(vs)} seed(s)</title></circle></a>")
    for k in range(n):
        if not values[k]:
            parts.append(f"<a href='#c{k}'><text x='{x(k) - 3:.1f}' y='{height - 2}' fill='#c62828' "
                         f"font-size='10'>&#215;<title>commit {k + 1}: no run succeeded</title></text></a>")
    parts.append(f"<text x='2' y='10' font-size='9' fill='#666'>{html.escape(fmt(hi))}</text>"
                 f"<text x='2' y='{height - 1}' font-size='9' fill='#666'>{html.escape(fmt(lo))}</text></svg>")
    return "".join(parts)


def _rel(path: str | None, base: Path) -> str | None:
    if not path:
        return None
    try:
        return os.path.relpath(path, base)
    except ValueError:
        return path


# what a point of a history is: a commit, or a day (``history_dates``)
WORDS = {"commit": ("commit", "commits", "per-commit"), "date": ("day", "days", "per-day")}


def render_index(history: History, changes: Sequence[Change], out: Path, reports: dict[str, str],
                 metrics: Sequence[str] = (), by: str = "commit") -> str:
    """The page (see the module docstring); links relative to ``out``. ``by="date"``: a history over days."""
    e = html.escape
    one, many, per = WORDS[by]
    over = " over the days it ran" if by == "date" else ""
    name = next((str(s.get("suite")) for s in history.status.values() if s.get("suite")), "suite")
    body = [f"<!doctype html><html><head><meta charset='utf-8'><title>slamreplay history: {e(name)}</title>"
            f"<style>{CSS}</style></head><body><h1>History of suite {e(name)}{over}</h1>",
            f"<p>{len(history.commits)} {one}(s)"
            + (f", {e(history.commits[0].short)} .. {e(history.commits[-1].short)}" if history.commits else "")
            + f"; {len(changes)} change(s). Each plot: {per} mean (line) and the seeds' range (whisker), "
              "changes dashed (<span class='regression'>worse</span>, <span class='improvement'>better</span>, "
              f"grey: changed). Click a point for its {one}'s runs"
            + (" and the comparison with the commit before.</p>" if by == "commit" else
               f" and the code versions that ran. Series \"{ALL_RECORDINGS}\": per seed, the mean over a day's "
               "recordings.</p>"),
            "<h2>Changes</h2>"]
    if changes:
        body.append(f"<table><tr><th>{one}</th><th>cell</th><th>metric</th><th>before</th><th>after</th>"
                    "<th>change</th><th>verdict</th><th>p</th><th>report</th></tr>")
        for ch in changes:
            c = history.commits[ch.index]
            rel = f" ({ch.relative:+.1%})" if ch.relative is not None else ""
            link = f"<a href='{e(ch.report)}'>compare</a>" if ch.report else ""
            body.append(f"<tr><td><a href='#c{ch.index}'><code>{e(c.short)}</code></a> {e(c.subject[:70])}</td>"
                        f"<td>{e(ch.cell)}</td><td>{e(ch.metric)}</td><td>{e(fmt(ch.mean_before))}</td>"
                        f"<td>{e(fmt(ch.mean_after))}</td><td>{e(fmt(ch.delta, signed=True))}{e(rel)}</td>"
                        f"<td class='{e(ch.verdict)}'>{e(ch.verdict)}</td><td>{e(fmt(ch.p_value, 3))}</td>"
                        f"<td>{link}</td></tr>")
        body.append("</table>")
    else:
        body.append("<p>No metric changed beyond seed noise and its tolerance.</p>")
    body.append(f"<h2>Metrics over {many}</h2>")
    by_group = series(history)
    for group, by_metric in sorted(by_group.items()):
        names = [m for m in sorted(by_metric) if not metrics or m in metrics]
        body.append(f"<h3>{e('/'.join(group))}</h3><table class='grid'><tr>")
        for i, m in enumerate(names):
            marks = [ch for ch in changes if (ch.recording, ch.pipeline, ch.variant) == group and ch.metric == m]
            if i and i % 4 == 0:
                body.append("</tr><tr>")
            plot = plot_svg(by_metric[m], marks, label=f"{m} of {'/'.join(group)} over {many}",
                            bounds=axis_bounds(m))
            body.append(f"<td><div class='small'>{e(m)}</div>{plot}</td>")
        body.append("</tr></table>")
    date_th = "<th>date</th>" if by == "commit" else ""
    body.append(f"<h2>{many.capitalize()}</h2><table><tr><th>#</th><th>{one}</th>{date_th}<th>status</th>"
                f"<th>runs</th><th>against the {one} before</th></tr>")
    for k, c in enumerate(history.commits):
        st = history.status.get(c.sha, {})
        status = str(st.get("status", "running"))
        runs = []
        for r in sorted((r for r in history.cells(c.sha) if not r.get("pooled")), key=lambda r: str(r.get("run_dir"))):
            label = (Path(str(r["run_dir"])).name.rsplit("-", 1)[0] if r.get("run_dir") else
                     f"{r.get('recording')}-{r.get('pipeline')}-{r.get('variant')}-seed{r.get('seed')}")
            href = _rel(str(Path(str(r["run_dir"])) / "run.rrd"), out) if r.get("run_dir") else None
            if r["status"] == "succeeded" and href:
                runs.append(f"<a href='{e(href)}'>{e(label)}</a>")
            elif r["status"] == "succeeded":
                runs.append(e(label))
            else:
                runs.append(f"<span class='failed' title='{e(str(r.get('error')))}'>{e(label)} failed</span>")
        err = f"<div class='failed small'>{e(str(st.get('error')))}</div>" if st.get("error") else ""
        cmp_link = f"<a href='{e(reports[c.sha])}'>compare</a>" if c.sha in reports else ""
        note = f"<div class='small'>{e(c.note)}</div>" if c.note else ""
        body.append(f"<tr id='c{k}'><td>{k + 1}</td><td><code>{e(c.short)}</code> {e(c.subject[:80])}{note}</td>"
                    + (f"<td>{e(c.date[:19])}</td>" if by == "commit" else "")
                    + f"<td class='{'failed' if 'failed' in status else ''}'>{e(status)}"
                    f"{err}</td><td class='small'>{' '.join(runs)}</td><td>{cmp_link}</td></tr>")
    body.append("</table></body></html>\n")
    return "\n".join(body)


def render_markdown(history: History, changes: Sequence[Change], base: Path, out: Path,
                    base_url: str | None = None, by: str = "commit") -> str:
    """The changes as a markdown table for a CI job summary; links relative to ``base`` (the summary's folder),
    or ``base_url`` + that path; files outside ``base`` are named, not linked. ``by="date"``: a history over days."""
    one, _many, _per = WORDS[by]
    page = REPORT[by]
    prefix = base_url.rstrip("/") + "/" if base_url else ""

    def link(path: Path, text: str) -> str:
        rel = _rel(str(path.resolve()), base.resolve())
        if rel is None or rel == ".." or rel.startswith("../") or rel.startswith("/"):
            return text
        return f"[{text}]({prefix}{rel})"

    name = next((str(s.get("suite")) for s in history.status.values() if s.get("suite")), "suite")
    worse = sum(1 for ch in changes if ch.verdict in ("regression", "lost"))
    lines = [f"### History of suite {name}: {len(changes)} change(s), {worse} for the worse, over "
             f"{len(history.commits)} {one}(s) ({link(out / page, 'report')})", ""]
    if not changes:
        return "\n".join(lines + ["No metric changed beyond seed noise and its tolerance.", ""])
    lines += [f"| {one} | cell | metric | before | after | change | verdict | report |",
              "| --- | --- | --- | ---: | ---: | ---: | --- | --- |"]
    icon = {"regression": "🔴 ", "lost": "🔴 ", "improvement": "🟢 ", "changed": ""}
    for ch in changes:
        c = history.commits[ch.index]
        rel = f" ({ch.relative:+.1%})" if ch.relative is not None else ""
        rep = link(out / ch.report, "compare") if ch.report else ""
        subject = c.subject[:60].replace("|", "\\|")
        lines.append(f"| `{c.short}` {subject} | {ch.cell} | {ch.metric} | {fmt(ch.mean_before)} | "
                     f"{fmt(ch.mean_after)} | {fmt(ch.delta, signed=True)}{rel} | {icon[ch.verdict]}{ch.verdict} | "
                     f"{rep} |")
    return "\n".join(lines) + "\n"


def format_changes(history: History, changes: Sequence[Change]) -> str:
    """The changes as plain text for the terminal."""
    if not changes:
        return "no change: every metric stayed within seed noise and its tolerance"
    lines = []
    for ch in changes:
        c = history.commits[ch.index]
        rel = f" ({ch.relative:+.1%})" if ch.relative is not None else ""
        after = "missing" if ch.mean_after is None else fmt(ch.mean_after)
        lines.append(f"  {c.short} {ch.verdict.upper():11s} {ch.cell} {ch.metric}: {fmt(ch.mean_before)} -> "
                     f"{after}{rel}  {c.subject[:50]}")
    return "changes:\n" + "\n".join(lines)


def write_history_reports(history: History, changes: Sequence[Change], out: Path, markdown: str | Path | None = None,
                          base_url: str | None = None, metrics: Sequence[str] = (), by: str = "commit") -> list[Change]:
    """``out/index.html``, the compare reports it links, ``out/changes.json`` and, with ``markdown``, the summary;
    the changes with their report paths (relative to ``out``). ``by="date"`` (a history over days,
    ``history_dates``): ``out/by-date.html`` and ``out/changes-by-date.json``, without compare reports."""
    reports, linked = pair_reports(history, changes, out) if by == "commit" else ({}, list(changes))
    atomic_write(out / REPORT[by], render_index(history, linked, out, reports, metrics, by))
    atomic_write(out / CHANGES[by], json.dumps([ch.to_json() for ch in linked], indent=1, default=str) + "\n")
    if markdown is not None:
        md = Path(markdown)
        atomic_write(md, render_markdown(history, linked, md.resolve().parent, out.resolve(), base_url, by))
    return linked
