"""Loop-closure detection time per 320x240 image, split into features, BoW, filter, validation.

Runs :class:`slamreplay.algorithms.topometric.TopoMetricMapper` single-threaded (``cv2.setNumThreads(1)``,
BLAS threads 1) over a seeded sim-corridor route (``--route``, default the simulator's default
tours) or over the RTAB-Map loop samples (``--rtabmap DIR``: 84 images resized to 320x240, no
odometry), and prints per-stage mean / median / p95 process-CPU time (wall time on a shared machine
mostly measures the other jobs) per taken
image, against the paper's 0.016-0.019 s (Battesti, Bazeille, Filliat, ECMR 2011, Table I, Xeon 3 GHz).
The stage split uses the mapper's injected clock; "total" includes the relaxation at loop closures.

    .venv/bin/python benchmarks/loop_closure.py [--seed 1] [--route rooms,left,right-cw]
    .venv/bin/python benchmarks/loop_closure.py --rtabmap ../shared/data/rtabmap-loop-samples
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402
from bench_io import write_json  # noqa: E402

from slamreplay.algorithms.topometric import MapperConfig, StepStatus, TopoMetricMapper  # noqa: E402

STAGES = ("features", "bow", "filter", "validation", "relaxation")
PAPER_S = 0.016


def corridor_frames(seed: int, route: str) -> list[tuple[np.ndarray, np.ndarray]]:
    from slamreplay.recorder.messages import CameraImage, OdometryPose
    from slamreplay.recorder.sim.corridor import CorridorConfig, simulate_corridor
    from slamreplay.replay.engine.reader import RecordingReader

    kwargs = {"route": route} if route else {}
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "corridor.mcap"
        simulate_corridor(path, CorridorConfig(**kwargs), seed=seed)
        frames, odom = [], None
        for env in RecordingReader(path).messages(["/camera/image", "/odom"]):
            if isinstance(env.msg, OdometryPose):
                odom = env.msg.xy_yaw
            elif isinstance(env.msg, CameraImage) and odom is not None:
                frames.append((np.asarray(env.msg.pixels), odom))
    return frames


def rtabmap_frames(root: Path) -> list[tuple[np.ndarray, None]]:
    out = []
    for f in range(1, 85):
        img = cv2.imread(str(root / "images" / f"{f}.jpg"), cv2.IMREAD_GRAYSCALE)
        out.append((cv2.resize(img, (320, 240), interpolation=cv2.INTER_AREA), None))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--route", default="")
    ap.add_argument("--rtabmap", type=Path, default=None)
    ap.add_argument("--json", type=Path, metavar="PATH", help="also write the figures as JSON to PATH")
    args = ap.parse_args()
    if args.rtabmap is not None and not (args.rtabmap / "images").is_dir():
        ap.error(f"--rtabmap {args.rtabmap} has no images/ folder (the RTAB-Map loop samples)")
    cv2.setNumThreads(1)
    frames = rtabmap_frames(args.rtabmap) if args.rtabmap else corridor_frames(args.seed, args.route)
    mapper = TopoMetricMapper(MapperConfig(), np.random.default_rng(0), clock=time.process_time)
    wall: dict[str, list[float]] = {k: [] for k in (*STAGES, "total")}
    cpu: list[float] = []
    loops = 0
    for img, odom in frames:
        c0 = time.process_time()
        s = mapper.step(img, odom)
        if s.status is StepStatus.SKIPPED:
            continue
        cpu.append(time.process_time() - c0)
        loops += s.status is StepStatus.LOOP_CLOSURE
        for k in STAGES:
            wall[k].append(s.durations_s.get(k, 0.0))
        wall["total"].append(sum(s.durations_s.values()))
    n = len(wall["total"])
    print(f"{n} images taken, {mapper.n_locations} locations, {loops} loop closures, "
          f"{mapper.vocabulary.n_words} words")
    print(f"{'stage':<12}{'mean ms':>10}{'median ms':>11}{'p95 ms':>9}")
    for k, v in wall.items():
        a = 1e3 * np.asarray(v)
        print(f"{k:<12}{a.mean():>10.2f}{np.median(a):>11.2f}{np.percentile(a, 95):>9.2f}")
    print(f"{'cpu total':<12}{1e3 * np.mean(cpu):>10.2f}{1e3 * np.median(cpu):>11.2f}"
          f"{1e3 * np.percentile(cpu, 95):>9.2f}")
    print(f"paper (Table I): {1e3 * PAPER_S:.0f}-19 ms per image; ours/paper (mean CPU) "
          f"{np.mean(cpu) / PAPER_S:.2f}")
    if args.json:
        write_json(args.json, {
            "benchmark": "loop_closure", "source": "rtabmap" if args.rtabmap else f"sim-corridor seed {args.seed}",
            "clock": "process CPU time", "images": n, "locations": mapper.n_locations, "loop_closures": loops,
            "words": mapper.vocabulary.n_words, "ms_per_image": 1e3 * float(np.mean(cpu)),
            "ms_per_image_median": 1e3 * float(np.median(cpu)), "paper_ms": 1e3 * PAPER_S,
            "over_paper": float(np.mean(cpu)) / PAPER_S,
            "stages_ms": {k: 1e3 * float(np.mean(v)) for k, v in wall.items()}})


if __name__ == "__main__":
    main()
