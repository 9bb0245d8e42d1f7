"""Sources of recordings, simulators and importers alike: the ``Importer`` protocol and the built-in ones.

``slamreplay record NAME`` has one sub-command per importer found in the entry-point group
``slamreplay.importers`` (:mod:`slamreplay.recorder.plugins`); the built-ins below are declared there in
slamreplay's pyproject.toml, the same way as a user's. An importer declares its command-line
arguments (``add_arguments``) and writes one recording from their values (``record``); the
heavy modules it needs are imported only when it records: ``add_arguments`` reads the simulators'
config dataclasses from their light ``*_config`` modules, so that ``--help`` starts fast.
"""

from __future__ import annotations

import argparse
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any, Protocol, runtime_checkable

from slamreplay.recorder.errors import RecorderError
from slamreplay.recorder.options import add_dataclass_options, dataclass_from_options, parse_pairs, seed_value
from slamreplay.recorder.plugins import Plugin, discover

IMPORTER_GROUP = "slamreplay.importers"
Progress = Callable[[int, int], None]
OUT_HELP = "the .mcap file to write (must not exist)"


@runtime_checkable
class Importer(Protocol):
    """A source of recordings, found through the entry-point group ``slamreplay.importers``.

    The entry point names a class whose instances (made with no arguments) have:

    - ``name``: the sub-command, equal to the entry point's name (``record NAME``);
    - ``help`` (one line for ``record --help``) and ``description`` (for ``record NAME --help``);
    - ``progress_label``: what the progress bar says while it runs;
    - ``add_arguments(parser)``: its arguments, ``--out`` among them;
    - ``record(options, progress, log) -> str``: write the recording from the parsed ``options``
      (argument dest -> value), calling ``progress(done, total)`` now and then and ``log(text)`` for
      a note to the user; it returns the one-line summary printed after ``wrote FILE:``. Bad input
      raises ``RecorderError`` (one line for the user, exit 2); nothing that looks whole is left behind.

    Optional: ``service = True`` offers it over HTTP too (``POST /recordings/record/NAME``,
    api/service/record_routes.py): only an importer that needs no input from the machine it runs on (no positional
    argument) may say so, and ``file_options`` lists the dests of its options that name a file or folder there
    (the service refuses them).
    """

    name: str
    help: str
    description: str
    progress_label: str

    def add_arguments(self, parser: argparse.ArgumentParser) -> None: ...

    def record(self, options: Mapping[str, Any], progress: Progress, log: Callable[[str], None]) -> str: ...


def _check_importer(name: str, obj: Any) -> str | None:
    """What is wrong with an entry point's object as an importer (None: nothing)."""
    if not isinstance(obj, type):
        return f"is not an importer class (it is {type(obj).__name__} {getattr(obj, '__name__', obj)!r})"
    try:
        instance = obj()
    except Exception as err:  # noqa: BLE001 -- a plugin's constructor is reported, never fatal
        return f"cannot be constructed with no arguments: {type(err).__name__}: {err}"
    if not isinstance(instance, Importer):
        missing = [a for a in ("name", "help", "description", "progress_label", "add_arguments", "record")
                   if not hasattr(instance, a)]
        return f"does not implement the Importer protocol (missing {', '.join(missing)})"
    if instance.name != name:
        return f"is registered as {name!r} but its class says name = {instance.name!r}: make the two agree"
    return None


def importer_plugins() -> dict[str, Plugin]:
    """Every importer entry point, built-in or a user's, working or broken (loaded on first use)."""
    return discover(IMPORTER_GROUP, _check_importer)


def get_importer(name: str) -> Importer:
    """An instance of importer ``name``; RecorderError naming the known ones, or why a plugin is broken."""
    plugins = importer_plugins()
    if name not in plugins:
        raise RecorderError(f"unknown importer {name!r}; known: {', '.join(plugins) or '(none)'}")
    instance: Importer = plugins[name].load()()
    return instance


# ---------------------------------------------------------------------------------------
# Helpers for importers whose options are a config dataclass


