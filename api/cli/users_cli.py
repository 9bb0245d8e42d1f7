"""``slamreplay users``: the people of a server's data directory (docs/service.md, "A server a team shares").

``users add NAME --role viewer|runner|admin`` prints the new person's token once, alone on stdout (so that
``TOKEN=$(slamreplay users add ...)`` works), and the store keeps only its slow hash. ``users token NAME``
replaces a token (the old one stops working, its page sessions end), ``users disable NAME`` shuts a person
out at once, ``users enable`` and ``users role`` undo and change. The commands write the same SQLite database
the server reads at each request (``--data-dir``, as ``serve`` takes it), so they work while it serves.
Each change goes into the audit trail, by the account that ran the command, from ``command line``.
"""

from __future__ import annotations

import argparse
import getpass
import sys
import time
from typing import Any

from slamreplay.api.cli.cli_parser import EXIT_OK


def _store(args: argparse.Namespace, create: bool = False) -> Any:
    """The data directory's store (``--data-dir``, else SLAMREPLAY_DATA_DIR, else here); CliError-like ValueError
    when it holds no server and ``create`` is not set (a mistyped folder is not made into a server)."""
    from slamreplay.api.service.settings import Settings
    from slamreplay.api.service.store import Store
    from slamreplay.replay.errors import ReplayError

    settings = Settings.from_env(data_dir=args.data_dir)
    if not settings.db_path.is_file():
        if not create:
            raise ReplayError(f"no server data in {settings.data_dir.resolve()} (no runs/jobs.sqlite): give the "
                              "folder `slamreplay serve --data-dir` uses, with --data-dir or SLAMREPLAY_DATA_DIR")
        settings.make_dirs()
    return Store(settings.db_path)


def _actor() -> str:
    try:
        return f"{getpass.getuser()} (command line)"
    except (KeyError, OSError):
        return "command line"


def _audit(store: Any, action: str, name: str, detail: str | None = None) -> None:
    store.add_audit(_actor(), "command line", action, name, detail)


def _run(args: argparse.Namespace) -> int:
    from slamreplay.api.service.people import PeopleError
    from slamreplay.replay.errors import ReplayError

    try:
        return int(args.users_func(args))
    except PeopleError as err:
        raise ReplayError(str(err)) from None


def cmd_add(args: argparse.Namespace) -> int:
    store = _store(args, create=True)
    token = store.add_user(args.name, args.role)
    _audit(store, "user-add", args.name, args.role)
    print(token)
    print(f"added {args.name} ({args.role}); the token above is shown once, the server keeps only its hash: give "
          f"it to {args.name} (for the API: Authorization: Bearer TOKEN; for the page: sign in at /login)",
          file=sys.stderr)
    return EXIT_OK


def cmd_token(args: argparse.Namespace) -> int:
    store = _store(args)
    token = store.new_user_token(args.name)
    _audit(store, "user-token", args.name, "a new token; the old one and its page sessions ended")
    print(token)
    print(f"a new token for {args.name}, shown once; the old one no longer works and their page sessions ended",
          file=sys.stderr)
    return EXIT_OK


def cmd_disable(args: argparse.Namespace) -> int:
    store = _store(args)
    store.set_disabled(args.name, True)
    _audit(store, "user-disable", args.name)
    print(f"disabled {args.name}: their token and page sessions no longer work (`users enable {args.name}` "
          "undoes it)", file=sys.stderr)
    return EXIT_OK


def cmd_enable(args: argparse.Namespace) -> int:
    store = _store(args)
    store.set_disabled(args.name, False)
    _audit(store, "user-enable", args.name)
    print(f"enabled {args.name}: their token works again", file=sys.stderr)
    return EXIT_OK


def cmd_role(args: argparse.Namespace) -> int:
    store = _store(args)
    store.set_role(args.name, args.role)
    _audit(store, "user-role", args.name, args.role)
    print(f"{args.name} is now a{'n' if args.role == 'admin' else ''} {args.role}", file=sys.stderr)
    return EXIT_OK


def cmd_list(args: argparse.Namespace) -> int:
    store = _store(args)
    users = store.users()
    if not users:
        print("no people: the server is single-user (no token on 127.0.0.1, or SLAMREPLAY_TOKEN); "
              "`slamreplay users add NAME --role admin` makes it a team's", file=sys.stderr)
        return EXIT_OK
    print(f"{'name':<24} {'role':<7} {'since (UTC)':<17} state")
    for u in users:
        since = time.strftime("%Y-%m-%d %H:%M", time.gmtime(u.created))
        state = "active" if u.active else "disabled " + time.strftime("%Y-%m-%d %H:%M", time.gmtime(u.disabled or 0))
        print(f"{u.name:<24} {u.role:<7} {since:<17} {state}")
    return EXIT_OK


def add_users_parser(sub: Any) -> None:
    """``slamreplay users {add,list,disable,enable,role,token}``."""
    from slamreplay.api.service.people import ROLES

    users = sub.add_parser("users", help="the people of a shared server: add, list, disable, new tokens, roles",
                           description="Manage who may use a server, in its data directory (the server need not be "
                                       "stopped). Roles: viewer reads; runner also uploads, submits, cancels and "
                                       "labels; admin also deletes runs and recordings and reads the audit trail. A "
                                       "server with no people stays single-user (no token on 127.0.0.1, or "
                                       "SLAMREPLAY_TOKEN).")
    users.set_defaults(func=_run)
    usub = users.add_subparsers(dest="users_command", required=True, metavar="ACTION")
    data = argparse.ArgumentParser(add_help=False)
    data.add_argument("--data-dir", default=None,
                      help="the server's data directory, as `serve --data-dir` (default: SLAMREPLAY_DATA_DIR, else "
                           "the current directory)")
    name = argparse.ArgumentParser(add_help=False)
    name.add_argument("name", help="the person's user name (letters, digits, . _ -)")

    add = usub.add_parser("add", parents=[name, data], help="add a person; prints their token once")
    add.add_argument("--role", required=True, choices=ROLES, help="viewer, runner or admin")
    add.set_defaults(users_func=cmd_add)
    ls = usub.add_parser("list", parents=[data], help="everyone, with role and state (tokens are never shown)")
    ls.set_defaults(users_func=cmd_list)
    dis = usub.add_parser("disable", parents=[name, data], help="shut a person out at once (token and sessions)")
    dis.set_defaults(users_func=cmd_disable)
    en = usub.add_parser("enable", parents=[name, data], help="let a disabled person in again")
    en.set_defaults(users_func=cmd_enable)
    role = usub.add_parser("role", parents=[name, data], help="give a person another role")
    role.add_argument("role", choices=ROLES, help="viewer, runner or admin")
    role.set_defaults(users_func=cmd_role)
    tok = usub.add_parser("token", parents=[name, data], help="a new token for a person (the old one stops working)")
    tok.set_defaults(users_func=cmd_token)

