"""The ``slamreplay`` command line.

Exit codes: 0 success; 1 a check failed (``diff`` found a regression, ``inspect`` found a
damaged file); 2 bad input (one line on stderr saying what is wrong and what to do).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import sys
import traceback
from collections.abc import Sequence
from pathlib import Path
from typing import Any

# Only light modules here (a test checks it): the parser is built before every command, --help included, and
# each command imports the heavy stack (numpy, rerun, mcap, fastapi ...) in its function.
from slamreplay.api.cache_cli import add_cache_parsers
from slamreplay.api.cli_parser import SuggestingParser, VersionAction, command_of
from slamreplay.api.external_cli import add_external_parsers
from slamreplay.api.graph_cli import add_graph_parser
from slamreplay.api.hints import spell_commands, tool, view_hint
from slamreplay.api.history_cli import add_history_parsers
from slamreplay.api.live_cli import add_live_parser
from slamreplay.api.pipelines_cli import add_pipelines_parser
from slamreplay.api.progress import progress_bar
from slamreplay.api.push_cli import add_push_parser
from slamreplay.api.suite_cli import add_suite_parsers
from slamreplay.api.users_cli import add_users_parser
from slamreplay.recorder.errors import RecorderError
from slamreplay.replay.errors import ReplayError

EXIT_OK, EXIT_CHECK_FAILED, EXIT_BAD_INPUT = 0, 1, 2


class CliError(Exception):
    """Bad command-line input."""


def _eprint(*args: Any) -> None:
    print(*args, file=sys.stderr)


def _parse_pairs(items: Sequence[str], what: str) -> dict[str, str]:
    out = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or not key or not value:
            raise CliError(f"{what} expects A=B, got {item!r}")
        out[key] = value
    return out


# ---------------------------------------------------------------------------------------
# record


def cmd_record(args: argparse.Namespace) -> int:
    """``record NAME``: the importer (or simulator) NAME writes one recording (recorder/sources.py)."""
    from slamreplay.recorder.sources import get_importer

    importer = get_importer(args.source)
    options = {k: v for k, v in vars(args).items() if k not in ("func", "source", "command", "debug", "quiet")}
    log = (lambda text: None) if args.quiet else _eprint
    with progress_bar(f"record {args.source}", args.quiet) as update:
        summary = importer.record(options, update, log)
    if not args.quiet:
        _eprint(f"wrote {args.out}: {summary}")
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

    report = inspect_recording(args.file, _parse_pairs(args.topic_map, "--topic-map"))
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

    return plan_bag(Path(args.file), _parse_pairs(args.topic_map, "--topic-map"), base_frame=args.base_frame,
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


# ---------------------------------------------------------------------------------------
# run, diff


def _load_config_file(path: str | None) -> dict[str, Any]:
    if path is None:
        return {}
    try:
        doc = json.loads(Path(path).read_text())
    except FileNotFoundError:
        raise CliError(f"--config {path}: no such file") from None
    except json.JSONDecodeError as err:
        raise CliError(f"--config {path} is not valid JSON: {err}") from err
    if not isinstance(doc, dict):
        raise CliError(f"--config {path} must hold a JSON object of key: value")
    return doc


def cmd_run(args: argparse.Namespace) -> int:
    from slamreplay.replay.engine.recording_file import check_recording

    check_recording(args.file)  # a typo in the path: one line at once, before the replay stack is imported
    from slamreplay.replay.engine.pipeline import parse_assignments
    from slamreplay.replay.runs.run import run_recording

    config = {**_load_config_file(args.config), **parse_assignments(args.set)}
    if args.check_determinism:
        from slamreplay.api.external_cli import determinism_config

        config.update(determinism_config(args.pipeline))
    with progress_bar(f"run {args.pipeline} on {Path(args.file).name}", args.quiet, unit="messages") as update:
        result = run_recording(args.file, args.pipeline, args.out, seed=args.seed, config=config,
                               topic_map=_parse_pairs(args.topic_map, "--topic-map"),
                               start_ns=args.start_ns, end_ns=args.end_ns, log_timings=args.log_timings,
                               progress=update, preset=args.preset, robot=args.robot)
    if not args.quiet:
        for name, value in sorted(result.metrics.items()):
            print(f"  {name:<28} {value:.6g}")
        wall = result.manifest["timings"]["wall_s"]
        print(f"run {result.run_id} succeeded in {wall:.2f} s")
        print("\n".join(view_hint(Path(args.out) / "run.rrd")))
    return EXIT_OK


# `navigate --preset paper`: section IV-B resets the position to the matched node; section V takes an image
# every 50 cm or 10 degrees (the topometric-nav pipeline's paper preset holds the same values)
PAPER_NAVIGATION = {"keep_along_m": 0.0, "image_every_m": 0.5, "image_every_deg": 10.0}


def cmd_navigate(args: argparse.Namespace) -> int:
    from slamreplay.replay.tools.navigate import navigate

    overrides = dict(PAPER_NAVIGATION) if args.preset == "paper" else {}
    overrides.update({k: v for k in PAPER_NAVIGATION if (v := getattr(args, k)) is not None})
    with progress_bar(f"navigate to node {args.goal}", args.quiet) as update:
        s = navigate(args.map, args.world, args.goal, Path(args.out), start=args.start, seed=args.seed,
                     visual_correction=not args.no_visual_correction, through_walls=args.through_walls,
                     progress=update, overrides=overrides)
    if not args.quiet:
        how = "at the goal by its own estimate" if s.reached else (
            "stopped at a wall" if s.collided and not args.through_walls else "time limit, goal not reached")
        _eprint(f"wrote {args.out}: {s.messages:,} messages; route of {len(s.route)} nodes ({s.route_length_m:.1f} m), "
                f"{how} after {s.duration_s:.1f} s, {s.goal_distance_m:.2f} m from the goal node; {s.images} images, "
                f"{s.loop_closures} loop closures, {s.visual_corrections} visual corrections; cross-track error "
                f"(true position to the {'true' if s.scored_against == 'truth' else 'map (no ground truth in it)'} "
                f"path) mean {s.cross_track_mean_m:.3f} m, max {s.cross_track_max_m:.3f} m")
        _eprint(f"replay it with: {tool('slamreplay')} run {args.out} --pipeline topometric-nav --out RUN_DIR")
    return EXIT_OK


def cmd_diff(args: argparse.Namespace) -> int:
    from slamreplay.replay.runs.diff import diff_runs, format_table, parse_tolerances
    from slamreplay.replay.runs.diff_view import write_comparison_rrd

    diff = diff_runs(args.run_a, args.run_b, parse_tolerances(args.tolerance))
    if args.rrd:
        write_comparison_rrd(args.run_a, args.run_b, args.rrd, diff)
    if args.json:
        print(json.dumps(diff.to_json(), indent=2))
    else:
        print(format_table(diff))
        if args.rrd:
            print(f"comparison recording {args.rrd}: " + "\n".join(view_hint(args.rrd)))
    return EXIT_CHECK_FAILED if diff.worse else EXIT_OK


def cmd_trajectory(args: argparse.Namespace) -> int:
    from slamreplay.replay.runs.trajectory_eval import evaluate_run, export_kitti

    run_dir = Path(args.run)
    if args.kitti:
        for path in export_kitti(run_dir, Path(args.kitti)):
            _eprint(f"wrote {path}")
        if not args.json and not args.stats:
            return EXIT_OK
    report = evaluate_run(run_dir, args.align, args.delta, args.delta_unit)
    print(json.dumps(report.to_json(), indent=2) if args.json else report.table())
    return EXIT_OK


def cmd_snapshot(args: argparse.Namespace) -> int:
    from slamreplay.replay.tools.snapshot import parse_at, parse_size, snapshot

    shots = snapshot(Path(args.source), Path(args.out), size=parse_size(args.size), at=parse_at(args.at))
    for shot in shots:
        print(f"{shot.tab}: {shot.path}")
    return EXIT_OK


def cmd_demo(args: argparse.Namespace) -> int:
    from slamreplay.api.demo import run_demo

    return run_demo(Path(args.out), Path(args.data) if args.data else None, quiet=args.quiet)


def _auth_text(settings: Any) -> str:
    """What the server asks of its clients: people's tokens, the shared token, or nothing (api/auth.py)."""
    from slamreplay.api.store import Store

    users = Store(settings.db_path).users()
    if users:
        active = sum(u.active for u in users)
        ignored = "; SLAMREPLAY_TOKEN is not used" if settings.token else ""
        return f"people: {active} active of {len(users)}, each with their own token and role{ignored}"
    if settings.token:
        return "single user: one shared bearer token required"
    return "single user: no token (set SLAMREPLAY_TOKEN, or add people with `slamreplay users add`)"


