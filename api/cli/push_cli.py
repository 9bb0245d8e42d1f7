"""``slamreplay push RUN_DIR... --server URL``: runs made here (``run``, ``suite run``, ``evaluate``, an external
program) put on a team's server, beside its own runs (`slamreplay.api.client.client`; docs/service.md).

A ``suite run`` output folder (it holds ``results.jsonl``) pushes each of its cells' runs, then the suite (its
name, file and cells), which the server's suite pages, comparisons and history of that name then count. The
recording a run replayed is uploaded first when the server lacks it (``--recording FILE``, else the path its
manifest records).
One line per run: where it went, or why the server refused it. Exit 0 when every run is on the server, 2 when any
was refused or could not be read (the others are still pushed).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

from slamreplay.api.cli.cli_parser import EXIT_BAD_INPUT, EXIT_OK


def cmd_push(args: argparse.Namespace) -> int:
    from slamreplay.api.client.client import Client, ClientError
    from slamreplay.replay.errors import ReplayError

    try:
        server = Client(args.server, args.token)
        for folder in args.run_dir:
            if not (folder / "manifest.json").is_file() and not (folder / "results.jsonl").is_file():
                raise ClientError(f"{folder} is not a run directory (no manifest.json) nor a `suite run` output "
                                  "folder (no results.jsonl)")
    except ClientError as err:
        raise ReplayError(str(err)) from None
    counts = {"runs": 0, "refused": 0}

    def said(run: Path, job: dict[str, Any] | None, new: bool, err: ClientError | None) -> None:
        counts["runs"] += 1
        if job is None:
            counts["refused"] += 1
            print(f"{run}: refused: {err}", file=sys.stderr)
            return
        what = "pushed as job" if new else "already on the server as job"
        metric = next(iter(sorted((job.get("metrics") or {}).items())), None)
        shown = f" ({metric[0]} {metric[1]:.6g})" if metric and isinstance(metric[1], float) else ""
        print(f"{run}: {what} {job['id'][:8]}, {job['pipeline']} seed {job['seed']} {job['status']}{shown}: "
              f"{server.url}/ui/jobs/{job['id']}")

    labels = {"recording": args.recording, "origin": args.origin, "name": args.name, "tags": args.tag,
              "note": args.note}
    try:
        for folder in args.run_dir:
            if (folder / "manifest.json").is_file():
                try:
                    said(folder, *server.push(folder, **labels), None)
                except ClientError as err:
                    if err.status == 0:
                        raise
                    said(folder, None, False, err)
                continue
            suite = server.push_suite(folder, on_run=said, **labels)
            if suite is not None:
                print(f"{folder}: suite {suite['name']!r} ({len(suite['cells'])} cells) recorded as "
                      f"{suite['id'][:8]}: {server.url}/ui/suites/{suite['id']}")
            else:
                print(f"{folder}: suite not recorded: {counts['refused']} of its runs were refused", file=sys.stderr)
    except ClientError as err:
        raise ReplayError(str(err)) from None
    if counts["runs"] > 1:
        print(f"{counts['runs'] - counts['refused']} of {counts['runs']} runs on {server.url}"
              + (f"; {counts['refused']} refused" if counts["refused"] else ""))
    return EXIT_BAD_INPUT if counts["refused"] else EXIT_OK


def add_push_parser(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    p = sub.add_parser("push", help="put runs made here (run, suite run, evaluate) on a team's server",
                       description=__doc__.split("\n\n")[0] + "\n\n" + __doc__.split("\n\n")[1],
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("run_dir", nargs="+", type=Path, metavar="RUN_DIR",
                   help="a run directory, or a `suite run` output folder (each of its cells' runs)")
    p.add_argument("--server", required=True, metavar="URL", help="the server, e.g. http://slam.lan:8000")
    p.add_argument("--token", default=None, help="your token (default: $SLAMREPLAY_TOKEN; none on an open server)")
    p.add_argument("--recording", type=Path, default=None, metavar="FILE",
                   help="the recording the runs replayed, uploaded when the server lacks it (default: the path each "
                        "run's manifest records)")
    p.add_argument("--origin", default=None, metavar="TEXT",
                   help="where the runs were made, shown on the page (default: the CI job's URL on GitHub Actions "
                        "or GitLab CI, else this host's name)")
    p.add_argument("--name", default=None, help="a name for the pushed runs")
    p.add_argument("--tag", action="append", default=[], metavar="TAG", help="a tag of the pushed runs (repeatable)")
    p.add_argument("--note", default=None, help="a note on the pushed runs")
    p.set_defaults(func=cmd_push)
