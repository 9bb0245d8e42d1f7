"""The short fuzz pass: a fixed-seed campaign of damaged recordings of every kind, zero findings allowed.

Each mutant goes through `slamreplay inspect`, `run` and `recover` in a worker process with a
time limit per command and a bounded address space (tests/fuzz/runner.py). Any internal error
(exit 3 or an exception out of the CLI), hang, or `recover` that exits 0 without a healthy
result fails the test, listing the mutants: rebuild one with
``tests.fuzz.mutate.mutant(base, seed, index)``, then keep it under tests/fuzz/cases/.
The long pass is ``benchmarks/fuzz_recordings.py --mutants 5000``.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from tests.fuzz.mutate import KINDS, OPS, make_base
from tests.fuzz.runner import COMMANDS, run_campaign

SEED = 18
MUTANTS_PER_KIND = 60  # 300 mutants, 900 commands: about 30 s on two workers


@pytest.mark.slow
def test_short_fuzz_pass(tmp_path: Path) -> None:
    """300 fixed-seed mutants (60 per kind): no internal error, no hang, no untruthful recover."""
    bases = {k: make_base(k, tmp_path / "bases") for k in KINDS}
    assert all(p.stat().st_size < 50_000 for p in bases.values())
    tasks = [(k, SEED, i) for i in range(MUTANTS_PER_KIND) for k in KINDS]
    campaign = run_campaign(bases, tasks, tmp_path / "work", workers=2, time_limit_s=20)
    assert len(campaign.results) == len(tasks)
    findings = [{"kind": r["kind"], "seed": r["seed"], "index": r["index"], "recipe": r["recipe"],
                 **{c: e for c, e in r["results"].items() if e["outcome"] not in ("ok", "clean")}}
                for r in campaign.findings()]
    assert not findings, "\n" + campaign.table() + "\n" + json.dumps(findings, indent=1, default=str)[:20000]
    counts = campaign.counts()
    for kind in KINDS:
        for command in COMMANDS:
            c = counts[(kind, command)]
            assert sum(c.values()) == MUTANTS_PER_KIND
            assert c["clean"] > 0, (kind, command)  # the damage is real: every command refuses some mutants
    ops = {r["recipe"]["op"] for r in campaign.results}
    assert ops == set(OPS)  # every operator was drawn