def cmd_serve(args: argparse.Namespace) -> int:
    """Take the data directory's lock, then the port, and only then announce and build the app: a second
    server on a directory or a port in use exits 2 on one line without touching the first one's jobs."""
    from pydantic import ValidationError

    from slamreplay.api.datalock import DataDirInUseError, DataDirLock
    from slamreplay.api.listen import ListenError, listen, url_host
    from slamreplay.api.settings import Settings
    from slamreplay.api.siteguard import LOOPBACK_HOSTS, served_hosts

    try:
        settings = Settings.from_env(data_dir=args.data_dir, workers=args.workers, executor=args.executor,
                                     ray_address=args.ray_address, storage_url=args.storage_url,
                                     job_memory_mib=args.job_memory_mib, job_timeout_s=args.job_timeout_s,
                                     allowed_hosts=tuple(args.allowed_host) or None)
    except ValidationError as err:
        problems = "; ".join(f"{'.'.join(map(str, e['loc'])) or 'settings'}: {e['msg']}" for e in err.errors())
        raise CliError(f"invalid setting (from SLAMREPLAY_* or the options): {problems}") from None
    try:
        settings.make_dirs()
    except OSError as err:
        raise CliError(f"--data-dir {settings.data_dir}: cannot create it: {err.strerror or err}") from None
    settings = settings.model_copy(update={"allowed_hosts": served_hosts(settings.allowed_hosts, args.host)})
    lock = DataDirLock(settings.data_dir)
    try:
        lock.acquire()
        sock = listen(args.host, args.port)
    except (DataDirInUseError, ListenError) as err:
        lock.release()
        raise CliError(str(err)) from None
    except OSError as err:  # the lock file: a read-only data directory
        raise CliError(f"--data-dir {settings.data_dir}: cannot lock it: {err.strerror or err}") from None
    base = f"http://{url_host(args.host)}:{sock.getsockname()[1]}"
    lock.set_address(base)
    auth = _auth_text(settings)
    names = [h for h in settings.allowed_hosts if h not in LOOPBACK_HOSTS]
    hosts = "" if args.host == "127.0.0.1" else (
        f"; host names served: loopback, {', '.join(names)}" if names else
        "; host names served: loopback only (clients elsewhere need --allowed-host NAME)")
    _eprint(f"slamreplay serve: {base} over {settings.data_dir.resolve()} "
            f"({settings.workers} {settings.executor} worker(s), {auth}{hosts})")
    import uvicorn  # the service's stack, imported once the directory and the port are ours (a refusal is quick)

    from slamreplay.api.app import create_app
    from slamreplay.api.timeouts import server_config

    try:
        app = create_app(settings, lock=lock)
    except ImportError as err:  # --executor ray without the extra: the message has the install command
        raise CliError(str(err)) from None
    config = server_config(app, args.host, args.port, args.log_level, settings.header_timeout_s)  # api/timeouts.py
    uvicorn.Server(config).run(sockets=[sock])
    lock.release()
    return EXIT_OK


