"""``slamreplay history``: a suite's metrics over a range of commits, the changes found, a static report.

The work is in ``slamreplay.replay.runs.history`` (running, the store), ``changepoints`` (the
detector) and ``history_report`` (index.html, markdown); this module parses, prints progress and
picks the executor. Imports are inside the handler: the command line builds its parser from here.
"""

from __future__ import annotations

import argparse
import threading
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

from slamreplay.api.cli.progress import progress_bar, say
from slamreplay.replay.errors import ReplayError

if TYPE_CHECKING:
    from slamreplay.replay.runs.revisions import Revision
    from slamreplay.replay.runs.suite_run import CellJob


def ray_runner() -> Any:
    """``run(revision, job)`` as a Ray task: each cell runs the revision's ``slamreplay run`` on a worker (whose
    node must see the worktree and the recordings at the same paths: one machine, or a shared file system)."""
    try:
        import ray
    except ImportError:
        raise ReplayError("--executor ray needs Ray: pip install 'slamreplay[ray]'") from None
    from slamreplay.replay.runs.revisions import run_cell

    remote = ray.remote(num_cpus=1)(run_cell)
    lock = threading.Lock()

    def run(revision: Revision, job: CellJob) -> str | None:
        with lock:  # connected on the first cell: a history with nothing to run needs no cluster
            if not ray.is_initialized():
                ray.init(ignore_reinit_error=True, log_to_driver=False)  # a cluster when RAY_ADDRESS names one
        return ray.get(remote.remote(revision, job))  # type: ignore[no-any-return]

    return run


def cmd_history(args: argparse.Namespace) -> int:
    from slamreplay.replay.runs.changepoints import detect_changes
    from slamreplay.replay.runs.history import run_history, select_commits
    from slamreplay.replay.runs.history_dates import history_by_date, store_rows
    from slamreplay.replay.runs.history_report import REPORT, format_changes, write_history_reports
    from slamreplay.replay.runs.revisions import find_repo, resolve
    from slamreplay.replay.runs.suite import load_suite

    tic = time.perf_counter()
    if args.version and args.by != "date":
        raise ReplayError("--version picks the runs of one code version for --by date: add --by date")
    suite = load_suite(args.suite)
    repo = find_repo()
    shas = select_commits(repo, args.revs, args.commits, args.every)
    version = resolve(repo, args.version) if args.version else None
    out = Path(args.out)
    run = ray_runner() if args.executor == "ray" else None
    label = f"history {suite.name}"
    say(f"{label}: {len(shas)} commit(s) x {len(suite.cells())} cell(s) into {out}", args.quiet)
    with progress_bar(label, args.quiet, unit="cells") as update:
        kwargs: dict[str, Any] = {"run": run} if run is not None else {}
        history = run_history(suite, out, shas, repo, workers=args.jobs, retry_failed=args.retry_failed,
                              note=lambda text: say(f"{label}: {text}", args.quiet), progress=update, **kwargs)
    by_commit = args.by == "commit"
    changes = write_history_reports(history, detect_changes(history, args.metric), out,
                                    args.markdown if by_commit else None, base_url=args.base_url, metrics=args.metric)
    if not by_commit:
        history = history_by_date(store_rows(history), version, suite.name)
        changes = write_history_reports(history, detect_changes(history, args.metric), out, args.markdown,
                                        base_url=args.base_url, metrics=args.metric, by="date")
    if not args.quiet:
        print(format_changes(history, changes))
        points = f"{len(history.commits)} {'commit' if by_commit else 'day'}(s)"
        print(f"history: {points} in {out / 'history.jsonl'}, {len(changes)} change(s); "
              f"report {out / REPORT[args.by]} ({time.perf_counter() - tic:.1f} s)")
    return 0


def add_history_parsers(sub: Any, quiet: argparse.ArgumentParser) -> None:
    """The ``history`` subcommand."""
    hp = sub.add_parser("history", parents=[quiet], help="a suite's metrics over commits, where they changed",
                        description="Run SUITE.toml at each selected commit (cached worktrees and environments, "
                                    "as compare rev: builds them) into DIR/history.jsonl, an append-only store a "
                                    "later call extends; find the commits where each cell's metric changed beyond "
                                    "seed noise; write DIR/index.html (self-contained; commits in git's order, "
                                    "whenever they ran) and, with --markdown, the changes for a CI job summary; "
                                    "--by date: the same over the days the runs started. A commit that does not "
                                    "build or run is recorded and the history goes on. Exit 0 when the history "
                                    "ran, 2 on bad input.")
    hp.add_argument("suite", metavar="SUITE.toml", help="the suite file (see docs/compare.md)")
    which = hp.add_mutually_exclusive_group(required=True)
    which.add_argument("--revs", metavar="A..B", help="A and each commit after it up to B (first parents), or one "
                                                      "revision")
    which.add_argument("--commits", metavar="FILE", help="the commits to run, one revision a line, oldest first")
    hp.add_argument("--every", type=int, default=1, metavar="N",
                    help="every Nth commit, counted back from the newest (the oldest is kept) (default: 1)")
    hp.add_argument("--out", required=True, metavar="DIR", help="history directory (created or extended)")
    hp.add_argument("--executor", choices=["local", "ray"], default="local",
                    help="cells as local processes, or as Ray tasks (slamreplay[ray]) (default: local)")
    hp.add_argument("--jobs", type=int, default=1, metavar="N", help="cells running at once (default: 1)")
    hp.add_argument("--retry-failed", action="store_true",
                    help="run again the cells that failed and the commits that did not build")
    hp.add_argument("--by", choices=["commit", "date"], default="commit",
                    help="commit: the metrics over the commits, in git's order (DIR/index.html); date: over the days "
                         "the runs started, whatever code they ran (also DIR/by-date.html; its changes are the ones "
                         "printed and summarized) (default: commit)")
    hp.add_argument("--version", metavar="REV", help="with --by date: only the runs of this commit's code")
    hp.add_argument("--metric", action="append", default=[], metavar="NAME",
                    help="only these metrics in the report (repeatable; default: every metric)")
    hp.add_argument("--markdown", metavar="SUMMARY.md", help="write the changes as markdown for a CI job summary; "
                    "links relative to its folder, only to files inside it")
    hp.add_argument("--base-url", metavar="URL", help="where CI publishes the markdown summary's folder: its links "
                    "become URL/<path relative to that folder>")
    hp.set_defaults(func=cmd_history)
