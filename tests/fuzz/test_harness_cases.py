"""Regression cases of the suite, upload, ROS 2 bag and dataset importer harnesses: each crasher they found, replayed.

``cases/harness_cases.json`` lists each stored input (under ``cases/<harness>/``, < 100 KB), what
slamreplay did before the fix, and a pattern the error (or ``ok``) of the parser now matches. Each input
also goes through its harness's ``test_one_input``, which asserts the whole contract: a result or
slamreplay's own error in one line (a 4xx answer for the service), never another exception.
"""

from __future__ import annotations

import importlib
import json
import re
import sys
from pathlib import Path
from types import ModuleType
from typing import Any

import pytest

CASES_DIR = Path(__file__).parent / "cases"
CASES: list[dict[str, Any]] = json.loads((CASES_DIR / "harness_cases.json").read_text())
HARNESSES = ("suite", "upload", "ros2bag", "datasets")


def _harness(name: str) -> ModuleType:
    """The harness module, imported without atheris: no instrumentation in the test process, no fuzz extra."""
    module = f"tests.fuzz.harness_{name}"
    if module not in sys.modules:
        saved = sys.modules.get("atheris")
        sys.modules["atheris"] = None  # type: ignore[assignment]  # makes `import atheris` fail
        try:
            importlib.import_module(module)
        finally:
            if saved is None:
                del sys.modules["atheris"]
            else:
                sys.modules["atheris"] = saved
    return sys.modules[module]


def _outcome(harness: ModuleType, name: str, data: bytes) -> str:
    """``ok`` or the first error message the parser under ``harness`` gives for ``data``."""
    try:
        if name == "suite":
            harness._TOML.write_bytes(data)
            if data.lstrip().startswith(b"{"):
                harness.parse_suite(data.decode(), harness._DIR / "suite.json", fmt="json")
            else:
                harness.load_suite(harness._TOML)
        elif name == "upload":
            harness._LOOP.run_until_complete(harness._upload(*harness.split(data)))
        elif name == "datasets":
            harness.record(data)
        else:
            harness.build_bag(data)
            harness.plan_bag(harness._BAG, ground_truth_frame="map")
            harness._OUT.unlink(missing_ok=True)
            harness.import_ros2_bag(harness._BAG, harness._OUT)
    except Exception as err:  # noqa: BLE001  # the message is what the case checks; its type the harness
        return str(err)
    return "ok"


def test_cases_are_small_and_listed() -> None:
    """Every stored input is listed, exists and stays under 100 KB."""
    files = {str(p.relative_to(CASES_DIR)) for h in HARNESSES for p in (CASES_DIR / h).glob("*")}
    assert files == {c["file"] for c in CASES}
    assert all((CASES_DIR / f).stat().st_size < 100_000 for f in files)


@pytest.mark.parametrize("case", CASES, ids=[c["file"] for c in CASES])
def test_case(case: dict[str, Any]) -> None:
    """The parser gives the expected outcome, and the harness's whole contract holds for the input."""
    name = case["file"].split("/")[0]
    harness = _harness(name)
    data = (CASES_DIR / case["file"]).read_bytes()
    outcome = _outcome(harness, name, data)
    assert "\n" not in outcome and re.search(case["expect"], outcome), outcome
    harness.test_one_input(data)
