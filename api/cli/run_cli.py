"""``run``, ``navigate``, ``diff``, ``trajectory``, ``snapshot`` and ``demo``: a recording through a pipeline into a
run directory, and what looks at runs afterwards."""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

from slamreplay.api.cli.cli_parser import EXIT_CHECK_FAILED, EXIT_OK, CliError, eprint
from slamreplay.api.cli.hints import tool, view_hint
from slamreplay.api.cli.progress import progress_bar
from slamreplay.recorder.options import parse_pairs


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
        from slamreplay.api.cli.external_cli import determinism_config

        config.update(determinism_config(args.pipeline))
    with progress_bar(f"run {args.pipeline} on {Path(args.file).name}", args.quiet, unit="messages") as update:
        result = run_recording(args.file, args.pipeline, args.out, seed=args.seed, config=config,
                               topic_map=parse_pairs(args.topic_map),
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
        eprint(f"wrote {args.out}: {s.messages:,} messages; route of {len(s.route)} nodes ({s.route_length_m:.1f} m), "
                f"{how} after {s.duration_s:.1f} s, {s.goal_distance_m:.2f} m from the goal node; {s.images} images, "
                f"{s.loop_closures} loop closures, {s.visual_corrections} visual corrections; cross-track error "
                f"(true position to the {'true' if s.scored_against == 'truth' else 'map (no ground truth in it)'} "
                f"path) mean {s.cross_track_mean_m:.3f} m, max {s.cross_track_max_m:.3f} m")
        eprint(f"replay it with: {tool('slamreplay')} run {args.out} --pipeline topometric-nav --out RUN_DIR")
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
            eprint(f"wrote {path}")
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


def add_run_parsers(sub: Any, quiet: argparse.ArgumentParser) -> None:
    """``run``, ``navigate``, ``diff``, ``trajectory`` and ``snapshot``."""
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


def cmd_demo(args: argparse.Namespace) -> int:
    from slamreplay.api.cli.demo import run_demo

    return run_demo(Path(args.out), Path(args.data) if args.data else None, quiet=args.quiet)


def add_demo_parser(sub: Any, quiet: argparse.ArgumentParser) -> None:
    """``demo``."""
    demo = sub.add_parser("demo", parents=[quiet], help="record the built-in simulations, replay them, print metrics")
    demo.add_argument("--out", default="runs/demo", help="where recordings and runs go (default: runs/demo)")
    demo.add_argument("--data", default=None, help="public datasets folder; MRCLAM is replayed too when present")
    demo.set_defaults(func=cmd_demo)
