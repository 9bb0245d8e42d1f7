"""The command line's argument parser class: one-line errors with "did you mean", and a lazy ``--version``.

argparse prints its usage before an error and leaves a mistyped option or command unexplained;
``slamreplay`` errors are one line saying what to do, exit 2, and a near miss is named as git
names it (``unrecognized arguments: --sed (did you mean --seed?)``). Nothing here imports more
than the standard library: the parser is built before every command, ``--help`` included.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from typing import Any, NoReturn

from slamreplay.recorder.options import did_you_mean

EXIT_OK, EXIT_CHECK_FAILED, EXIT_BAD_INPUT = 0, 1, 2


class CliError(Exception):
    """Bad command-line input: one line on stderr, exit 2."""


def eprint(*args: Any) -> None:
    print(*args, file=sys.stderr)


class SuggestingParser(argparse.ArgumentParser):
    """An ``ArgumentParser`` whose errors are one line, with the closest command, choice or option."""

    def error(self, message: str) -> NoReturn:
        """Print ``PROG: error: MESSAGE (see `PROG --help`)`` on stderr and exit 2."""
        self.exit(2, f"{self.prog}: error: {message} (see `{self.prog} --help`)\n")

    def _check_value(self, action: argparse.Action, value: Any) -> None:
        # argparse's own check, with the closest choice named (a mistyped command or --executor value)
        if action.choices is not None and value not in action.choices:
            known = [str(c) for c in action.choices]
            raise argparse.ArgumentError(action, f"invalid choice: {value!r}{did_you_mean(str(value), known, True)}"
                                                 f" (choose from {', '.join(known)})")

    def parse_args_suggesting(self, argv: Sequence[str] | None) -> argparse.Namespace:
        """``parse_args``, but an unrecognized option is reported by the (sub)command it was given to, with the
        closest of that command's options."""
        args, extras = self.parse_known_args(argv)
        if extras:
            chosen = chosen_parser(self, args)
            hints = "".join(did_you_mean(x.partition("=")[0], chosen.option_strings()) for x in extras
                            if x.startswith("-"))
            chosen.error(f"unrecognized arguments: {' '.join(extras)}{hints}")
        return args

    def option_strings(self) -> list[str]:
        """Every option string of this parser (``--seed``, ``-q`` ...)."""
        return [s for a in self._actions for s in a.option_strings]


def chosen_parser(parser: argparse.ArgumentParser, args: argparse.Namespace) -> SuggestingParser:
    """The innermost sub-command parser that ``args`` went through (``slamreplay suite run`` ...)."""
    current = parser
    while True:
        subs = [a for a in current._actions if isinstance(a, argparse._SubParsersAction)]
        name = getattr(args, subs[0].dest, None) if subs and subs[0].dest else None
        if name is None or name not in subs[0].choices:
            break
        current = subs[0].choices[name]
    assert isinstance(current, SuggestingParser)
    return current


class VersionAction(argparse.Action):
    """``--version``: slamreplay's version, read from the installed metadata only when asked."""

    def __init__(self, option_strings: list[str], dest: str = argparse.SUPPRESS, **kwargs: Any) -> None:
        super().__init__(option_strings, dest, nargs=0, default=argparse.SUPPRESS,
                         help="print slamreplay's version and exit", **kwargs)

    def __call__(self, parser: argparse.ArgumentParser, namespace: argparse.Namespace, values: Any,
                 option_string: str | None = None) -> None:
        from slamreplay.recorder.version import version

        print(f"slamreplay {version()}", file=sys.stdout)
        parser.exit(0)


def command_of(argv: Sequence[str]) -> str | None:
    """The sub-command named in ``argv`` (its first word that is not an option), or None."""
    return next((a for a in argv if not a.startswith("-")), None)

