"""SLSJF against EKF-SLAM (issue 29's figures): Victoria Park, MRCLAM Dataset 6 robots 1-5, the paper scenario.

For each recording both pipelines run with the recording's own sensor model and no setting; SLSJF also
linearized once (``--preset paper``) where ``--paper`` is given. Prints a table per data set with the
ratios SLSJF / EKF-SLAM (landmark RMSE, robot ATE) and writes ``--json``.

Run: ``.venv/bin/python benchmarks/slsjf_evaluation.py --out /tmp/slsjf-eval --data ../shared/data
[--seeds 1 2 3] [--duration-s 1800] [--robots 1 2 3 4 5] [--skip-vp] [--paper] [--json out.json]``.
Run directories under ``--out`` are reused when their metrics exist (a fresh ``--out`` after a code change).
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path
from typing import Any

import numpy as np

from slamreplay.recorder.importers.mrclam import import_mrclam
from slamreplay.recorder.sim import LandmarkSimConfig, simulate_landmarks
from slamreplay.replay.runs.run import run_recording

KEYS = ("landmarks_mapped", "landmark_rmse_m", "ape_rmse_m", "landmark_nees_mean", "robot_nees_mean")


def metrics(recording: Path, pipeline: str, out: Path, preset: str | None = None) -> dict[str, float]:
    if not (out / "metrics.json").exists():
        run_recording(recording, pipeline, out, seed=0, preset=preset)
    doc = json.loads((out / "metrics.json").read_text())["metrics"]
    return {k: float(v["value"]) for k, v in doc.items()}


def row(name: str, ekf: dict[str, float], sl: dict[str, float]) -> dict[str, Any]:
    ratio = {k: sl[k] / ekf[k] for k in ("landmark_rmse_m", "ape_rmse_m") if ekf.get(k)}
    print(f"  {name:<22} " + "  ".join(f"{k}={ekf.get(k, math.nan):.4g}/{sl.get(k, math.nan):.4g}" for k in KEYS)
          + "  ratios " + " ".join(f"{k}={v:.2f}" for k, v in ratio.items()))
    return {"name": name, "ekfslam": ekf, "slsjf": sl, "ratio": ratio}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--data", type=Path, default=Path(__file__).resolve().parents[2] / "shared" / "data")
    ap.add_argument("--seeds", type=int, nargs="*", default=list(range(1, 20)))
    ap.add_argument("--duration-s", type=float, default=1800.0)
    ap.add_argument("--robots", type=int, nargs="*", default=[1, 2, 3, 4, 5])
    ap.add_argument("--skip-vp", action="store_true")
    ap.add_argument("--paper", action="store_true", help="also SLSJF linearized once (--preset paper)")
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    out: dict[str, Any] = {"victoria_park": [], "mrclam": [], "sim": []}
    print("each cell: ekfslam/slsjf")
    vp = args.out / "victoria-park.mcap"
    if not args.skip_vp and vp.exists():  # `slamreplay record victoria-park DATA/victoria-park-isam --out` it first
        print("Victoria Park (against the batch optimum)")
        out["victoria_park"].append(row("victoria-park", metrics(vp, "ekfslam", args.out / "vp-ekfslam"),
                                        metrics(vp, "slsjf", args.out / "vp-slsjf")))
        if args.paper:
            out["victoria_park"].append(row("victoria-park paper", metrics(vp, "ekfslam", args.out / "vp-ekfslam"),
                                            metrics(vp, "slsjf", args.out / "vp-slsjf-paper", "paper")))
    mrclam = args.data / "mrclam-dataset6"
    if mrclam.is_dir() and args.robots:
        print("MRCLAM Dataset 6")
        for r in args.robots:
            rec = args.out / f"mrclam{r}.mcap"
            if not rec.exists():
                import_mrclam(mrclam, r, rec)
            out["mrclam"].append(row(f"robot {r}", metrics(rec, "ekfslam", args.out / f"mrclam{r}-ekfslam"),
                                     metrics(rec, "slsjf", args.out / f"mrclam{r}-slsjf")))
    if args.seeds:
        print(f"Paper scenario ({args.duration_s:g} s)")
        for s in args.seeds:
            rec = args.out / f"sim{s}.mcap"
            if not rec.exists():
                simulate_landmarks(rec, LandmarkSimConfig(duration_s=args.duration_s), seed=s)
            out["sim"].append(row(f"seed {s}", metrics(rec, "ekfslam", args.out / f"sim{s}-ekfslam"),
                                  metrics(rec, "slsjf", args.out / f"sim{s}-slsjf")))
        nees = [r["slsjf"]["landmark_nees_mean"] for r in out["sim"] if "landmark_nees_mean" in r["slsjf"]]
        if nees:
            out["sim_landmark_nees_mean_over_seeds"] = float(np.mean(nees))
            print(f"  SLSJF landmark NEES, mean over {len(nees)} seeds: {np.mean(nees):.3f}")
    if args.json:
        args.json.write_text(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
