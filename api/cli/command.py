"""The ``slamreplay`` command line.

Exit codes: 0 success; 1 a check failed (``diff`` found a regression, ``inspect`` found a
damaged file); 2 bad input (one line on stderr saying what is wrong and what to do).
"""

from __future__ import annotations

import contextlib
import os
import sys
import traceback
from collections.abc import Sequence

# Only light modules here (a test checks it): the parser is built before every command, --help included, and
# each command imports the heavy stack (numpy, rerun, mcap, fastapi ...) in its function.
from slamreplay.api.cli.cache_cli import add_cache_parsers
from slamreplay.api.cli.cli_parser import EXIT_BAD_INPUT, CliError, SuggestingParser, VersionAction, command_of, eprint
from slamreplay.api.cli.external_cli import add_external_parsers
from slamreplay.api.cli.graph_cli import add_graph_parser
from slamreplay.api.cli.hints import spell_commands
from slamreplay.api.cli.history_cli import add_history_parsers
from slamreplay.api.cli.pipelines_cli import add_pipelines_parser
from slamreplay.api.cli.push_cli import add_push_parser
from slamreplay.api.cli.record_cli import add_record_parsers
from slamreplay.api.cli.run_cli import add_demo_parser, add_run_parsers
from slamreplay.api.cli.serve_cli import add_serve_parser
from slamreplay.api.cli.suite_cli import add_suite_parsers
from slamreplay.api.cli.users_cli import add_users_parser
from slamreplay.recorder.errors import RecorderError
from slamreplay.replay.errors import ReplayError


def build_parser(command: str | None = None) -> SuggestingParser:
    """The ``slamreplay`` parser; with ``command`` (the one on the command line) not ``record``, the sub-commands
    of ``record`` (one per importer plugin, each imported to ask for its options) are left out."""
    p = SuggestingParser(
        prog="slamreplay",
        description="Record sensor streams to MCAP, replay them deterministically through SLAM pipelines, "
                    "and inspect every step in Rerun.",
        epilog="Start with `make demo`, then `slamreplay pipelines`. Each command has its own --help.",
    )
    p.add_argument("--debug", action="store_true", help="show a traceback on errors")
    p.add_argument("--version", action=VersionAction)
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND")
    quiet = SuggestingParser(add_help=False)
    quiet.add_argument("-q", "--quiet", action="store_true", help="no progress (bar or lines) and no summary")

    add_record_parsers(sub, quiet, command)  # record, inspect, recover (api/cli/record_cli.py)
    add_pipelines_parser(sub)

    add_run_parsers(sub, quiet)  # run, navigate, diff, trajectory, snapshot (api/cli/run_cli.py)
    add_demo_parser(sub, quiet)
    add_serve_parser(sub)
    add_graph_parser(sub)
    add_suite_parsers(sub, quiet)
    add_history_parsers(sub, quiet)
    add_cache_parsers(sub, quiet)
    add_external_parsers(sub, quiet)
    add_users_parser(sub)
    add_push_parser(sub)
    return p


def main(argv: Sequence[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    parser = build_parser(command_of(argv))
    args = parser.parse_args_suggesting(argv)
    try:
        return int(args.func(args))
    except (CliError, ReplayError, RecorderError) as err:
        if args.debug:
            traceback.print_exc()
        eprint(f"slamreplay: error: {spell_commands(str(err))}")
        return EXIT_BAD_INPUT
    except KeyboardInterrupt:
        eprint("slamreplay: interrupted")
        return 130
    except BrokenPipeError:  # `slamreplay ... | head`: the reader left; end quietly, as git does (128 + SIGPIPE)
        with contextlib.suppress(OSError):
            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())  # the exit's flush must not fail again
        return 141
    except Exception as err:  # noqa: BLE001 -- never a traceback to a user unless asked
        if args.debug:
            traceback.print_exc()
        eprint(f"slamreplay: internal error: {type(err).__name__}: {err} (rerun with --debug for a traceback, "
                f"and please report it)")
        return 3

