"""``slamreplay suite run`` and ``slamreplay compare``: suites of runs, across revisions.

Cells of the running code go through the service's executors (``LocalExecutor``: spawned
worker processes; ``RayExecutor``: Ray tasks), running the same ``run_task`` as service jobs.
Cells of another revision (``--rev``) run through that revision's own ``slamreplay run``
(``slamreplay.replay.runs.revisions``).
"""

from __future__ import annotations

import argparse
import json
import os
import uuid
from collections.abc import Iterable, Iterator
from concurrent.futures import ThreadPoolExecutor, as_completed
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING, Any

from slamreplay.api.cli.progress import progress_bar, say
from slamreplay.recorder.options import did_you_mean
from slamreplay.replay.errors import ReplayError

if TYPE_CHECKING:  # imported where used: the command line builds its parser from this module, and starts fast
    from slamreplay.api.service.executor import Outcome, Report, Task
    from slamreplay.replay.runs.suite_run import CellJob


def suite_job(task: Task, report: Report | None = None) -> Outcome:
    """What a suite's worker runs: ``run_task`` with progress kept in the worker (no job store)."""
    from slamreplay.api.service.executor import run_task

    del report
    return run_task(task, lambda fraction: None)


def _executor(kind: str, jobs: int) -> Any:
    if kind == "ray":
        from slamreplay.api.service.ray_executor import RayExecutor
        try:
            return RayExecutor(jobs, job=suite_job)
        except ImportError as err:
            raise ReplayError(str(err)) from None
    from slamreplay.api.service.executor import LocalExecutor
    return LocalExecutor(jobs, job=suite_job)


@contextmanager
def _one_blas_thread() -> Iterator[None]:
    """Workers started inside see one BLAS/OpenMP thread each, as Ray gives its workers: replays do
    small dense algebra that BLAS threads slow down, and N workers with a thread per core each would
    oversubscribe the cores. A user's own setting wins."""
    names = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")
    saved = {n: os.environ.get(n) for n in names}
    for n in names:
        os.environ.setdefault(n, "1")
    try:
        yield
    finally:
        for n, v in saved.items():
            if v is None:
                os.environ.pop(n, None)
            else:
                os.environ[n] = v


def executor_runner(kind: str, jobs: int) -> Any:
    """``run_cells`` for ``slamreplay.replay.runs.suite_run.run_suite`` on a local process pool or Ray."""
    from slamreplay.api.service.executor import Task

    def run_cells(todo: list[CellJob]) -> Iterator[tuple[CellJob, str | None]]:
        if not todo:
            return
        ex = _executor(kind, min(jobs, len(todo)))
        with _one_blas_thread():
            ex.start()
        try:
            with ThreadPoolExecutor(max_workers=ex.slots) as pool:
                futures = {}
                for job in todo:
                    task = Task(uuid.uuid4().hex, str(job.recording.path), job.cell.pipeline, dict(job.cell.config),
                                job.cell.seed, str(job.run_dir), "", dict(job.recording.topic_map))
                    futures[pool.submit(ex.run, task)] = job
                for fut in as_completed(futures):
                    outcome: Outcome = fut.result()
                    yield futures[fut], (None if outcome.status == "succeeded" else outcome.error or outcome.status)
        finally:
            ex.close()

    return run_cells


def run_suite_at(suite_path: str, out: Path, rev: str | None, executor: str, jobs: int, quiet: bool,
                 repo: Path | None = None, label: str | None = None) -> list[dict[str, Any]]:
    """Run a suite with the running code (``rev`` None) or at revision ``rev``; the results rows.

    ``label`` starts the progress lines and notes (default: ``suite NAME``, with ``@REV`` at a revision).
    """
    from slamreplay.replay.runs.revisions import find_repo, prepare_revision, run_cells
    from slamreplay.replay.runs.suite import load_suite
    from slamreplay.replay.runs.suite_run import cache_dir, code_version, run_suite

    if jobs < 1:
        raise ReplayError(f"--jobs must be >= 1, got {jobs}")
    suite = load_suite(suite_path)
    cache = cache_dir()
    label = label or f"suite {suite.name}" + (f" @{rev}" if rev is not None else "")
    if rev is None:
        runner, code = executor_runner(executor, jobs), code_version()
    else:
        if executor != "local":
            raise ReplayError("--rev runs cells in the revision's own environment: use --executor local")
        revision = prepare_revision(repo or find_repo(), rev, cache, note=lambda text: say(f"{label}: {text}", quiet))
        code = revision.sha

        def runner(todo: list[CellJob]) -> Iterable[tuple[CellJob, str | None]]:
            return run_cells(revision, todo, jobs)
    with progress_bar(label, quiet, unit="cells", reused="reused") as update:
        return run_suite(suite, out, code, runner, cache=cache, rev=rev, progress=update)


