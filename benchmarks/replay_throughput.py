"""Replay throughput: slamreplay's reader and engine against the raw `mcap` reader, in one run.

Measures, on one synthetic recording (poses at 100 Hz and range-bearing scans at 10 Hz):
1. the raw `mcap` reader decoding every message with `mcap_protobuf` (the floor),
2. slamreplay's ordered reader (decode + validation into message dataclasses),
3. the engine with a no-op pipeline (reader + per-message time setting + dispatch),
4. the odometry pipeline with a null observer and with the Rerun observer writing a `.rrd`:
   the difference is the cost of Rerun logging per message.

Run: `.venv/bin/python benchmarks/replay_throughput.py [--messages N] [--repeat R]`.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from mcap.reader import make_reader
from mcap_protobuf.decoder import DecoderFactory

from algorithms.observe import Observation
from recorder import GroundTruthPose, OdometryPose, RangeBearingScan, Recorder
from replay.engine import replay
from replay.observer import RerunObserver
from replay.pipeline import MetricSpec, Pipeline, get_pipeline, resolve_config
from replay.reader import Envelope, RecordingReader


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


def best_of(repeat: int, fn: Callable[[], int]) -> tuple[float, int]:
    """Fastest wall time of ``repeat`` runs, and the count ``fn`` returned."""
    best, n = float("inf"), 0
    for _ in range(repeat):
        tic = time.perf_counter()
        n = fn()
        best = min(best, time.perf_counter() - tic)
    return best, n


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--poses", type=int, default=20000, help="pose samples (3 messages per 10 poses more)")
    parser.add_argument("--repeat", type=int, default=3)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "bench.mcap"
        total = make_recording(path, args.poses)

        def raw_mcap() -> int:
            with open(path, "rb") as f:
                reader = make_reader(f, decoder_factories=[DecoderFactory()])
                return sum(1 for _ in reader.iter_decoded_messages(log_time_order=True))

        def our_reader() -> int:
            return sum(1 for _ in RecordingReader(path).messages())

        def engine(pipeline: type[Pipeline], observer_factory: Callable[[int], object]) -> Callable[[], int]:
            counter = iter(range(10**6))

            def run() -> int:
                obs = observer_factory(next(counter))
                stats = replay(RecordingReader(path), pipeline, resolve_config(pipeline), obs,  # type: ignore[arg-type]
                               seed=0, log=lambda s: None)
                if isinstance(obs, RerunObserver):
                    obs.close()
                return stats.messages
            return run

        odometry = get_pipeline("odometry")
        rows = [
            ("raw mcap reader + mcap_protobuf decode", *best_of(args.repeat, raw_mcap)),
            ("slamreplay RecordingReader (decode + validate)", *best_of(args.repeat, our_reader)),
            ("engine, no-op pipeline", *best_of(args.repeat, engine(NoOp, lambda i: NullObserver()))),
            ("engine, odometry pipeline, null observer", *best_of(args.repeat, engine(odometry,
                                                                                       lambda i: NullObserver()))),
            ("engine, odometry pipeline, Rerun .rrd", *best_of(args.repeat, engine(
                odometry, lambda i: RerunObserver(Path(tmp) / f"r{i}.rrd", f"bench{i}")))),
        ]
    print(f"recording: {total} messages ({args.poses} poses), best of {args.repeat}")
    base = rows[0][1]
    print(f"{'what':<50} {'messages':>9} {'time s':>8} {'msg/s':>10} {'time / raw':>11}")
    for name, t, n in rows:
        print(f"{name:<50} {n:>9} {t:>8.3f} {n / t:>10.0f} {t / base:>11.2f}")
    odo_messages = rows[3][2]
    per_msg_us = (rows[4][1] - rows[3][1]) / odo_messages * 1e6
    print(f"Rerun logging cost: {per_msg_us:.1f} us per replayed message "
          f"(odometry logs a pose and a trajectory tail per /odom and per /ground_truth/pose message)")


if __name__ == "__main__":
    main()
