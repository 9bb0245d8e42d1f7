"""False alarms and detections of the history's change detector on synthetic histories of known answer.

Each history: n commits of a metric near 1.0 with a fixed offset per seed (5 sigma: the seed's world) and
fresh noise per commit and seed (sigma = 0.02: every commit changes the random stream, the hardest case;
real replays are deterministic, and commits that touch nothing give identical values). Flat histories
count false alarms (any change flagged); histories with one step of 2, 3 or 5 sigma half-way count
detections at exactly that commit. Metric "lower is better", tolerance as measured metrics have it.

    python benchmarks/history_changepoints.py [--trials 500] [--seed 0]
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from slamreplay.replay.runs.changepoints import find_steps

SIGMA = 0.02


def history(rng: np.random.Generator, n: int, seeds: int, step: float = 0.0) -> list[dict[int, float]]:
    offset = rng.normal(0, 5 * SIGMA, seeds)
    return [{s: float(1.0 + (step if k >= n // 2 else 0.0) + offset[s] + rng.normal(0, SIGMA)) for s in range(seeds)}
            for k in range(n)]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--trials", type=int, default=500)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    rng = np.random.default_rng(args.seed)
    print(f"{args.trials} histories per row; steps in units of the per-seed noise sigma")
    print("| commits | seeds | false alarms (flat) | found: 2 sigma | 3 sigma | 5 sigma | ms per series |")
    print("| ---: | ---: | ---: | ---: | ---: | ---: | ---: |")
    for n in (10, 30, 100):
        for seeds in (1, 3, 5):
            tic = time.perf_counter()
            fa = sum(bool(find_steps(history(rng, n, seeds), "lower", 1e-6, 1e-3)) for _ in range(args.trials))
            found = []
            for k in (2, 3, 5):
                hits = sum(any(s.index == n // 2 for s in find_steps(history(rng, n, seeds, k * SIGMA), "lower",
                                                                      1e-6, 1e-3)) for _ in range(args.trials))
                found.append(hits / args.trials)
            ms = 1000 * (time.perf_counter() - tic) / (4 * args.trials)
            print(f"| {n} | {seeds} | {fa / args.trials:.1%} | " + " | ".join(f"{f:.0%}" for f in found)
                  + f" | {ms:.1f} |")


if __name__ == "__main__":
    main()
