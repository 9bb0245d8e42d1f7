"""Coverage-guided fuzzing (atheris, libFuzzer) of the suite loader: TOML and JSON suite files.

Contract: for any bytes, ``load_suite`` (a TOML file, as ``slamreplay suite run`` reads it) and
``parse_suite`` (JSON, and the service's form that names recordings by id) give a ``Suite`` or a
``ReplayError`` whose message is one line. Any other exception, a timeout or a memory blow-up is a
finding (libFuzzer writes the input to ``crash-*``/``timeout-*``/``oom-*``).

    nice -n 10 .venv/bin/python tests/fuzz/harness_suite.py -max_total_time=600 -timeout=10 \\
        -rss_limit_mb=2048 -max_len=4096 -dict=tests/fuzz/suite.dict -artifact_prefix=/tmp/fuzz-suite/ \\
        /tmp/fuzz-suite/corpus tests/fuzz/corpus/suite

The first directory is the working corpus libFuzzer grows, the second the committed seeds (the example
suites and JSON equivalents). A fixed finding is kept under tests/fuzz/cases/suite/ and replayed by
tests/fuzz/test_harness_cases.py.
"""

from __future__ import annotations

import contextlib
import os
import sys
import tempfile
from pathlib import Path

try:
    import atheris
except ImportError:  # replaying stored cases (tests/fuzz/test_harness_cases.py) needs no fuzzer
    atheris = None

# our code only: tomllib and json are C or stdlib, pipelines' numpy would swamp the map
with atheris.instrument_imports(include=["slamreplay"]) if atheris else contextlib.nullcontext():
    from slamreplay.replay.errors import ReplayError
    from slamreplay.replay.runs.suite import Suite, load_suite, parse_suite

# tmpfs when there is one: every execution writes the suite file
_DIR = Path(tempfile.mkdtemp(prefix="fuzz-suite-", dir="/dev/shm" if os.path.isdir("/dev/shm") else None))
_TOML = _DIR / "suite.toml"
(_DIR / "run.mcap").write_bytes(b"")  # so that a seed's relative `path` exists and the check passes


def _one_line(err: Exception) -> None:
    """A finding when one of our errors is not the promised single line."""
    text = str(err)
    if not text or "\n" in text:
        raise AssertionError(f"{type(err).__name__} message is not one line: {text[:300]!r}")


def _ids(rid: str) -> Path:
    """The service's id lookup: 64 hex digits name a stored recording, anything else is refused."""
    if len(rid) != 64 or not all(c in "0123456789abcdef" for c in rid):
        raise ReplayError(f"no recording with id {rid[:80]!r}")
    return _DIR / "run.mcap"


def test_one_input(data: bytes) -> None:
    """Read ``data`` as a TOML suite file, as a JSON suite and as the service's JSON suite; only a Suite or a
    one-line ReplayError may come out."""
    _TOML.write_bytes(data)
    try:
        suite = load_suite(_TOML)
        assert isinstance(suite, Suite) and suite.cells()
    except ReplayError as err:
        _one_line(err)
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError:
        return  # the service and the CLI read text: load_suite above covered undecodable bytes
    for ids in (None, _ids):
        try:
            suite = parse_suite(text, _DIR / "suite.json", ids=ids, fmt="json")
            assert isinstance(suite, Suite) and suite.cells()
        except ReplayError as err:
            _one_line(err)


def main() -> None:
    """libFuzzer's command line: corpus directories and -flags (see the module docstring)."""
    atheris.Setup(sys.argv, test_one_input)
    atheris.Fuzz()


if __name__ == "__main__":
    main()
