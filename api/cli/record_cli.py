"""``record`` (one sub-command per importer plugin, and ``record live``), ``inspect`` and ``recover``: making
recordings and checking them."""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

from slamreplay.api.cli.cli_parser import EXIT_BAD_INPUT, EXIT_CHECK_FAILED, EXIT_OK, CliError, eprint
from slamreplay.api.cli.live_cli import add_live_parser
from slamreplay.api.cli.progress import progress_bar
from slamreplay.recorder.errors import RecorderError
from slamreplay.recorder.options import parse_pairs


def cmd_record(args: argparse.Namespace) -> int:
    """``record NAME``: the importer (or simulator) NAME writes one recording (recorder/sources.py)."""
    from slamreplay.recorder.sources import get_importer

    importer = get_importer(args.source)
    options = {k: v for k, v in vars(args).items() if k not in ("func", "source", "command", "debug", "quiet")}
    log = (lambda text: None) if args.quiet else eprint
    with progress_bar(f"record {args.source}", args.quiet) as update:
        summary = importer.record(options, update, log)
    if not args.quiet:
        eprint(f"wrote {args.out}: {summary}")
    return EXIT_OK


def cmd_record_broken(args: argparse.Namespace) -> int:
    """A broken importer plugin: its one-line error, exit 2."""
    from slamreplay.recorder.sources import importer_plugins

    importer_plugins()[args.source].load()  # raises PluginError, a RecorderError
    return EXIT_BAD_INPUT


def _add_record_parsers(rsub: Any, quiet: argparse.ArgumentParser) -> None:
    """One ``record`` sub-command per importer of the entry-point group ``slamreplay.importers``."""
    from slamreplay.recorder.sources import importer_plugins

    for name, plugin in importer_plugins().items():
        if plugin.error is not None:
            broken = rsub.add_parser(name, help=f"BROKEN ({plugin.origin}): {plugin.error}", add_help=False)
            broken.add_argument("rest", nargs=argparse.REMAINDER)
            broken.set_defaults(func=cmd_record_broken, quiet=False)
            continue
        importer = plugin.load()()
        origin = "" if plugin.builtin else f" [{plugin.origin}]"
        parser = rsub.add_parser(name, parents=[quiet], help=importer.help + origin, description=importer.description)
        importer.add_arguments(parser)
        parser.set_defaults(func=cmd_record)


# ---------------------------------------------------------------------------------------
# inspect, recover


def cmd_inspect(args: argparse.Namespace) -> int:
    from slamreplay.recorder.importers.ros2bag import is_ros2_bag, iter_plan_lines
    from slamreplay.replay.tools.inspect import inspect_recording

    path = Path(args.file)
    if path.suffix == ".db3" or (path.is_dir() and any(path.glob("*.db3"))):
        return _inspect_bag(args)  # sqlite3 storage: only rosbags reads it

    report = inspect_recording(args.file, parse_pairs(args.topic_map))
    bag = is_ros2_bag(path) or any(t["encoding"] == "cdr" for t in report.get("topics", []))
    if not bag and (given := _bag_options_given(args)):
        raise CliError(f"{', '.join(given)} apply to ROS 2 bags, and {path.name} is a slamreplay recording: drop "
                       f"{'them' if len(given) > 1 else 'it'}")
    plan: Any = None
    if bag:  # an MCAP-storage ROS 2 bag: also what `record ros2` would make of it
        try:
            plan = _plan(args)
        except RecorderError as err:
            plan = err
    if args.json:
        if bag:
            report["ros2_import"] = plan.as_dict() if not isinstance(plan, RecorderError) else {"error": str(plan)}
        print(json.dumps(report, indent=2, sort_keys=True))
    else:
        print(f"{report['path']}  ({report['size_bytes']:,} bytes)")
        print(f"health: {report['health']}")
        for p in report["problems"]:
            print(f"  problem: {p}")
        if "message_count" in report:
            print(f"messages: {report['message_count']:,} in {report['chunk_count']} chunks, "
                  f"{report['duration_s']:.3f} s ({report['start_ns']} .. {report['end_ns']} ns)")
            print(f"{'topic':<28} {'read as':<26} {'schema':<32} {'messages':>9} {'rate Hz':>9}")
            for t in report["topics"]:
                rate = "" if t["rate_hz"] is None else f"{t['rate_hz']:.2f}"
                print(f"{t['topic']:<28} {t['read_as'] or '-':<26} {t['schema']:<32} {t['messages']:>9} {rate:>9}")
            for name, meta in report["metadata"].items():
                print(f"metadata {name}: " + ", ".join(f"{k}={v}" for k, v in sorted(meta.items())
                                                        if k != "sensor_model"))  # printed below, line by line
            models = {"": report["sensor_model"], **report["robot_sensor_models"]}
            if len(models) > 1 and models[""] is None:
                del models[""]  # several robots, each with its own
            for robot, model in models.items():
                whose = f"robot {robot} (run --robot {robot})" if robot else "sensor model"
                if model is None:
                    print(f"{whose}: not stated (pipelines use their defaults where you set nothing)")
                    continue
                print(f"{whose} ({model['source'] or 'source not stated'}); pipelines use it where you set nothing:")
                for line in model["lines"]:
                    print(f"  {line}")
    if isinstance(plan, RecorderError) and not args.json:
        print(f"\n`slamreplay record ros2` cannot import it: {plan}")
    elif plan is not None and not args.json:
        print("\n`slamreplay record ros2` would import it as:\n" + "\n".join(iter_plan_lines(plan)))
    return EXIT_OK if report["health"] == "ok" else EXIT_CHECK_FAILED