def cmd_suite_run(args: argparse.Namespace) -> int:
    import time

    tic = time.perf_counter()
    rows = run_suite_at(args.suite, Path(args.out), args.rev, args.executor, args.jobs, args.quiet)
    failed = [r for r in rows if r["status"] != "succeeded"]
    cached = sum(1 for r in rows if r.get("cached"))
    if not args.quiet:
        from slamreplay.replay.runs.compare import variants_table
        print(variants_table(rows))
        for r in failed:
            print(f"  FAILED {Path(r['run_dir']).name}: {r['error']}")
        print(f"suite: {len(rows)} cells, {cached} from cache, {len(rows) - cached - len(failed)} run, "
              f"{len(failed)} failed in {time.perf_counter() - tic:.2f} s; "
              f"results in {Path(args.out) / 'results.jsonl'}")
    return 0


def _side(spec: str, suite: str | None, args: argparse.Namespace) -> Any:
    from slamreplay.replay.runs.compare import load_side
    from slamreplay.replay.runs.revisions import find_repo, resolve
    from slamreplay.replay.runs.suite_run import cache_dir

    if not spec.startswith("rev:"):
        return load_side(spec)
    if suite is None:
        raise ReplayError(f"{spec} needs --suite SUITE.toml (the suite to run at that revision)")
    rev = spec[4:]
    sha = resolve(find_repo(), rev)
    out = cache_dir() / "results" / sha
    shown = f"rev:{sha[:10]}" if rev == sha else spec  # bisect names commits by their full sha
    run_suite_at(suite, out, rev, "local", args.jobs, args.quiet, label=f"{args.command} {shown}")
    return load_side(out, label=spec, kind="rev", sha=sha)


def cmd_compare(args: argparse.Namespace) -> int:
    from slamreplay.replay.runs.compare import compare, format_table
    from slamreplay.replay.runs.diff import parse_tolerances
    from slamreplay.replay.runs.report import write_reports
    from slamreplay.replay.runs.revisions import commit_range, find_repo

    tolerances = parse_tolerances(args.tolerance)
    if args.suite is not None:
        from slamreplay.replay.runs.suite import load_suite
        load_suite(args.suite)  # a broken suite fails before anything runs
    a, b = _side(args.a, args.suite, args), _side(args.b, args.suite, args)
    result = compare(a, b, tolerances)
    if a.sha and b.sha:
        result.commits = commit_range(find_repo(), a.sha, b.sha)
    pair_links = None
    if args.rrd_dir is not None:
        from slamreplay.replay.runs.diff_view import write_comparison_rrd
        from slamreplay.replay.runs.report import pair_file_links, write_pair_rrds
        pair_links = pair_file_links(write_pair_rrds(result, Path(args.rrd_dir), write_comparison_rrd))
    write_reports(result, args.report, args.markdown, pair_links, base_url=args.base_url)
    if args.json:
        print(json.dumps(result.to_json(), indent=2, default=str))
    else:  # -q: the verdict line alone (the exit code says it too)
        print(format_table(result).splitlines()[-1] if args.quiet else format_table(result))
    return 1 if result.regressions else 0


def cmd_bisect(args: argparse.Namespace) -> int:
    from slamreplay.replay.runs.compare import compare
    from slamreplay.replay.runs.diff import parse_tolerances
    from slamreplay.replay.runs.revisions import ancestry, find_repo, one_line, resolve
    from slamreplay.replay.runs.suite import load_suite

    tolerances = parse_tolerances(args.tolerance)
    load_suite(args.suite)
    repo = find_repo()
    good, bad = resolve(repo, args.good), resolve(repo, args.bad)
    commits = ancestry(repo, good, bad)
    if not commits:
        raise ReplayError(f"{args.good} and {args.bad} are the same commit: nothing to bisect")
    base = _side(f"rev:{good}", args.suite, args)
    known = {m for r in base.rows for m in r.get("metrics", {})}
    if args.metric not in known:
        raise ReplayError(f"--metric {args.metric!r} is not a metric of this suite"
                          f"{did_you_mean(args.metric, known, True)}; it has: {', '.join(sorted(known))}")
    tested: dict[str, bool] = {}

    def regressed(sha: str) -> bool:
        c = compare(base, _side(f"rev:{sha}", args.suite, args), tolerances)
        tested[sha] = any(r.metric == args.metric or r.verdict == "failed" for r in c.regressions)
        print(f"  {sha[:10]} {'regressed' if tested[sha] else 'good'}", flush=True)
        return tested[sha]

    print(f"bisecting {len(commits)} commit(s) after {good[:10]} for a regression of {args.metric}")
    if not regressed(bad):
        raise ReplayError(f"{args.metric} did not regress at {args.bad} against {args.good}: nothing to bisect")
    lo, hi = -1, len(commits) - 1  # commits[hi] regressed; lo: the last known good (-1: GOOD itself)
    while hi - lo > 1:
        mid = (lo + hi) // 2
        if regressed(commits[mid]):
            hi = mid
        else:
            lo = mid
    print(f"first regressed commit ({len(tested)} revision(s) run): {one_line(repo, commits[hi])}")
    return 0