def _out_and_seed(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out", required=True, help=OUT_HELP)
    parser.add_argument("--seed", type=seed_value, default=0,
                        help="seed of the simulation's random generator: the same seed and options make the same "
                             "recording (default: 0)")


# ---------------------------------------------------------------------------------------
# Simulators


class SimLandmarks:
    name = "sim-landmarks"
    service = True
    help = "D-SLAM paper scenario: point landmarks, range-bearing sensor, odometry"
    description = ("Simulate a robot among point landmarks (default: the D-SLAM paper's section 4.2 scenario) and "
                   "record odometry, scans and ground truth.")
    progress_label = "simulating"

    def add_arguments(self, parser: argparse.ArgumentParser) -> None:
        from slamreplay.recorder.sim.landmarks_config import LandmarkSimConfig

        _out_and_seed(parser)
        add_dataclass_options(parser, LandmarkSimConfig)

    def record(self, options: Mapping[str, Any], progress: Progress, log: Callable[[str], None]) -> str:
        from slamreplay.recorder.sim.landmarks import LandmarkSimConfig, simulate_landmarks

        config = dataclass_from_options(options, LandmarkSimConfig)
        s = simulate_landmarks(Path(options["out"]), config, seed=options["seed"], progress=progress)
        return (f"{s.messages:,} messages, {s.poses:,} poses, {s.scans:,} scans ({s.observations:,} observations), "
                f"{s.landmarks_observed}/{s.landmarks} landmarks seen, {s.path_length_m:.1f} m driven in a "
                f"{s.area_m:g} m square")


class SimSeabed:
    name = "sim-seabed"
    service = True
    file_options = ("cfg_texture",)
    help = "downward camera over a seabed texture: lawn-mower survey with revisits"
    description = ("Simulate a downward camera flying a lawn-mower survey over a seabed texture (procedural, an image "
                   "file, or a folder of frames given with --texture) and record images, odometry and ground truth.")
    progress_label = "simulating"

    def add_arguments(self, parser: argparse.ArgumentParser) -> None:
        from slamreplay.recorder.sim.seabed_config import SeabedSimConfig

        _out_and_seed(parser)
        add_dataclass_options(parser, SeabedSimConfig)

    def record(self, options: Mapping[str, Any], progress: Progress, log: Callable[[str], None]) -> str:
        from slamreplay.recorder.sim.seabed import SeabedSimConfig, simulate_seabed

        config = dataclass_from_options(options, SeabedSimConfig)
        s = simulate_seabed(Path(options["out"]), config, seed=options["seed"], progress=progress)
        return (f"{s.messages:,} messages, {s.images} images over a {s.texture_px[0]}x{s.texture_px[1]} px seabed, "
                f"{s.path_length_m:.1f} m surveyed")


class SimCorridor:
    name = "sim-corridor"
    service = True
    file_options = ("cfg_texture",)
    help = "forward camera driven round an indoor floor plan with loops: images, odometry"
    description = ("Simulate a wheeled robot teleoperated round corridors and rooms whose walls carry photo textures, "
                   "and record forward-camera images, drifting wheel odometry and ground truth.")
    progress_label = "simulating"

    def add_arguments(self, parser: argparse.ArgumentParser) -> None:
        from slamreplay.recorder.sim.corridor_config import CorridorConfig

        _out_and_seed(parser)
        add_dataclass_options(parser, CorridorConfig)

    def record(self, options: Mapping[str, Any], progress: Progress, log: Callable[[str], None]) -> str:
        from slamreplay.recorder.sim.corridor import CorridorConfig, simulate_corridor

        config = dataclass_from_options(options, CorridorConfig)
        s = simulate_corridor(Path(options["out"]), config, seed=options["seed"], progress=progress)
        return (f"{s.messages:,} messages, {s.images:,} images, {s.poses:,} poses, {s.path_length_m:.1f} m driven in "
                f"{s.duration_s:.0f} s, odometry off by {s.odom_final_error_m:.2f} m at the end")


class SimRos2Bag:
    name = "sim-ros2-bag"
    help = "a small ROS 2 bag (not a recording): odometry, tf, IMU, laser scans of poles, camera; to try `record ros2`"
    description = ("Write a small ROS 2 bag folder, as `ros2 bag record` would: a robot circling among poles with "
                   "drifting /odom, /tf (map -> odom -> base_link), /tf_static, /imu, /scan, camera images and "
                   "calibration. `slamreplay inspect BAG` and `slamreplay record ros2 BAG` then work as on a bag of "
                   "your own.")
    progress_label = "writing"

    def add_arguments(self, parser: argparse.ArgumentParser) -> None:
        parser.add_argument("--out", required=True, help="the bag folder to write (must not exist)")
        parser.add_argument("--seed", type=seed_value, default=0,
                            help="seed of the simulation's random generator (pole positions, noise) (default: 0)")
        parser.add_argument("--storage", choices=("sqlite3", "mcap"), default="sqlite3",
                            help="the bag's storage plugin: sqlite3 (.db3, ROS 2's default before Jazzy) or mcap "
                                 "(default: sqlite3)")
        parser.add_argument("--duration-s", type=float, default=20.0,
                            help="seconds of driving: a 10 m circle takes 52 s at 1.2 m/s (default: 20)")

    def record(self, options: Mapping[str, Any], progress: Progress, log: Callable[[str], None]) -> str:
        import shutil

        from slamreplay.recorder.sim.ros2bag import write_bag

        out = Path(options["out"])
        if out.exists():
            raise RecorderError(f"--out {out} exists: give a new folder (a bag is never overwritten)")
        if not options["duration_s"] > 0.2:
            raise RecorderError(f"--duration-s must be > 0.2 s (two odometry messages), got {options['duration_s']}")
        # written inside a hidden sibling folder under its own name (rosbags names the storage file after the
        # folder), then moved into place: the bag appears whole or not at all
        staging = out.with_name(f".{out.name}.partial")
        shutil.rmtree(staging, ignore_errors=True)  # left by an interrupted earlier attempt
        staging.mkdir(parents=True)
        try:
            truth = write_bag(staging / out.name, options["storage"], seed=options["seed"],
                              seconds=options["duration_s"])
            (staging / out.name).rename(out)
        finally:
            shutil.rmtree(staging, ignore_errors=True)
        return (f"a {options['storage']} bag of {len(truth.stamps_ns):,} odometry messages and "
                f"{len(truth.scan_stamps_ns):,} scans among {len(truth.poles)} poles")


# ---------------------------------------------------------------------------------------
# Importers


class Images:
    name = "images"
    help = "import a folder of frames (no navigation)"
    description = (
        "Record the images of DIR, ordered by the frame counter in their names, as /camera/image (mono8, PNG).")
    progress_label = "importing images"

    def add_arguments(self, parser: argparse.ArgumentParser) -> None:
        parser.add_argument("dir", help="the folder holding the frames")
        parser.add_argument("--out", required=True, help=OUT_HELP)
        parser.add_argument("--rate-hz", type=float, default=1.0, help="frame rate that sets the stamps (default: 1)")

    def record(self, options: Mapping[str, Any], progress: Progress, log: Callable[[str], None]) -> str:
        from slamreplay.recorder.importers.images import import_images

        s = import_images(Path(options["dir"]), Path(options["out"]), rate_hz=options["rate_hz"], progress=progress)
        return f"{s.images} images of {s.width_px}x{s.height_px} ({s.first} .. {s.last})"


def _mrclam_robot(text: str) -> int | str:
    if text == "all":
        return text
    try:
        return int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected 1-5 or all, got {text!r}") from None


class Mrclam:
    name = "mrclam"
    help = "import one robot, or all five, of the UTIAS MRCLAM dataset"
    description = ("Import one robot (or all five) of an MRCLAM dataset folder: odometry integrated into poses, "
                   "landmark sightings as scans, Vicon ground truth, the landmark map, and each robot's sensor noise "
                   "measured against the ground truth.")
    progress_label = "importing MRCLAM"

    def add_arguments(self, parser: argparse.ArgumentParser) -> None:
        parser.add_argument("dir", help="the dataset folder (with Robot1_Odometry.dat ...)")
        parser.add_argument("--robot", type=_mrclam_robot, required=True,
                            help="robot number, 1-5, or `all`: the five robots in one recording, each under /robotN/")
        parser.add_argument("--out", required=True, help=OUT_HELP)

    def record(self, options: Mapping[str, Any], progress: Progress, log: Callable[[str], None]) -> str:
        from slamreplay.recorder.importers.mrclam import import_mrclam

        s = import_mrclam(Path(options["dir"]), options["robot"], Path(options["out"]), progress=progress)
        return (f"{s.messages:,} messages ({s.odometry_poses:,} odometry, {s.ground_truth_poses:,} ground truth, "
                f"{s.scans:,} scans with {s.measurements_kept:,} landmark sightings; {s.robot_sightings_dropped} robot "
                f"sightings and {s.unknown_barcodes_dropped} unknown barcodes dropped)")


class Ros2Bag:
    name = "ros2"
    help = "import a ROS 2 bag (sqlite3 or MCAP storage)"
    description = ("Import a ROS 2 bag read with rosbags: odometry, poses, /tf and /tf_static, IMU, LaserScan (poles "
                   "and trunks become landmarks), images and camera info. `slamreplay inspect BAG` shows what each "
                   "topic becomes.")
    progress_label = "importing ROS 2 bag"

    def add_arguments(self, parser: argparse.ArgumentParser) -> None:
        from slamreplay.recorder.importers.pole_config import PoleConfig

        parser.add_argument("bag", help="the bag folder, or its .db3 or .mcap file")
        parser.add_argument("--out", required=True, help=OUT_HELP)
        parser.add_argument("--topic-map", action="append", default=[], metavar="BAG_TOPIC=TOPIC",
                            help="read a bag topic as a logical topic, e.g. /gps/pose=/ground_truth/pose (repeatable)")
        parser.add_argument("--base-frame", default="base_link", help="the robot's tf frame (default: base_link)")
        parser.add_argument("--odom-frame", default="odom",
                            help="tf frame of odometry, used when the bag has no Odometry topic (default: odom)")
        parser.add_argument("--ground-truth-frame", default=None, metavar="FRAME",
                            help="record the base frame's pose in FRAME, composed through /tf, as ground truth "
                                 "(e.g. map)")
        parser.add_argument("--typestore", choices=("humble", "jazzy"), default="humble",
                            help="message definitions for bags that store none (default: humble)")
        add_dataclass_options(parser, PoleConfig, prefix="pole_", option_prefix="pole-",
                              help_prefix="pole extractor (recorder/importers/poles.py): ")

    def record(self, options: Mapping[str, Any], progress: Progress, log: Callable[[str], None]) -> str:
        from slamreplay.recorder.importers.pole_config import PoleConfig
        from slamreplay.recorder.importers.ros2bag import import_ros2_bag

        poles = dataclass_from_options(options, PoleConfig, prefix="pole_", what="pole extractor option")
        s = import_ros2_bag(Path(options["bag"]), Path(options["out"]), topic_map=parse_pairs(options["topic_map"]),
                            base_frame=options["base_frame"], odom_frame=options["odom_frame"],
                            ground_truth_frame=options["ground_truth_frame"], typestore=options["typestore"],
                            poles=poles, progress=progress)
        counts = ", ".join(f"{n:,} {t}" for t, n in sorted(s.counts.items()))
        skipped = [t.topic for t in s.plan.topics if t.maps_to is None]
        return (f"{s.messages:,} messages ({counts}); {s.poles:,} poles extracted"
                + (f"; skipped {', '.join(skipped)} (see `slamreplay inspect {options['bag']}`)" if skipped else ""))
