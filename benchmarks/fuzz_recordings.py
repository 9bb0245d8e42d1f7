"""Fuzz slamreplay's readers with damaged recordings: the long pass of tests/fuzz.

Mutants of every kind of recording slamreplay produces (see tests/fuzz/mutate.py) go through
`slamreplay inspect`, `run` and `recover`, in-process in worker processes with a time limit
per command and a bounded address space. Prints a table of outcomes per kind and command
(ok, clean error, internal error, hang, wrong recover) and lists every finding.

    .venv/bin/python benchmarks/fuzz_recordings.py --mutants 5000 --json fuzz.json

Exit 1 when any mutant gave an internal error, a hang or a wrong recover; its mutant file is
kept in --keep and its (kind, seed, index) rebuilds it: tests/fuzz/mutate.py `mutant()`.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from tests.fuzz.mutate import KINDS, make_base  # noqa: E402
from tests.fuzz.runner import run_campaign  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--mutants", type=int, default=5000, help="mutants in all, spread evenly over the kinds")
    p.add_argument("--seed", type=int, default=2026, help="campaign seed (mutant i of kind k is fixed by it)")
    p.add_argument("--kinds", default=",".join(KINDS), help=f"comma-separated subset of {','.join(KINDS)}")
    p.add_argument("--workers", type=int, default=2, help="worker processes")
    p.add_argument("--time-limit-s", type=int, default=30, help="per command")
    p.add_argument("--memory-headroom-mib", type=int, default=2048,
                   help="address space a worker may add to its warm size (the mutants are < 100 KB)")
    p.add_argument("--json", type=Path, help="write every mutant's outcomes here")
    p.add_argument("--keep", type=Path, help="copy the mutant files of findings here")
    args = p.parse_args(argv)
    kinds = [k for k in args.kinds.split(",") if k]
    with tempfile.TemporaryDirectory(prefix="slamreplay-fuzz-") as tmp:
        work = Path(tmp)
        bases = {k: make_base(k, work / "bases") for k in kinds}
        per = -(-args.mutants // len(kinds))
        tasks = [(k, args.seed, i) for i in range(per) for k in kinds][: args.mutants]
        if args.keep:
            args.keep.mkdir(parents=True, exist_ok=True)
        t0 = time.perf_counter()

        def progress(done: int, total: int) -> None:
            if done % 250 == 0 or done == total:
                print(f"  {done}/{total} mutants, {time.perf_counter() - t0:.0f} s", file=sys.stderr, flush=True)

        campaign = run_campaign(bases, tasks, work, workers=args.workers, time_limit_s=args.time_limit_s,
                                memory_headroom=args.memory_headroom_mib << 20, keep=args.keep, progress=progress)
        wall = time.perf_counter() - t0
        sizes = {k: v.stat().st_size for k, v in bases.items()}
    print(f"{len(campaign.results)} mutants (seed {args.seed}) of {', '.join(f'{k} ({sizes[k]:,} B)' for k in kinds)}"
          f" through inspect, run and recover in {wall:.0f} s on {args.workers} workers "
          f"({args.time_limit_s} s per command, address space warm size + {args.memory_headroom_mib} MiB)\n")
    print(campaign.table())
    findings = campaign.findings()
    if findings:
        print(campaign.findings_text(lambda r: str(r["kind"])))
    if args.json:
        args.json.write_text(json.dumps({"seed": args.seed, "mutants": len(campaign.results), "wall_s": round(wall, 1),
                                         "base_sizes": sizes, "results": campaign.results}, indent=1))
    return 1 if findings else 0


if __name__ == "__main__":
    sys.exit(main())