BAG_OPTION_DEFAULTS = {"base_frame": "base_link", "odom_frame": "odom", "ground_truth_frame": None,
                       "typestore": "humble"}


def _bag_options_given(args: argparse.Namespace) -> list[str]:
    """The ROS 2 bag options of ``inspect`` set to something else than their defaults."""
    return [f"--{k.replace('_', '-')}" for k, v in BAG_OPTION_DEFAULTS.items() if getattr(args, k) != v]


def _plan(args: argparse.Namespace) -> Any:
    from slamreplay.recorder.importers.ros2bag import plan_bag

    return plan_bag(Path(args.file), parse_pairs(args.topic_map), base_frame=args.base_frame,
                    odom_frame=args.odom_frame, ground_truth_frame=args.ground_truth_frame, typestore=args.typestore)


def _inspect_bag(args: argparse.Namespace) -> int:
    """A ROS 2 bag (folder or .db3): each topic, its type and what `record ros2` makes of it."""
    from slamreplay.recorder.importers.ros2bag import iter_plan_lines

    plan = _plan(args)
    if args.json:
        print(json.dumps(plan.as_dict(), indent=2, sort_keys=True))
    else:
        print("\n".join(iter_plan_lines(plan)))
    return EXIT_OK


def cmd_recover(args: argparse.Namespace) -> int:
    from slamreplay.recorder.recover import describe, recover

    print(describe(recover(args.file, args.out), args.out))
    return EXIT_OK


def add_record_parsers(sub: Any, quiet: argparse.ArgumentParser, command: str | None) -> None:
    """``record`` (its sub-commands only when ``command`` is ``record``: each importer is imported to ask for its
    options), ``inspect`` and ``recover``."""
    rec = sub.add_parser("record", help="make a recording from a simulator or a public dataset")
    rsub = rec.add_subparsers(dest="source", required=True, metavar="SOURCE")
    if command in (None, "record"):
        _add_record_parsers(rsub, quiet)
        add_live_parser(rsub, quiet)  # record live: a stream, until stopped (api/cli/live_cli.py)

    ins = sub.add_parser("inspect", help="topics, schemas, counts, time span and health of a recording")
    ins.add_argument("file", help="an .mcap recording or a ROS 2 bag directory")
    ins.add_argument("--json", action="store_true", help="machine-readable output")
    ins.add_argument("--topic-map", action="append", default=[], metavar="FILE_TOPIC=TOPIC",
                     help="read FILE_TOPIC as a slamreplay topic (repeatable)")
    bag = ins.add_argument_group("ROS 2 bags", "what `record ros2` would make of the bag with these options: the tf "
                                 "frames it would compose, each checked against the bag's tf tree")
    bag.add_argument("--base-frame", default="base_link", help="the robot's tf frame (default: base_link)")
    bag.add_argument("--odom-frame", default="odom", help="tf frame of odometry (default: odom)")
    bag.add_argument("--ground-truth-frame", default=None, metavar="FRAME",
                     help="the frame ground truth would be taken in (e.g. map)")
    bag.add_argument("--typestore", choices=("humble", "jazzy"), default="humble",
                     help="message definitions for bags that store none (default: humble)")
    ins.set_defaults(func=cmd_inspect)

    rcv = sub.add_parser("recover", help="salvage a truncated or damaged recording into a valid one")
    rcv.add_argument("file", help="the damaged .mcap (or .mcap.partial)")
    rcv.add_argument("--out", required=True, help="the new .mcap to write (must not exist)")
    rcv.set_defaults(func=cmd_recover)
