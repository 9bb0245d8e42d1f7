"""Regression cases: every internal error the fuzz harness found, stored as the small mutant that caused it.

``cases/cases.json`` lists each file (< 50 KB), where it came from (base kind, seed, index and
recipe: ``tests.fuzz.mutate.mutant`` rebuilds it), what slamreplay did before the fix, and
what each command must do now: its exit code and a pattern its output matches. An error is
one line on stderr (exit 2); ``inspect`` reports damage as ``problem:`` lines (exit 1).
"""

from __future__ import annotations

import json
import re
import resource
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

from slamreplay.api.cli.command import main

CASES_DIR = Path(__file__).parent / "cases"
CASES: list[dict[str, Any]] = json.loads((CASES_DIR / "cases.json").read_text())


def _run(argv: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, str, str]:
    code = main(argv)
    out, err = capsys.readouterr()
    return code, out, err


def test_cases_are_small_and_listed() -> None:
    """Every stored mutant is listed, exists and stays under 50 KB."""
    files = {p.name for p in CASES_DIR.glob("*.mcap")}
    assert files == {c["file"] for c in CASES}
    assert all((CASES_DIR / f).stat().st_size < 50_000 for f in files)


@pytest.mark.parametrize("case", CASES, ids=[c["file"] for c in CASES])
def test_case(case: dict[str, Any], tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """inspect, run and recover give the expected exit code and a message saying what is damaged and where."""
    path = CASES_DIR / case["file"]
    expect = case["expect"]
    code, out, err = _run(["inspect", str(path)], capsys)
    assert (code, err) == (expect["inspect"]["exit"], ""), err
    assert re.search(expect["inspect"]["match"], out), out

    code, out, err = _run(["run", str(path), "--pipeline", case["pipeline"], "--out", str(tmp_path / "run"), "-q"],
                          capsys)
    assert code == expect["run"]["exit"], err
    if code == 2:
        assert err.startswith("slamreplay: error: ") and err.count("\n") == 1, err  # one line, no traceback
        assert re.search(expect["run"]["match"], err), err
        if expect["run"].get("manifest", True):
            manifest = json.loads((tmp_path / "run" / "manifest.json").read_text())
            assert manifest["status"] == "failed" and not (tmp_path / "run" / "metrics.json").exists()
        else:  # refused before the run starts (a truncated file): no run directory at all
            assert not (tmp_path / "run").exists()

    fixed = tmp_path / "fixed.mcap"
    code, out, err = _run(["recover", str(path), "--out", str(fixed)], capsys)
    assert code == expect["recover"]["exit"], err
    if code == 0:
        assert re.search(expect["recover"]["match"], out, re.S), out
        code, out, _ = _run(["inspect", str(fixed)], capsys)
        assert code == 0 and "health: ok" in out  # what recover writes is whole
    else:
        assert err.count("\n") == 1 and re.search(expect["recover"]["match"], err), err
        assert not fixed.exists() and not fixed.with_name("fixed.mcap.partial").exists()


def _limit_address_space() -> None:
    resource.setrlimit(resource.RLIMIT_AS, (3 << 30, 3 << 30))


def test_length_field_is_not_trusted_for_an_allocation() -> None:
    """Under the issue's 3 GB address-space limit, a 3.75 GB record length gives a clean report, not MemoryError."""
    path = CASES_DIR / "summary-record-length.mcap"
    proc = subprocess.run([sys.executable, "-m", "slamreplay.api.cli",
                           "inspect", str(path)], capture_output=True, text=True, timeout=120,
                          preexec_fn=_limit_address_space, cwd=Path(__file__).resolve().parents[2])
    assert proc.returncode == 1, proc.stderr
    assert "Schema record at byte 8752 claims 4,026,531,840 bytes" in proc.stdout
