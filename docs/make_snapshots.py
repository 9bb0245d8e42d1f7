"""Render the README's pictures: each demo pipeline's tabs and a diff, in the real (headless) Rerun viewer.

Run with `make snapshots` (installs Mesa's Vulkan driver if needed). It runs `slamreplay demo` into
``runs/snapshots-demo`` unless ``--demo DIR`` points at a finished demo, renders every tab of every
run with `slamreplay snapshot`, and keeps the chosen tabs under ``--out`` as PNGs of at most 300 KB.
"""

from __future__ import annotations

import argparse
import shutil
import sys
import tempfile
from pathlib import Path

import cv2
import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from slamreplay.api.demo import run_demo  # noqa: E402
from slamreplay.replay.runs.diff_view import write_comparison_rrd  # noqa: E402
from slamreplay.replay.tools.snapshot import snapshot  # noqa: E402

# (demo run directory, the tabs to keep, picture name)
PICTURES = (
    ("sim-landmarks--dslam", ("Summary", "Filter internals"), "dslam"),
    ("sim-landmarks--ekfslam", ("Filter internals",), "ekfslam"),
    ("sim-landmarks--odometry", ("Summary",), "odometry"),
    ("sim-seabed--ifmi", ("Summary", "Registration", "Pose graph"), "ifmi"),
    ("sim-corridor--topometric", ("Summary", "Loop closure"), "topometric"),
    ("sim-corridor-navigation--topometric-nav", ("Navigation",), "topometric-nav"),
)
MAX_BYTES = 300_000


def save_small(src: Path, dst: Path, width: int = 1280) -> int:
    """Write ``src`` as a PNG of at most MAX_BYTES (scaled down until it fits); its size in bytes."""
    img = cv2.imread(str(src))
    while True:
        scale = width / img.shape[1]
        small = cv2.resize(img, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA) if scale < 1 else img
        ok, data = cv2.imencode(".png", small, [cv2.IMWRITE_PNG_COMPRESSION, 9])
        if not ok:
            raise RuntimeError(f"could not encode {src}")
        if len(data) <= MAX_BYTES or width <= 480:
            dst.write_bytes(np.asarray(data).tobytes())
            return len(data)
        width = int(width * 0.85)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=REPO / "docs" / "images")
    ap.add_argument("--demo", type=Path, default=None, help="a finished `slamreplay demo` folder to reuse")
    ap.add_argument("--size", default="1600x900", help="viewer size (default: 1600x900)")
    args = ap.parse_args(argv)
    demo = args.demo
    if demo is None:
        demo = REPO / "runs" / "snapshots-demo"
        if run_demo(demo, None) != 0:
            return 1
    w, h = (int(v) for v in args.size.split("x"))
    args.out.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory() as tmp:
        for run, keep, name in PICTURES:
            shots = snapshot(demo / run, Path(tmp) / name, size=(w, h))
            for shot in shots:
                if shot.tab in keep:
                    dst = args.out / f"{name}-{shot.tab.lower().replace(' ', '-')}.png"
                    print(f"{dst.relative_to(REPO) if dst.is_relative_to(REPO) else dst}: "
                          f"{save_small(shot.path, dst) / 1000:.0f} kB")
        cmp = Path(tmp) / "diff.rrd"
        write_comparison_rrd(demo / "sim-landmarks--dslam", demo / "sim-landmarks--ekfslam", cmp)
        for shot in snapshot(cmp, Path(tmp) / "diff", size=(w, h)):
            if shot.tab in ("Summary", "Metrics A vs B"):
                dst = args.out / f"diff-{shot.tab.lower().replace(' ', '-')}.png"
                print(f"{dst}: {save_small(shot.path, dst) / 1000:.0f} kB")
    if args.demo is None:
        shutil.rmtree(demo, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
