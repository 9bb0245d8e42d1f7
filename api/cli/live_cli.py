"""``slamreplay record live URL --out FILE.mcap``: record a robot's Foxglove WebSocket stream (recorder/importers/
foxglove_live.py).

A command of its own beside the importers' ``record NAME``, not an importer plugin: it has no total to show a bar
for and ends when told (Ctrl-C is its normal end, not an interruption), and on the service it is a task that is
started, listed while it grows and stopped (api/service/live_routes.py), not one request that returns a file.

Progress: on a terminal one status line redrawn every second (time, messages, rate per topic, bytes, connection);
elsewhere a plain line every ``SLAMREPLAY_PROGRESS_INTERVAL_S`` seconds (10). Connection losses, gaps, channels
that stop and channels skipped are lines of their own.
"""

from __future__ import annotations

import argparse
import json
import signal
import sys
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from slamreplay.api.cli.progress import duration, interval_s
from slamreplay.recorder.errors import RecorderError

HELP = "record a live robot from a Foxglove WebSocket stream (foxglove_bridge, the Foxglove SDK)"
DESCRIPTION = (
    "Connect to a Foxglove WebSocket server (foxglove_bridge on a ROS 1/2 robot, or any program using the Foxglove "
    "SDK; ws://HOST:8765 by default), subscribe to its channels and record them until --duration-s is over or Ctrl-C. "
    "Protobuf and JSON channels in Foxglove's and slamreplay's schemas are written as they come; ROS 2 CDR channels "
    "are converted as `record ros2` converts a bag; others are listed and skipped. The file is FILE.partial until "
    "the end (after a crash: `slamreplay recover FILE.partial --out FILE`); a dropped connection is retried and the "
    "gap written into the recording.")


def add_live_parser(rsub: Any, quiet: argparse.ArgumentParser) -> None:
    """``record live``: registered beside the importers' sub-commands."""
    from slamreplay.recorder.importers.pole_config import PoleConfig
    from slamreplay.recorder.options import add_dataclass_options

    p = rsub.add_parser("live", parents=[quiet], help=HELP, description=DESCRIPTION)
    p.add_argument("url", help="the server, e.g. ws://robot.local:8765")
    p.add_argument("--out", required=True, help="the .mcap file to write (must not exist; FILE.partial until the end)")
    p.add_argument("--topics", nargs="+", default=[], metavar="PATTERN",
                   help="channels to record: names, globs (/robot/*) or re:REGEX on the whole topic (default: every "
                        "channel slamreplay can read)")
    p.add_argument("--topic-map", action="append", default=[], metavar="CHANNEL=TOPIC",
                   help="record a channel as a logical topic, e.g. /robot/pose=/ground_truth/pose (repeatable)")
    p.add_argument("--duration-s", type=float, default=None,
                   help="seconds to record, from the first subscription (default: until Ctrl-C)")
    p.add_argument("--sensor-model", metavar="FILE.json", default=None,
                   help="the sensors' noise and limits the recording carries: a JSON object of sensor model keys "
                        "(range_sigma_m, bearing_sigma_rad, ...; see `slamreplay inspect` of a simulated recording)")
    p.add_argument("--base-frame", default="base_link",
                   help="the robot's tf frame: ROS 2 laser scans are moved into it through /tf_static, and /tf "
                        "gives its pose (default: base_link)")
    p.add_argument("--odom-frame", default="odom",
                   help="without an odometry channel, /odom is --base-frame in this frame, composed through /tf "
                        "(default: odom)")
    p.add_argument("--ground-truth-frame", default=None,
                   help="record /ground_truth/pose as --base-frame in this frame (e.g. map), composed through /tf "
                        "(default: none)")
    p.add_argument("--wait-s", type=float, default=5.0,
                   help="how long to wait for the server to advertise a channel to record (default: 5)")
    p.add_argument("--give-up-s", type=float, default=None,
                   help="end the recording when the server stays unreachable this long (default: retry until "
                        "stopped)")
    add_dataclass_options(p, PoleConfig, prefix="pole_", option_prefix="pole-",
                          help_prefix="pole extractor for ROS 2 laser scans (recorder/importers/poles.py): ")
    p.set_defaults(func=cmd_record_live)


