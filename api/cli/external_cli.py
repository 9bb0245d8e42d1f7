"""``slamreplay evaluate`` and ``slamreplay export``: SLAM systems outside slamreplay (docs/external.md).

``evaluate`` scores a trajectory estimated elsewhere (TUM, KITTI, a ROS 2 bag's pose topic) into a run
directory; ``export`` writes what an external program reads (odometry as TUM or CSV, range-bearing CSV,
images with their times). External programs as pipelines are declared in TOML files and run with
``slamreplay run`` like any pipeline. Imports are inside the handlers: the parser is built at every start.
"""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path
from typing import Any

from slamreplay.api.cli.cli_parser import EXIT_OK
from slamreplay.replay.tools.export_names import exports_help


def cmd_evaluate(args: argparse.Namespace) -> int:
    """``evaluate ESTIMATE --recording REC --out RUN``: a run directory scoring the estimate."""
    from slamreplay.api.cli.hints import view_hint
    from slamreplay.replay.runs.evaluate_run import association_from, evaluate_estimate

    assoc = association_from(args.t_offset_s, args.t_max_diff_s, args.align)
    limit = {"max_bytes": args.max_bytes} if args.max_bytes is not None else {}
    result = evaluate_estimate(args.estimate, args.recording, args.out, fmt=args.format, topic=args.topic,
                               times=args.times, association=assoc, min_coverage=args.min_coverage, **limit)
    if not args.quiet:
        for name, value in sorted(result.metrics.items()):
            print(f"  {name:<28} {value:.6g}")
        print(f"run {result.run_id}: {args.estimate} scored against {Path(args.recording).name}")
        print("\n".join(view_hint(Path(args.out) / "run.rrd")))
    return EXIT_OK


def cmd_export(args: argparse.Namespace) -> int:
    """``export REC --out DIR --what odometry_tum,...``: the files an external program may read."""
    from slamreplay.recorder.options import parse_pairs
    from slamreplay.replay.tools.export import export_recording, parse_exports

    written = export_recording(Path(args.recording), Path(args.out), parse_exports(args.what),
                               topic_map=parse_pairs(args.topic_map))
    if not args.quiet:
        for path in written:
            print(f"wrote {path}")
    return EXIT_OK


def determinism_config(pipeline: str) -> dict[str, str]:
    """The config of ``run --check-determinism``; ReplayError for a pipeline that is not an external program."""
    from slamreplay.replay.engine.pipeline import get_pipeline
    from slamreplay.replay.errors import ReplayError

    cls = get_pipeline(pipeline)
    if "check_determinism" not in {f.name for f in dataclasses.fields(cls.Config)}:
        raise ReplayError(f"--check-determinism runs an external program twice (docs/external.md); pipeline "
                          f"{pipeline} is slamreplay code, deterministic by design: run it twice and `slamreplay "
                          f"diff` the runs to check")
    return {"check_determinism": "true"}


def add_external_parsers(sub: Any, quiet: argparse.ArgumentParser) -> None:
    """The ``evaluate`` and ``export`` subcommands."""
    ev = sub.add_parser("evaluate", parents=[quiet], help="score a trajectory estimated elsewhere into a run directory",
                        description="Score ESTIMATE (a TUM file, a KITTI file with --times, or a pose topic of a ROS 2 "
                                    "bag with --topic) against the ground truth of REC into the run directory RUN, "
                                    "which diff, compare and trajectory read like any run (docs/external.md). The "
                                    "truth is interpolated at the estimate's times, as runs are scored. Exit 2 on "
                                    "bad input.")
    ev.add_argument("estimate", metavar="ESTIMATE", help="a TUM or KITTI file, or a ROS 2 bag (folder, .db3, .mcap)")
    ev.add_argument("--recording", required=True, metavar="REC", help="the recording with /ground_truth/pose")
    ev.add_argument("--out", required=True, metavar="RUN_DIR", help="run directory to create (must not exist)")
    ev.add_argument("--format", choices=["tum", "kitti", "topic"], default=None,
                    help="how to read ESTIMATE (default: topic with --topic, kitti for *.kitti, else tum)")
    ev.add_argument("--topic", metavar="TOPIC", help="the pose topic of a ROS 2 bag (PoseStamped, "
                    "PoseWithCovarianceStamped or Odometry), e.g. /slam/pose")
    ev.add_argument("--times", metavar="FILE", help="KITTI: the times of the poses (seconds, a line each)")
    ev.add_argument("--align", choices=["none", "origin", "se2"], default="none",
                    help="align the estimate to the truth before scoring (as `trajectory --align`; default none: "
                         "it is in the world frame already)")
    ev.add_argument("--t-offset-s", type=float, default=0.0, metavar="S",
                    help="add S seconds to every estimate time (evo's --t_offset; default 0)")
    ev.add_argument("--t-max-diff-s", type=float, default=None, metavar="S",
                    help="leave out estimates further than S seconds from any ground-truth message (evo's "
                         "--t_max_diff; default: keep every one inside the truth's time span)")
    ev.add_argument("--min-coverage", type=float, default=None, metavar="F",
                    help="fail when the estimate's times cover less than F of the ground truth's time span "
                         "(default 0.5; 0: any overlap; no overlap at all is always refused)")
    ev.add_argument("--max-bytes", type=int, default=None, metavar="N",
                    help="refuse an estimate file larger than N bytes before reading it (default 256 MiB)")
    ev.set_defaults(func=cmd_evaluate)

    ex = sub.add_parser("export", parents=[quiet], help="write a recording's data as files an external program reads",
                        description="Write the exports of REC that external pipelines ask for (docs/external.md) "
                                    f"into DIR: {exports_help()}.")
    ex.add_argument("recording", metavar="REC", help="an .mcap recording")
    ex.add_argument("--out", required=True, metavar="DIR", help="folder to write into (created if needed)")
    ex.add_argument("--what", default="odometry_tum,odometry_csv", metavar="EXPORT[,EXPORT]",
                    help="which exports (default: odometry_tum,odometry_csv)")
    ex.add_argument("--topic-map", action="append", default=[], metavar="FILE_TOPIC=TOPIC",
                    help="read the recording's topic FILE_TOPIC as TOPIC (repeatable)")
    ex.set_defaults(func=cmd_export)
