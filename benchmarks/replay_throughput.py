"""Replay throughput: slamreplay's reader and engine against the raw `mcap` reader, in one run.

Measures, on one synthetic recording (poses at 100 Hz and range-bearing scans at 10 Hz):
1. the raw `mcap` reader decoding every message with `mcap_protobuf` (the floor),
2. slamreplay's ordered reader (decode + validation into message dataclasses),
3. the engine with a no-op pipeline (reader + per-message time setting + dispatch),
4. the odometry pipeline with a null observer and with the Rerun observer writing a `.rrd`:
   the difference is the cost of Rerun logging per message.

Run: `.venv/bin/python benchmarks/replay_throughput.py [--poses N] [--repeat R] [--quick] [--json PATH]`.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from bench_io import write_json
from mcap.reader import make_reader
from mcap_protobuf.decoder import DecoderFactory

from slamreplay.algorithms.observe import Observation
from slamreplay.recorder import GroundTruthPose, OdometryPose, RangeBearingScan, Recorder
from slamreplay.replay.engine.loop import replay
from slamreplay.replay.engine.observer import RerunObserver
from slamreplay.replay.engine.pipeline import MetricSpec, Pipeline, get_pipeline, resolve_config
from slamreplay.replay.engine.reader import Envelope, RecordingReader


def make_recording(path: Path, n_poses: int) -> int:
    """Odometry + ground truth at 100 Hz and a 5-landmark scan every 10th step; returns the message count."""
    rng = np.random.default_rng(0)
    count = 0
    with Recorder(path, source={"benchmark": "replay_throughput"}) as rec:
        for k in range(n_poses):
            t = 1_000_000_000 + k * 10_000_000
            x = rng.normal(size=3)
            rec.write("/ground_truth/pose", GroundTruthPose(t, *x))
            rec.write("/odom", OdometryPose(t, *(x + 0.01)))
            count += 2
            if k % 10 == 0:
                rec.write("/landmarks/range_bearing", RangeBearingScan(t, rng.uniform(0, 5, 5),
                                                                       rng.uniform(-1.5, 1.5, 5), np.arange(5)))
                count += 1
    return count


@dataclass(frozen=True, slots=True)
class NoOpConfig:
    """No parameters."""


class NoOp(Pipeline):
    """Reads every topic, does nothing."""

    name = "noop"
    summary = "benchmark: does nothing"
    required_topics = ("/odom",)
    optional_topics = ("/ground_truth/pose", "/landmarks/range_bearing")
    start_topic = "/odom"
    Config = NoOpConfig
    metrics: dict[str, MetricSpec] = {}

    def step(self, env: Envelope) -> None:
        return None

    def finish(self) -> dict[str, float]:
        return {}


class NullObserver:
    """Discards everything (the engine still sets the time)."""

    step, sensor_time_ns = 0, 0

    def set_time(self, step: int, sensor_time_ns: int) -> None:
        self.step, self.sensor_time_ns = step, sensor_time_ns

    def log(self, path: str, item: Observation) -> None: ...
    def log_static(self, path: str, item: Observation) -> None: ...
    def send_series(self, *args: object) -> None: ...


def interleaved(repeat: int, fns: list[Callable[[], int]]) -> list[tuple[float, int]]:
    """Least CPU time of each ``fn`` over ``repeat`` rounds, and the count it returned.

    CPU time of the process (all its threads: Rerun's encoder and file writer included), not wall
    time: on a machine shared with other jobs, wall time mostly measures their load. Each round
    runs every function once, in turn, so that a burst of load hits all of them alike.
    """
    best = [float("inf")] * len(fns)
    counts = [0] * len(fns)
    for _ in range(repeat):
        for i, fn in enumerate(fns):
            tic = time.process_time()
            counts[i] = fn()
            best[i] = min(best[i], time.process_time() - tic)
    return list(zip(best, counts, strict=True))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--poses", type=int, default=20000, help="pose samples (3 messages per 10 poses more)")
    parser.add_argument("--repeat", type=int, default=5, help="rounds; each runs every variant once")
    parser.add_argument("--quick", action="store_true", help="5000 poses, 3 rounds")
    parser.add_argument("--json", type=Path, metavar="PATH", help="also write the figures as JSON to PATH")
    args = parser.parse_args()
    if args.poses < 10 or args.repeat < 1:
        parser.error("--poses must be >= 10 and --repeat >= 1")
    if args.quick:
        args.poses, args.repeat = 5000, 3
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "bench.mcap"
        total = make_recording(path, args.poses)
        rrd_sizes: list[int] = []

        def raw_mcap() -> int:
            with open(path, "rb") as f:
                reader = make_reader(f, decoder_factories=[DecoderFactory()])
                return sum(1 for _ in reader.iter_decoded_messages(log_time_order=True))

        def our_reader() -> int:
            return sum(1 for _ in RecordingReader(path).messages())

        def engine(pipeline: type[Pipeline], observer_factory: Callable[[int], object]) -> Callable[[], int]:
            counter = iter(range(10**6))

            def run() -> int:
                i = next(counter)
                obs = observer_factory(i)
                stats = replay(RecordingReader(path), pipeline, resolve_config(pipeline), obs,  # type: ignore[arg-type]
                               seed=0, log=lambda s: None)
                if isinstance(obs, RerunObserver):
                    obs.close()
                    rrd = Path(tmp) / f"r{i}.rrd"
                    rrd_sizes.append(rrd.stat().st_size)
                    rrd.unlink()
                return stats.messages
            return run

        odometry = get_pipeline("odometry")
        names = ["raw mcap reader + mcap_protobuf decode", "slamreplay RecordingReader (decode + validate)",
                 "engine, no-op pipeline", "engine, odometry pipeline, null observer",
                 "engine, odometry pipeline, Rerun .rrd"]
        results = interleaved(args.repeat, [
            raw_mcap, our_reader, engine(NoOp, lambda i: NullObserver()),
            engine(odometry, lambda i: NullObserver()),
            engine(odometry, lambda i: RerunObserver(Path(tmp) / f"r{i}.rrd", f"bench{i}"))])
    rows = [(name, t, n) for name, (t, n) in zip(names, results, strict=True)]
    print(f"recording: {total} messages ({args.poses} poses), best of {args.repeat} interleaved rounds")
    base = rows[0][1]
    print(f"{'what':<50} {'messages':>9} {'CPU s':>8} {'msg/s':>10} {'time / raw':>11}")
    for name, t, n in rows:
        print(f"{name:<50} {n:>9} {t:>8.3f} {n / t:>10.0f} {t / base:>11.2f}")
    odo_messages = rows[3][2]
    per_msg_us = (rows[4][1] - rows[3][1]) / odo_messages * 1e6
    print(f"Rerun logging cost: {per_msg_us:.1f} us per replayed message "
          f"(odometry logs a pose and a trajectory tail per /odom and per /ground_truth/pose message); "
          f".rrd {rrd_sizes[0] / 1e6:.2f} MB")
    if args.json:
        figures = {
            "benchmark": "replay_throughput", "messages": total, "poses": args.poses, "repeat": args.repeat,
            "raw_s": base, "reader_s": rows[1][1], "noop_s": rows[2][1], "odometry_null_s": rows[3][1],
            "rrd_s": rows[4][1],
            "reader_over_raw": rows[1][1] / base, "noop_over_raw": rows[2][1] / base,
            "odometry_null_over_raw": rows[3][1] / base, "rrd_over_raw": rows[4][1] / base,
            "rerun_us_per_message": per_msg_us, "rrd_bytes": rrd_sizes[0],
        }
        write_json(args.json, figures)


if __name__ == "__main__":
    main()
