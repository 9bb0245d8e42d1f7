"""The outsider's campaign of issue 26: five byte-level mutation kinds of a 30 s ``sim-landmarks`` recording.

Kinds: ``splice`` (copy a random span of the file to another place), ``zero_run``, ``truncate``,
``overwrite8`` (8 random bytes at a random offset) and ``huge_length`` (a huge little-endian length,
such as 0xFFFFFFFFFFFFFFF0 or 2**40, at a random offset). Each mutant goes through
``slamreplay inspect``, ``run --pipeline odometry`` and ``recover`` (tests/fuzz/runner.py: in-process
in one worker process, a time limit per command, a bounded address space). Internal error = exit
other than 0/1/2 or an exception out of the CLI; hang = over the time limit.

    nice -n 10 .venv/bin/python -m tests.fuzz.outsider --per-kind 100 --json /tmp/outsider.json

Exit 1 when any mutant gave an internal error, a hang or a wrong recover; ``--keep DIR`` keeps those
mutants, and (seed, index, kind) rebuilds one: ``tests.fuzz.mutate.mutant(base, seed, index, kind)``.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

from tests.fuzz.mutate import OUTSIDER_OPS, make_base
from tests.fuzz.runner import run_campaign

BASE = "landmarks30"


def main(argv: list[str] | None = None) -> int:
    """Run the campaign; print the outcome table per kind and command and every finding."""
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--per-kind", type=int, default=100, help="mutants of each of the five kinds")
    p.add_argument("--seed", type=int, default=26, help="campaign seed")
    p.add_argument("--ops", default=",".join(OUTSIDER_OPS), help="comma-separated subset of the kinds")
    p.add_argument("--workers", type=int, default=1, help="worker processes (the machine is shared)")
    p.add_argument("--time-limit-s", type=int, default=60, help="per command; over it is a hang")
    p.add_argument("--json", type=Path, help="write every mutant's outcomes here")
    p.add_argument("--keep", type=Path, help="copy the mutant files of findings here")
    args = p.parse_args(argv)
    ops = [o for o in args.ops.split(",") if o]
    with tempfile.TemporaryDirectory(prefix="slamreplay-outsider-") as tmp:
        work = Path(tmp)
        base = make_base(BASE, work / "bases")
        tasks = [(BASE, args.seed, i, op) for i in range(args.per_kind) for op in ops]
        if args.keep:
            args.keep.mkdir(parents=True, exist_ok=True)
        t0 = time.perf_counter()

        def progress(done: int, total: int) -> None:
            if done % 50 == 0 or done == total:
                print(f"  {done}/{total} mutants, {time.perf_counter() - t0:.0f} s", file=sys.stderr, flush=True)

        campaign = run_campaign({BASE: base}, tasks, work, workers=args.workers, time_limit_s=args.time_limit_s,
                                keep=args.keep, progress=progress)
        wall = time.perf_counter() - t0
        size = base.stat().st_size
    print(f"{len(campaign.results)} mutants (seed {args.seed}) of a {size:,}-byte 30 s sim-landmarks recording "
          f"through inspect, run and recover in {wall:.0f} s ({args.time_limit_s} s per command)\n")
    print(campaign.table(by="op"))
    findings = campaign.findings()
    if findings:
        print(campaign.findings_text(lambda r: str(r["recipe"].get("op"))))
    if args.json:
        args.json.write_text(json.dumps({"seed": args.seed, "mutants": len(campaign.results), "wall_s": round(wall, 1),
                                         "base_size": size, "results": campaign.results}, indent=1))
    return 1 if findings else 0


if __name__ == "__main__":
    sys.exit(main())
