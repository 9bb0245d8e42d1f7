"""``slamreplay cache``: what the revision cache holds (revisions' worktrees, shared environments), and pruning it.

The work is in ``slamreplay.replay.runs.rev_cache``; this module parses and prints. Imports are inside the
handlers: the command line builds its parser from here.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any


def _cache(args: argparse.Namespace) -> Path:
    from slamreplay.replay.tools.cache import cache_dir

    given = getattr(args, "cache_path", None)
    return Path(given).expanduser() if given else cache_dir()


def cmd_cache_list(args: argparse.Namespace) -> int:
    """List the revisions and environments, least recently used (pruned first) first."""
    from slamreplay.replay.runs.rev_cache import entries, format_size, format_time
    from slamreplay.replay.tools.cache import LIMIT_ENV, cache_limit

    cache = _cache(args)
    limit = cache_limit()
    found = entries(cache)
    total = sum(e.size for e in found)
    if getattr(args, "json", False):
        print(json.dumps({"cache": str(cache), "limit_bytes": limit, "total_bytes": total, "entries": [
            {"kind": e.kind, "name": e.name, "path": str(e.path), "size_bytes": e.size, "last_use": e.last_use,
             "in_use": e.in_use, "state": e.state or "free", "about": e.about} for e in found]}, indent=2))
        return 0
    revs = sum(1 for e in found if e.kind == "revision")
    print(f"revision cache {cache}: {revs} revision(s), {len(found) - revs} environment(s), {format_size(total)} "
          f"of its {format_size(limit)} limit (${LIMIT_ENV})")
    if not found:
        return 0
    width = max(len(e.name if e.kind == "environment" else e.name[:10]) for e in found)
    print(f"  {'KIND':<11}  {'NAME':<{width}}  {'SIZE':>10}  {'LAST USE':<16}  {'STATE':<8}  WHAT "
          f"(least recently used first: pruned first)")
    for e in found:
        name = e.name if e.kind == "environment" else e.name[:10]
        print(f"  {e.kind:<11}  {name:<{width}}  {format_size(e.size):>10}  {format_time(e.last_use):<16}  "
              f"{e.state or '-':<8}  {_short(e.about)}")
    return 0


def _short(text: str, n: int = 72) -> str:
    return text if len(text) <= n else text[: n - 3] + "..."


def cmd_cache_prune(args: argparse.Namespace) -> int:
    """Prune least recently used entries down to the limit; never one in use."""
    from slamreplay.replay.runs.rev_cache import format_size, prune
    from slamreplay.replay.tools.cache import cache_limit, parse_size

    limit = 0 if args.all else parse_size(args.limit, "--limit") if args.limit is not None else cache_limit()
    cache = _cache(args)
    done = prune(cache, limit, note=None if args.quiet else lambda text: print(f"cache: {text}"))
    if not args.quiet:
        kept = f"; kept {len(done.kept_in_use)} in use" if done.kept_in_use else ""
        over = " (still over: the rest is in use)" if done.after > limit else ""
        print(f"cache: {format_size(done.before)} -> {format_size(done.after)}, limit {format_size(limit)}{over}; "
              f"removed {len(done.removed)}{kept}")
    return 0


def add_cache_parsers(sub: Any, quiet: argparse.ArgumentParser) -> None:
    """The ``cache`` subcommand and its ``list`` and ``prune``."""
    where = argparse.ArgumentParser(add_help=False)
    where.add_argument("--cache", dest="cache_path", metavar="DIR", default=argparse.SUPPRESS,
                       help="the cache (default: $SLAMREPLAY_CACHE, else ~/.cache/slamreplay; the service's is "
                            "DATA_DIR/cache)")
    listing = argparse.ArgumentParser(add_help=False)
    listing.add_argument("--json", action="store_true", default=argparse.SUPPRESS, help="machine-readable output")
    cp = sub.add_parser("cache", parents=[where, listing],
                        help="the revision cache: worktrees and shared environments, their size; prune it",
                        description="List the revision cache (compare rev:, bisect, history and the service's "
                                    "revision jobs build there): each revision's worktree and each environment of "
                                    "dependencies shared by the commits that declare the same, with size, last use "
                                    "and whether a running job uses it. Its limit is $SLAMREPLAY_CACHE_LIMIT_GB "
                                    "(default 10), kept after each revision built, least recently used first, never "
                                    "what is in use. Exit 0, or 2 on bad input.")
    cp.set_defaults(func=cmd_cache_list)
    csub = cp.add_subparsers(dest="cache_command", metavar="{list,prune}")
    ls = csub.add_parser("list", parents=[where, listing], help="what the cache holds (the default)")
    ls.set_defaults(func=cmd_cache_list)
    pr = csub.add_parser("prune", parents=[where, quiet], help="remove least recently used entries down to a limit",
                         description="Remove revisions and environments, least recently used first, until the cache "
                                     "holds at most the limit; one in use (a running compare, history or job) or "
                                     "being built is kept. Worktrees are removed with git worktree remove.")
    which = pr.add_mutually_exclusive_group()
    which.add_argument("--limit", metavar="SIZE", help="e.g. 5G, 500M, or a number of GB (default: "
                                                       "$SLAMREPLAY_CACHE_LIMIT_GB, else 10)")
    which.add_argument("--all", action="store_true", help="remove everything not in use (a limit of 0)")
    pr.set_defaults(func=cmd_cache_prune)
