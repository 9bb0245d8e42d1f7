"""Figures the README quotes from `make demo`, checked against (or written from) a demo's own runs.

A figure in README.md (or docs/*.md) that comes from the demo is written between two markers::

    <!-- demo: sim-landmarks--dslam/landmark_rmse_m .3f -->0.165<!-- /demo -->
    <!-- demo: sim-landmarks--dslam/landmark_rmse_m / sim-landmarks--ekfslam/landmark_rmse_m .1f -->3.8<!-- /demo -->

The expression is one metric of one demo run (``RUN/METRIC``: the run folder ``runs/demo/RUN`` and
a name in its metrics.json) or the ratio of two, and the format is Python's. ``--check`` (what
``make test-docs`` runs after a fresh demo) exits 1 listing every figure that differs from the
demo's output; ``--write`` rewrites them (``make readme-figures``), so a figure can only drift
on purpose.

    python docs/demo_figures.py --demo runs/demo --check
"""

from __future__ import annotations

import argparse
import json
import re
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
FILES = [REPO / "README.md", *sorted((REPO / "docs").glob("*.md"))]
SPAN = re.compile(r"<!-- demo: (?P<expr>[^>]*?) (?P<fmt>[.\w,%]+) -->(?P<text>.*?)<!-- /demo -->")


def metric(demo: Path, ref: str) -> float:
    """The value of ``RUN/METRIC`` in the demo folder ``demo``; SystemExit naming what is missing."""
    run, _, name = ref.strip().rpartition("/")
    try:
        doc = json.loads((demo / run / "metrics.json").read_text())
    except FileNotFoundError:
        raise SystemExit(f"demo_figures: {demo / run} has no metrics.json (run `make demo` first)") from None
    try:
        return float(doc["metrics"][name]["value"])
    except KeyError:
        raise SystemExit(f"demo_figures: {demo / run} has no metric {name!r}") from None


def value(demo: Path, expr: str) -> float:
    """``RUN/METRIC`` or ``RUN/METRIC / RUN/METRIC`` (a ratio)."""
    parts = expr.split(" / ")
    if len(parts) == 1:
        return metric(demo, parts[0])
    if len(parts) == 2:
        return metric(demo, parts[0]) / metric(demo, parts[1])
    raise SystemExit(f"demo_figures: {expr!r} is not RUN/METRIC or RUN/METRIC / RUN/METRIC")


def figures(demo: Path, text: str) -> list[tuple[re.Match[str], str]]:
    """Each marked span of ``text`` and the figure the demo gives for it."""
    return [(m, format(value(demo, m["expr"]), m["fmt"])) for m in SPAN.finditer(text)]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--demo", type=Path, default=REPO / "runs" / "demo", help="the demo's folder (default runs/demo)")
    what = ap.add_mutually_exclusive_group(required=True)
    what.add_argument("--check", action="store_true", help="exit 1 when a quoted figure differs from the demo's")
    what.add_argument("--write", action="store_true", help="rewrite the quoted figures from the demo's runs")
    args = ap.parse_args(argv)
    wrong, seen = [], 0
    for path in FILES:
        text = path.read_text()
        found = figures(args.demo, text)
        seen += len(found)
        for m, fig in found:
            if m["text"] != fig:
                line = text.count("\n", 0, m.start()) + 1
                wrong.append(f"{path.relative_to(REPO)}:{line}: {m['expr']}: the text says {m['text']}, "
                             f"the demo gives {fig}")
        if args.write and found:
            new = SPAN.sub(lambda m: m[0].replace(f"-->{m['text']}<!--",
                                                  f"-->{format(value(args.demo, m['expr']), m['fmt'])}<!--"), text)
            if new != text:
                path.write_text(new)
    if args.write:
        print(f"demo_figures: {seen} figure(s) in {len(FILES)} files, {len(wrong)} rewritten from {args.demo}")
        return 0
    for w in wrong:
        print(w, file=sys.stderr)
    print(f"demo_figures: {seen} figure(s) checked against {args.demo}, {len(wrong)} differ"
          + (" (make readme-figures rewrites them)" if wrong else ""))
    return 1 if wrong else 0


if __name__ == "__main__":
    sys.exit(main())
