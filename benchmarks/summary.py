"""One table of ratios from the benchmarks' ``--json`` files: what ``make bench`` ends with.

Each row is a figure measured side by side in one process run (CPU time), its target from issue 17,
and whether it meets it. The README's performance table is this output.

Run: ``.venv/bin/python benchmarks/summary.py DIR`` (DIR holds replay_throughput.json, posegraph.json,
loop_closure_sim.json, loop_closure_rtabmap.json; a missing file is reported as not run).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

# (file, key path, label, target, unit): ratio rows are "x", times "ms"; a target is an upper bound
ROWS: list[tuple[str, tuple[str, ...], str, float, str]] = [
    ("replay_throughput", ("reader_over_raw",), "RecordingReader / raw mcap decode", 1.2, "x"),
    ("replay_throughput", ("noop_over_raw",), "engine, no-op pipeline / raw decode", 1.3, "x"),
    ("replay_throughput", ("odometry_null_over_raw",), "odometry pipeline, no logging / raw decode", float("nan"), "x"),
    ("replay_throughput", ("rrd_over_raw",), "odometry pipeline + Rerun .rrd / raw decode", 2.5, "x"),
    ("posegraph", ("datasets", "m3500", "ours_over_g2o_gn"), "pose graph GN / g2o GN, M3500", 0.8, "x"),
    ("posegraph", ("datasets", "intel", "ours_over_g2o_gn"), "pose graph GN / g2o GN, intel", 0.8, "x"),
    ("posegraph", ("datasets", "city10000", "ours_over_g2o_gn"), "pose graph GN / g2o GN, city10000", 0.8, "x"),
    ("posegraph", ("datasets", "m3500", "ours_plain_over_g2o_gn"), "pose graph GN / g2o GN, M3500, plain install",
     0.8, "x"),
    ("posegraph", ("datasets", "intel", "ours_plain_over_g2o_gn"), "pose graph GN / g2o GN, intel, plain install",
     0.8, "x"),
    ("posegraph", ("datasets", "city10000", "ours_plain_over_g2o_gn"),
     "pose graph GN / g2o GN, city10000, plain install", 0.8, "x"),
    ("posegraph", ("incremental_m3500", "ours_over_isam2"), "incremental M3500 / iSAM2, per closure update, median",
     1.0, "x"),
    ("posegraph", ("incremental_m3500", "ours_over_isam2_mean"), "incremental M3500 / iSAM2, per closure update, mean",
     1.0, "x"),
    ("loop_closure_sim", ("ms_per_image",), "loop closure per 320x240 image, simulator", 8.0, "ms"),
    ("loop_closure_rtabmap", ("ms_per_image",), "loop closure per 320x240 image, RTAB-Map samples", 8.0, "ms"),
]


def _get(doc: dict[str, Any], path: tuple[str, ...]) -> float | None:
    value: Any = doc
    for key in path:
        if not isinstance(value, dict) or key not in value:
            return None
        value = value[key]
    return float(value) if isinstance(value, (int, float)) else None


def table(root: Path) -> list[str]:
    """The summary table's lines (markdown)."""
    docs: dict[str, dict[str, Any] | None] = {}
    for name in {r[0] for r in ROWS}:
        f = root / f"{name}.json"
        try:
            docs[name] = json.loads(f.read_text()) if f.exists() else None
        except json.JSONDecodeError as err:
            print(f"summary: {f} is not JSON ({err}); re-run its benchmark with --json {f}", file=sys.stderr)
            raise SystemExit(2) from err
    lines = ["| figure | measured | target | met |", "| --- | ---: | ---: | :---: |"]
    for name, path, label, target, unit in ROWS:
        doc = docs[name]
        value = None if doc is None else _get(doc, path)
        if value is None:
            lines.append(f"| {label} | not run | {_fmt(target, unit)} | |")
            continue
        met = "" if target != target else ("yes" if value <= target else "no")
        lines.append(f"| {label} | {_fmt(value, unit)} | {_fmt(target, unit)} | {met} |")
    extra = []
    rt = docs.get("replay_throughput")
    if rt and "rrd_bytes" in rt:
        extra.append(f".rrd of the replay benchmark: {rt['rrd_bytes'] / 1e6:.2f} MB ({rt['messages']} messages)")
    pg = docs.get("posegraph")
    if pg:
        extra.append(f"pose-graph linear solver: {pg.get('linear_solver')}; plain install (no `solver` extra): "
                     f"{pg.get('plain_linear_solver', 'superlu')}")
    return lines + ([""] + extra if extra else [])


def _fmt(value: float, unit: str) -> str:
    if value != value:
        return "-"
    return f"{value:.2f}x" if unit == "x" else f"{value:.1f} ms"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("dir", type=Path, help="the folder the benchmarks wrote their --json files to")
    args = parser.parse_args()
    if not args.dir.is_dir():
        print(f"summary: {args.dir} is not a directory; run the benchmarks with --json {args.dir}/NAME.json first",
              file=sys.stderr)
        raise SystemExit(2)
    print("\n".join(table(args.dir)))


if __name__ == "__main__":
    main()
