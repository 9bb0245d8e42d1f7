"""False alarms of `compare` on a program that is not deterministic: unchanged code, compared with itself.

An external program whose output carries run-to-run noise (dead reckoning of the exported odometry plus a
few millimetres of noise per step from ``os.urandom``: a multithreaded solver's summation order, say) is run
on the same recordings (``sim-landmarks``, five simulator seeds) twice per comparison, A and B, with the
same code; ``compare`` judges B against A. Every regression it reports is a false alarm. The first run of
the program checks its determinism by itself (docs/external.md), so ``compare`` knows; for the figure
without that knowledge the same rows are judged again with the determinism verdict removed.

Run: ``.venv/bin/python benchmarks/false_alarms.py [--compares 20] [--seeds 5] [--json PATH]``.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

from bench_io import write_json

from slamreplay.recorder.plugins import refresh
from slamreplay.recorder.sim import LandmarkSimConfig, simulate_landmarks
from slamreplay.replay.engine.declared import DECLARATIONS_ENV
from slamreplay.replay.runs.compare import Side, compare, run_row
from slamreplay.replay.runs.run import run_recording

NOISY = '''
import math, os, sys
out = open(sys.argv[1], "w")
prev = None
x = y = th = 0.0
for line in sys.stdin.read().splitlines()[1:]:
    t, ox, oy, oth = line.split(",")
    t, ox, oy, oth = int(t), float(ox), float(oy), float(oth)
    if prev is not None:
        px, py, pth = prev
        c, s = math.cos(pth), math.sin(pth)
        dx, dy = c * (ox - px) + s * (oy - py), -s * (ox - px) + c * (oy - py)
        x, y = x + math.cos(th) * dx - math.sin(th) * dy, y + math.sin(th) * dx + math.cos(th) * dy
        th = th + oth - pth + (int.from_bytes(os.urandom(2), "big") / 65535.0 - 0.5) * 2e-4
    prev = (ox, oy, oth)
    out.write(f"{t // 10**9}.{t % 10**9:09d} {x!r} {y!r} 0 0 0 {math.sin(th / 2)!r} {math.cos(th / 2)!r}\\n")
'''
DECLARATION = '''[pipelines.noisy]
command = ["{python}", "noisy.py", "{out}/trajectory.tum"]
exports = ["odometry_csv"]
stdin = "{exports}/odometry.csv"
'''


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--compares", type=int, default=20)
    ap.add_argument("--seeds", type=int, default=5)
    ap.add_argument("--duration-s", type=float, default=30.0)
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()
    with tempfile.TemporaryDirectory(prefix="slamreplay-false-alarms-") as tmp:
        root = Path(tmp)
        (root / "noisy.py").write_text(NOISY)
        (root / "noisy.toml").write_text(DECLARATION)
        os.environ[DECLARATIONS_ENV] = str(root / "noisy.toml")
        os.environ["SLAMREPLAY_CACHE"] = str(root / "cache")
        refresh()
        recordings = []
        for seed in range(1, args.seeds + 1):
            path = root / f"rec{seed}.mcap"
            simulate_landmarks(path, LandmarkSimConfig(duration_s=args.duration_s), seed=seed)
            recordings.append(path)

        def side(label: str) -> Side:
            rows = []
            for k, rec in enumerate(recordings):
                run = run_recording(rec, "noisy", root / "runs" / label / str(k))
                row = run_row(run.run_dir)
                row.update(recording="sim-landmarks", recording_seed=k + 1)
                rows.append(row)
            return Side(label, rows, "results", [label])

        tic = time.perf_counter()
        sides = [side(f"s{i}") for i in range(args.compares + 1)]
        alarms = plain = 0
        for a, b in zip(sides, sides[1:]):
            alarms += bool(compare(a, b).regressions)
            for r in (*a.rows, *b.rows):
                r.pop("deterministic", None)
            plain += bool(compare(a, b).regressions)
            for r in (*a.rows, *b.rows):
                r["deterministic"] = False
        known = sum(r.get("deterministic") is False for s in sides for r in s.rows)
        wall = time.perf_counter() - tic
    print(f"{args.compares} comparisons of an unchanged program that is not deterministic, {args.seeds} seeds each "
          f"({wall:.0f} s; {known} of {sum(len(s.rows) for s in sides)} runs knew it was not deterministic):")
    print(f"  regressions reported: {alarms} (judged by seed spread, Holm over its metrics); {plain} if compare "
          f"did not know")
    if args.json:
        write_json(args.json, {"compares": args.compares, "seeds": args.seeds, "false_alarms": alarms,
                               "false_alarms_without_determinism": plain, "wall_s": wall})
    return 0


if __name__ == "__main__":
    sys.exit(main())