def add_suite_parsers(sub: Any, quiet: argparse.ArgumentParser) -> None:
    """The ``suite`` and ``compare`` subcommands."""
    st = sub.add_parser("suite", help="run a suite: recordings x pipelines x config variants x seeds")
    ssub = st.add_subparsers(dest="suite_command", required=True, metavar="ACTION")
    sr = ssub.add_parser("run", parents=[quiet], help="run every cell of a suite file into a results directory",
                         description="Run every cell (recording x pipeline x variant x seed) of SUITE.toml into "
                                     "RESULTS_DIR/runs/ and write RESULTS_DIR/results.jsonl. Cells whose inputs "
                                     "already have a finished run there are not run again. Exit 0 when the suite "
                                     "ran (failed cells are recorded as failed), 2 on bad input.")
    sr.add_argument("suite", metavar="SUITE.toml", help="the suite file (see docs/compare.md)")
    sr.add_argument("--out", required=True, metavar="RESULTS_DIR", help="results directory (created or reused)")
    sr.add_argument("--rev", default=None, metavar="GITREV",
                    help="run the suite at this git revision: its cached worktree, in the environment shared by "
                         "commits of the same dependencies (slamreplay cache)")
    sr.add_argument("--executor", choices=["local", "ray"], default="local",
                    help="local worker processes, or Ray tasks (slamreplay[ray]) (default: local)")
    sr.add_argument("--jobs", type=int, default=1, metavar="N", help="cells running at once (default: 1)")
    sr.set_defaults(func=cmd_suite_run)

    cp = sub.add_parser("compare", parents=[quiet], help="compare two sets of runs; exit 1 on a regression",
                        description="Compare B against A, cell by cell (recording, pipeline, variant), metric by "
                                    "metric, with a paired t-test over seeds to tell a regression from seed noise. "
                                    "A and B: a run directory, a suite results directory, or rev:GITREV with "
                                    "--suite. Exit 0: nothing significantly worse; 1: a regression; 2: bad input.")
    cp.add_argument("a", help="baseline: RUN_DIR, RESULTS_DIR or rev:GITREV")
    cp.add_argument("b", help="to judge: RUN_DIR, RESULTS_DIR or rev:GITREV")
    cp.add_argument("--suite", metavar="SUITE.toml", help="the suite to run at a rev: side (cached)")
    cp.add_argument("--report", metavar="REPORT.html", help="write a self-contained HTML report")
    cp.add_argument("--markdown", metavar="SUMMARY.md", help="write the table as markdown for a CI job summary: "
                    "regressions first, unchanged rows folded; links relative to its folder, only to files inside it")
    cp.add_argument("--base-url", metavar="URL", help="where CI publishes the markdown summary's folder: its links "
                    "become URL/<path relative to that folder> (default: relative links)")
    cp.add_argument("--rrd-dir", metavar="DIR", help="write one comparison .rrd per A/B run pair (both runs, "
                                                     "same axes) into DIR; the report links each cell's pairs")
    cp.add_argument("--tolerance", action="append", default=[], metavar="NAME=VALUE",
                    help="allowed worsening of a metric: absolute, or N%% of A's mean; NAME * means every metric")
    cp.add_argument("--jobs", type=int, default=1, metavar="N", help="cells at once when a rev: side runs")
    cp.add_argument("--json", action="store_true", help="machine-readable output")
    cp.set_defaults(func=cmd_compare)

    bs = sub.add_parser("bisect", parents=[quiet], help="find the first commit at which a metric regressed",
                        description="Binary search over the commits from GOOD to BAD (ancestry path): runs the "
                                    "suite at each revision tried (cached, as compare rev: does) and compares it "
                                    "with GOOD. Prints the first commit where METRIC is a regression. Exit 0 when "
                                    "found, 2 on bad input (BAD not regressed, unknown metric or revision).")
    bs.add_argument("good", help="a revision where the metric is fine")
    bs.add_argument("bad", help="a later revision where it regressed")
    bs.add_argument("--suite", required=True, metavar="SUITE.toml", help="the suite to run at each revision")
    bs.add_argument("--metric", required=True, metavar="NAME", help="the metric that regressed")
    bs.add_argument("--tolerance", action="append", default=[], metavar="NAME=VALUE",
                    help="as for compare")
    bs.add_argument("--jobs", type=int, default=1, metavar="N", help="cells at once")
    bs.set_defaults(func=cmd_bisect)
