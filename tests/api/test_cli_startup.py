"""The command line starts fast: --help, --version and argument errors import nothing heavy.

Measured in a fresh interpreter, never as wall time alone (a loaded CI machine would flake): the
modules a command leaves in ``sys.modules``, and its import time as a ratio to a bare ``python -c
pass`` run the same way.
"""

from __future__ import annotations

import json
import subprocess
import sys
import time

import pytest

HEAVY = ("numpy", "scipy", "cv2", "rerun", "mcap", "fastapi", "pydantic", "google.protobuf", "rich", "uvicorn")

# Runs main(argv) in a fresh interpreter and prints which heavy modules it imported and how it exited.
PROBE = """
import contextlib, io, json, sys
from slamreplay.api.cli.command import main
argv = json.loads(sys.argv[1])
out, err = io.StringIO(), io.StringIO()
with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
    try:
        code = main(argv)
    except SystemExit as exc:
        code = exc.code
heavy = sorted({m.split(".")[0] if not m.startswith("google.") else "google.protobuf" for m in sys.modules
                if any(m == h or m.startswith(h + ".") for h in json.loads(sys.argv[2]))})
print(json.dumps({"code": code, "heavy": heavy, "out": out.getvalue(), "err": err.getvalue()}))
"""


def probe(argv: list[str]) -> dict[str, object]:
    done = subprocess.run([sys.executable, "-c", PROBE, json.dumps(argv), json.dumps(HEAVY)], capture_output=True,
                          text=True, timeout=120, check=True)
    result: dict[str, object] = json.loads(done.stdout)
    return result


@pytest.mark.parametrize("argv", [
    ["--help"], ["--version"], ["run", "--help"], ["suite", "run", "--help"], ["compare", "--help"],
    ["graph", "optimize", "--help"], ["serve", "--help"], ["pipelines", "--help"], ["record", "--help"],
    ["record", "sim-landmarks", "--help"],
    ["record", "sim-corridor", "--help"], ["record", "ros2", "--help"], ["rn"], ["run", "x.mcap"],
    ["run", "x.mcap", "--pipeline", "dslam", "--out", "r", "--sed", "1"],
    ["run", "missing.mcap", "--pipeline", "dslam", "--out", "r"],
])
def test_help_and_argument_errors_import_nothing_heavy(argv: list[str]) -> None:
    """Building the parser, --help, --version and a bad argument (or a missing input file) leave numpy, scipy,
    cv2, rerun, mcap, fastapi, pydantic, protobuf and rich unimported."""
    result = probe(argv)
    assert result["code"] in (0, 2), result
    assert result["heavy"] == [], f"slamreplay {' '.join(argv)} imported {result['heavy']}"


def test_argument_errors_are_one_line_with_a_suggestion() -> None:
    """A mistyped command or option: exit 2, one line naming the closest one and where the help is."""
    result = probe(["rn"])
    assert result["code"] == 2
    assert result["err"].strip() == (  # type: ignore[union-attr]
        "slamreplay: error: argument COMMAND: invalid choice: 'rn' (did you mean 'run'?) (choose from record, "
        "inspect, recover, pipelines, run, navigate, diff, trajectory, snapshot, demo, serve, graph, suite, compare, "
        "bisect, history, cache, evaluate, export, users, push) (see `slamreplay --help`)")
    result = probe(["run", "x.mcap", "--pipeline", "dslam", "--out", "r", "--sed", "1"])
    assert result["code"] == 2
    assert result["err"] == ("slamreplay run: error: unrecognized arguments: --sed 1 (did you mean --seed?) "
                             "(see `slamreplay run --help`)\n")
    result = probe(["--version"])
    assert result["code"] == 0 and str(result["out"]).startswith("slamreplay ")


def _best_of(argv: list[str], runs: int = 5) -> float:
    best = float("inf")
    for _ in range(runs):
        tic = time.perf_counter()
        subprocess.run([sys.executable, *argv], capture_output=True, timeout=120, check=False)
        best = min(best, time.perf_counter() - tic)
    return best


def test_help_costs_a_few_bare_interpreter_starts() -> None:
    """`slamreplay --help` takes at most 12 times a bare `python -c pass` (best of 5 each, so that a busy machine
    slows both alike): about 0.1 s against 0.02 s here; importing the stack first took 1-2.6 s (60-100x)."""
    bare = _best_of(["-c", "pass"])
    helped = _best_of(["-c", "import sys; from slamreplay.api.cli.command import main; sys.exit(main(['--help']))"])
    assert helped < 12 * bare, f"--help took {helped:.3f} s, a bare interpreter {bare:.3f} s"


def test_graph_choices_match_the_solver() -> None:
    """The graph command's choices are spelled in the CLI (no scipy import): they must be graph_io's."""
    from slamreplay.api.cli import graph_cli
    from slamreplay.replay.tools import graph_io

    assert (graph_cli.SOLVERS, graph_cli.INITS, graph_cli.ROBUST) == (graph_io.SOLVERS, graph_io.INITS,
                                                                       graph_io.ROBUST)


def test_a_closed_pipe_ends_a_command_quietly() -> None:
    """`slamreplay pipelines | head -1` once said "internal error: BrokenPipeError ... please report it": a reader
    that left ends the command with no word on stderr and git's exit status (128 + SIGPIPE)."""
    import os

    read_end, write_end = os.pipe()
    os.close(read_end)  # the reader has gone before the first line
    try:
        done = subprocess.run([sys.executable, "-m", "slamreplay.api.cli", "pipelines"], stdout=write_end,
                              stderr=subprocess.PIPE, timeout=120)
    finally:
        os.close(write_end)
    assert (done.returncode, done.stderr.decode()) == (141, ""), done.stderr.decode()