def live_options(args: argparse.Namespace) -> Any:
    """The LiveOptions of the command line's arguments; RecorderError for a bad one."""
    from slamreplay.recorder.importers.foxglove_live import LiveOptions
    from slamreplay.recorder.importers.pole_config import PoleConfig
    from slamreplay.recorder.options import dataclass_from_options, parse_pairs
    from slamreplay.recorder.sensor_model import SensorModel

    if args.duration_s is not None and not args.duration_s > 0:
        raise RecorderError(f"--duration-s must be > 0, got {args.duration_s:g}")
    model = None
    if args.sensor_model is not None:
        try:
            data = json.loads(Path(args.sensor_model).read_text())
        except (OSError, ValueError) as err:
            raise RecorderError(f"--sensor-model {args.sensor_model}: {err}") from None
        if not isinstance(data, dict):
            raise RecorderError(f"--sensor-model {args.sensor_model}: expected a JSON object of sensor model keys")
        data.setdefault("source", f"given with --sensor-model {Path(args.sensor_model).name}")
        model = SensorModel.from_mapping(data)
    poles = dataclass_from_options(vars(args), PoleConfig, prefix="pole_", what="pole extractor option")
    return LiveOptions(url=args.url, out=Path(args.out), topics=tuple(args.topics),
                       topic_map=parse_pairs(args.topic_map), duration_s=args.duration_s, sensor_model=model,
                       base_frame=args.base_frame, odom_frame=args.odom_frame,
                       ground_truth_frame=args.ground_truth_frame, poles=poles, wait_s=args.wait_s,
                       give_up_s=args.give_up_s)


def _count(c: Any) -> str:
    """Messages written from a channel, or read from it when it writes none (/tf_static: the transform tree)."""
    return f"{c.written:,}" if c.written or c.maps_to != "transform tree" else f"{c.received:,} read"


def status_text(s: Any) -> str:
    """One line of a LiveStatus: time, messages, rate per topic, bytes, connection."""
    topics = ", ".join(f"{c.topic} {_count(c)}" + (" stopped" if c.stopped else f" {c.rate_hz:.1f} Hz")
                       for c in s.topics)
    state = "" if s.connected else ", reconnecting"
    gaps = f", {s.gaps} gap{'s' if s.gaps != 1 else ''}" if s.gaps else ""
    return (f"{duration(s.elapsed_s)}, {s.messages:,} messages, {s.bytes_on_disk / 1e6:.1f} MB{gaps}{state}"
            + (f" ({topics})" if topics else ""))


class _Printer:
    """Lines and status on stderr: a redrawn status line on a terminal, plain periodic lines elsewhere."""

    def __init__(self, url: str, quiet: bool) -> None:
        self.url, self.quiet = url, quiet
        self.tty = sys.stderr.isatty()
        self.every_s, self.last = interval_s(), time.monotonic()
        self.drawn = False
        self.lock = threading.RLock()  # the Ctrl-C handler says a line, maybe while the main thread prints one

    def say(self, line: str) -> None:
        if self.quiet:
            return
        with self.lock:
            if self.drawn:
                sys.stderr.write("\r\x1b[K")
                self.drawn = False
            print(line, file=sys.stderr, flush=True)

    def status(self, s: Any) -> None:
        if self.quiet:
            return
        with self.lock:
            if self.tty:
                sys.stderr.write("\r\x1b[K" + f"record live: {status_text(s)}"[:200])
                sys.stderr.flush()
                self.drawn = True
            elif time.monotonic() - self.last >= self.every_s:
                self.last = time.monotonic()
                print(f"record live {self.url}: {status_text(s)}", file=sys.stderr, flush=True)

    def end(self) -> None:
        if self.drawn:
            sys.stderr.write("\r\x1b[K")
            sys.stderr.flush()
            self.drawn = False


@contextmanager
def _stop_on_signals(stop: threading.Event, printer: _Printer) -> Iterator[None]:
    """Ctrl-C and SIGTERM end the recording cleanly; a second Ctrl-C interrupts at once."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def first(signum: int, frame: Any) -> None:
        printer.say("stopping: finishing the recording (Ctrl-C again to interrupt at once)")
        stop.set()
        signal.signal(signal.SIGINT, signal.default_int_handler)

    old_int, old_term = signal.signal(signal.SIGINT, first), signal.signal(signal.SIGTERM, first)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, old_int)
        signal.signal(signal.SIGTERM, old_term)


def cmd_record_live(args: argparse.Namespace) -> int:
    from slamreplay.recorder.importers.foxglove_live import record_live

    options = live_options(args)
    printer = _Printer(args.url, args.quiet)
    stop = threading.Event()
    with _stop_on_signals(stop, printer):
        try:
            s = record_live(options, say=printer.say, status=printer.status, stop=stop)
        finally:
            printer.end()
    if not args.quiet:
        counts = ", ".join(f"{_count(c)} {c.maps_to} from {c.topic}" + (f" ({c.bad} bad)" if c.bad else "")
                           for c in s.topics)
        gaps = (f"; {len(s.gaps)} gap{'s' if len(s.gaps) != 1 else ''} ({sum(g.duration_s for g in s.gaps):.1f} s "
                f"without data)") if s.gaps else ""
        stopped = f"; channels that stopped: {', '.join(s.stopped)}" if s.stopped else ""
        skipped = f"; skipped {', '.join(p.channel.topic for p in s.skipped)}" if s.skipped else ""
        printer.say(f"wrote {s.path}: {s.messages:,} messages in {duration(s.duration_s)} ({counts}){gaps}{stopped}"
                    f"{skipped}; {s.end_reason}")
    return 0