# ---------------------------------------------------------------------------------------


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

    rec = sub.add_parser("record", help="make a recording from a simulator or a public dataset")
    rsub = rec.add_subparsers(dest="source", required=True, metavar="SOURCE")
    if command in (None, "record"):
        _add_record_parsers(rsub, quiet)
        add_live_parser(rsub, quiet)  # record live: a stream, until stopped (api/live_cli.py)

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

    add_pipelines_parser(sub)

    run = sub.add_parser("run", parents=[quiet], help="replay a recording through a pipeline into a run directory",
                         description="Replay FILE through a pipeline. Writes RUN_DIR/run.rrd (open with `rerun`), "
                                     "metrics.json, manifest.json and log.txt.")
    run.add_argument("file", help="an .mcap recording or a ROS 2 bag directory")
    run.add_argument("--pipeline", required=True, help="pipeline name (see `slamreplay pipelines`)")
    run.add_argument("--out", required=True, metavar="RUN_DIR", help="run directory to create (must not exist)")
    run.add_argument("--seed", type=int, default=0, help="seed of every random generator (default: 0)")
    run.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="config value (repeatable)")
    run.add_argument("--config", metavar="FILE.json", help="config values from a JSON object (--set wins)")
    run.add_argument("--preset", metavar="NAME",
                     help="a pipeline's named set of config values, e.g. `paper`: the algorithm exactly as its paper "
                          "says (see `slamreplay pipelines`); --set and --config win over it")
    run.add_argument("--topic-map", action="append", default=[], metavar="FILE_TOPIC=TOPIC",
                     help="read FILE_TOPIC as a slamreplay topic, e.g. /robot/odom=/odom (repeatable)")
    run.add_argument("--robot", metavar="N", help="which robot of a multi-robot recording (topics under /robotN/, "
                                                  "e.g. `record mrclam --robot all`) to replay")
    run.add_argument("--start-ns", type=int, default=None, help="replay from this log time (inclusive)")
    run.add_argument("--end-ns", type=int, default=None, help="replay up to this log time (exclusive)")
    run.add_argument("--log-timings", action="store_true",
                     help="also log per-step wall-clock durations to run.rrd (timings/step_ms)")
    run.add_argument("--check-determinism", action="store_true",
                     help="external pipelines: run the program twice and record whether its outputs are identical "
                          "(docs/external.md; the same as --set check_determinism=true)")
    run.set_defaults(func=cmd_run)

    nv = sub.add_parser("navigate", parents=[quiet],
                        help="drive a topo-metric map's route in the simulator, closed loop, and record it",
                        formatter_class=argparse.RawDescriptionHelpFormatter,
                        description="Navigation mode of the topo-metric map (Battesti et al. 2011, section IV):\n"
                                    "Dijkstra from --start to --goal over the map's nodes, qualitative visual\n"
                                    "localization (the last loop closure's node, heading corrected from the image\n"
                                    "x-translation, odometry since), path following, with the sim-corridor world in\n"
                                    "the loop: the robot moves by the commands, the camera renders from the true\n"
                                    "pose, the wheel odometry drifts. Ground truth, odometry, images, localizations\n"
                                    "and commands go to --out, with the map's sha256, the seed and a fingerprint of\n"
                                    "the code, so a replay through the topometric-nav pipeline reproduces them.",
                        epilog="example:\n"
                               "  slamreplay record sim-corridor --route outer,left --camera-rate-hz 2.5 --seed 1 \\\n"
                               "      --out corridor.mcap\n"
                               "  slamreplay run corridor.mcap --pipeline topometric --out runs/map\n"
                               "  slamreplay navigate --map runs/map --world corridor.mcap --goal 38 --out nav.mcap\n"
                               "  slamreplay run nav.mcap --pipeline topometric-nav --out runs/nav\n"
                               "\n"
                               "Node indices are the map's: 0 is where mapping started, then in the order the\n"
                               "locations were created. The summary gives the true cross-track error; the\n"
                               "replay adds goal_reached, visual_corrections, loop_closure_rate and\n"
                               "replay_mismatches (0: reproduced). Exit 0 when the recording is written, 2 on bad\n"
                               "input (no map.npz, not a map, not a sim-corridor world, bad node, start == goal,\n"
                               "--out exists).")
    nv.add_argument("--map", required=True, metavar="RUN_DIR",
                    help="a `topometric` run directory (its map.npz) or a map file")
    nv.add_argument("--world", required=True,
                    help="a sim-corridor recording (its metadata names the world) or a world JSON file "
                         '{"config": {...}, "seed": N}')
    nv.add_argument("--goal", required=True, type=int, metavar="NODE",
                    help="goal: a location index of the map (0 .. number of nodes - 1), not --start")
    nv.add_argument("--start", type=int, default=0, metavar="NODE",
                    help="start location index; the robot starts at its pose (default: 0)")
    nv.add_argument("--out", required=True, metavar="FILE.mcap", help="the recording to write (must not exist)")
    nv.add_argument("--seed", type=int, default=0, help="seed of the odometry, RANSAC and image noise (default: 0)")
    nv.add_argument("--no-visual-correction", action="store_true",
                    help="drive on odometry only (loop closures are still detected and recorded): the paper's "
                         "Fig. 4 comparison")
    nv.add_argument("--through-walls", action="store_true",
                    help="keep driving through walls instead of stopping at the first contact")
    nv.add_argument("--preset", choices=["paper"],
                    help="paper: the paper's rules (reset the position to the matched node, an image every 0.5 m "
                         "or 10 degrees); the options below override it")
    nv.add_argument("--keep-along-m", type=float, metavar="M",
                    help="beyond the paper: keep the estimate's offset along the matched node's heading, clamped "
                         "to +-M (default 0: the paper's reset to the node)")
    nv.add_argument("--image-every-m", type=float, metavar="M", help="take an image every M metres (default 0.3)")
    nv.add_argument("--image-every-deg", type=float, metavar="DEG",
                    help="... or every DEG degrees of turn (default 10)")
    nv.set_defaults(func=cmd_navigate)

    df = sub.add_parser("diff", help="compare two runs: what changed, and which metrics got worse",
                        description="Compare RUN_B against RUN_A. Exit 0 when no metric got worse beyond its "
                                    "tolerance, 1 when one did, 2 on bad input.")
    df.add_argument("run_a", help="baseline run directory")
    df.add_argument("run_b", help="run directory to judge")
    df.add_argument("--tolerance", action="append", default=[], metavar="NAME=VALUE",
                    help="allowed worsening of a metric: absolute, or N%% of A's value; NAME * means every metric")
    df.add_argument("--rrd", metavar="OUT.rrd", help="write one recording with both runs under runs/A and runs/B")
    df.add_argument("--json", action="store_true", help="machine-readable output")
    df.set_defaults(func=cmd_diff)

    tr = sub.add_parser("trajectory", help="a run's absolute and relative pose error (evo's APE/RPE), KITTI export",
                        description="APE (absolute pose error) of RUN's trajectory.tum against its truth.tum with "
                                    "the chosen alignment, and RPE (relative pose error) over pose pairs DELTA steps "
                                    "or metres apart, defined as evo defines them (planar); --kitti writes both "
                                    "trajectories as KITTI pose files. Exit 2 when the run has no trajectory or no "
                                    "ground truth.")
    tr.add_argument("run", help="a finished run directory")
    tr.add_argument("--align", choices=["none", "origin", "se2"], default="none",
                    help="none: as estimated (runs start at the true pose; default); origin: first poses aligned "
                         "(evo --align_origin); se2: best rigid motion of the positions (evo --align)")
    tr.add_argument("--delta", type=float, default=1.0, help="RPE pair distance (default 1)")
    tr.add_argument("--delta-unit", choices=["step", "m"], default="step",
                    help="step: DELTA poses apart; m: at least DELTA metres of true path apart (default step)")
    tr.add_argument("--kitti", metavar="DIR", help="write estimate.kitti and truth.kitti (line for line) into DIR")
    tr.add_argument("--stats", action="store_true", help="with --kitti: print the errors too")
    tr.add_argument("--json", action="store_true", help="machine-readable output")
    tr.set_defaults(func=cmd_trajectory)

    snap = sub.add_parser("snapshot", help="render a run's tabs in the real Rerun viewer to PNG files (headless)",
                          description="Open a run (or a diff's .rrd) in a headless Rerun viewer and save one PNG per "
                                      "tab of its layout, with the time cursor at the end (or --at). Needs a Vulkan "
                                      "driver; without a GPU, Mesa's software one (Debian: mesa-vulkan-drivers).")
    snap.add_argument("source", metavar="RUN_DIR_OR_RRD", help="a run directory or an .rrd file")
    snap.add_argument("--out", required=True, metavar="DIR", help="folder for the PNG files (created if needed)")
    snap.add_argument("--size", default="1600x900", metavar="WxH", help="viewer size in pixels (default: 1600x900)")
    snap.add_argument("--at", default="end", metavar="end|start|STEP",
                      help="where the time cursor stands (default: end, the run's outcome)")
    snap.set_defaults(func=cmd_snapshot)

    demo = sub.add_parser("demo", parents=[quiet], help="record the built-in simulations, replay them, print metrics")
    demo.add_argument("--out", default="runs/demo", help="where recordings and runs go (default: runs/demo)")
    demo.add_argument("--data", default=None, help="public datasets folder; MRCLAM is replayed too when present")
    demo.set_defaults(func=cmd_demo)

    srv = sub.add_parser("serve", help="run the HTTP service: upload recordings, run jobs, fetch runs and diffs",
                         description="Serve the HTTP API (OpenAPI docs at /docs). Settings come from SLAMREPLAY_* "
                                     "environment variables (SLAMREPLAY_TOKEN, SLAMREPLAY_MAX_UPLOAD_BYTES ...); "
                                     "these options win over them.")
    srv.add_argument("--host", default="127.0.0.1", help="address to listen on (default: 127.0.0.1)")
    srv.add_argument("--port", type=int, default=8000, help="port (default: 8000)")
    srv.add_argument("--data-dir", default=None,
                     help="holds recordings/ and runs/ (default: SLAMREPLAY_DATA_DIR, else the current directory)")
    srv.add_argument("--workers", type=int, default=None,
                     help="jobs running at once, each in its own process (default: SLAMREPLAY_WORKERS, else 2)")
    srv.add_argument("--executor", choices=["local", "ray"], default=None,
                     help="where jobs run: local worker processes, or Ray tasks (the ray extra) "
                          "(default: SLAMREPLAY_EXECUTOR, else local)")
    srv.add_argument("--ray-address", default=None, metavar="ADDR",
                     help="Ray cluster to join, e.g. ray://head:10001 or auto (default: SLAMREPLAY_RAY_ADDRESS, "
                          "else a local Ray instance)")
    srv.add_argument("--storage-url", default=None, metavar="URL",
                     help="where workers read recordings and write runs, e.g. s3://bucket/slam or a shared "
                          "file:// path (default: SLAMREPLAY_STORAGE_URL, else the data directory)")
    srv.add_argument("--job-memory-mib", type=int, default=None, metavar="MIB",
                     help="memory limit of each job's process (default: SLAMREPLAY_JOB_MEMORY_MIB, else none)")
    srv.add_argument("--job-timeout-s", type=float, default=None, metavar="S",
                     help="wall-time limit of each job (default: SLAMREPLAY_JOB_TIMEOUT_S, else none)")
    srv.add_argument("--allowed-host", action="append", default=[], metavar="NAME",
                     help="a host name clients may reach the server by, besides 127.0.0.1, localhost, ::1 and --host "
                          "(repeatable; *.example.org for subdomains, * for any; default: "
                          "SLAMREPLAY_ALLOWED_HOSTS, comma-separated); requests naming another host are refused")
    srv.add_argument("--log-level", default="info", choices=["critical", "error", "warning", "info", "debug"],
                     help="uvicorn log level (default: info)")
    srv.set_defaults(func=cmd_serve)

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
        _eprint(f"slamreplay: error: {spell_commands(str(err))}")
        return EXIT_BAD_INPUT
    except KeyboardInterrupt:
        _eprint("slamreplay: interrupted")
        return 130
    except BrokenPipeError:  # `slamreplay ... | head`: the reader left; end quietly, as git does (128 + SIGPIPE)
        with contextlib.suppress(OSError):
            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())  # the exit's flush must not fail again
        return 141
    except Exception as err:  # noqa: BLE001 -- never a traceback to a user unless asked
        if args.debug:
            traceback.print_exc()
        _eprint(f"slamreplay: internal error: {type(err).__name__}: {err} (rerun with --debug for a traceback, "
                f"and please report it)")
        return 3


if __name__ == "__main__":
    sys.exit(main())
