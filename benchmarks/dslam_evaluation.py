"""D-SLAM against EKF-SLAM on the paper scenario and on MRCLAM: the figures the README tables quote.

1. Paper scenario (``sim-landmarks`` defaults: D-SLAM section 4.2, 1800 s), seeds 1-5: both
   pipelines in known-id mode, and D-SLAM and EKF-SLAM in unknown-id mode (the true ids stay in the
   recording for scoring only).
2. MRCLAM Dataset 6, robots 1-5 (imported with the platform's importer): both pipelines, known ids
   (barcodes), and the dead-reckoning baseline (``odometry`` pipeline).

Every run is a normal run directory under ``--out``; the script prints one table per part, reads
the association error rate from each unknown-id run's log, and writes ``summary.json``.

Run: ``.venv/bin/python benchmarks/dslam_evaluation.py --out /tmp/dslam-eval [--seeds 1 2 3 4 5]
[--associations known unknown] [--robots 1 2 3 4 5] [--duration-s 1800] [--skip-sim] [--skip-mrclam]
[--composite]``.
Each run directory is reused when its metrics exist (use a fresh ``--out`` after changing the code).
"""

from __future__ import annotations

import argparse
import json
import re
from pathlib import Path
from typing import Any

from slamreplay.recorder.importers.mrclam import import_mrclam
from slamreplay.recorder.messages import TOPIC_RANGE_BEARING
from slamreplay.recorder.sim import LandmarkSimConfig, simulate_landmarks
from slamreplay.replay.engine.reader import RecordingReader
from slamreplay.replay.runs.run import run_recording

DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "mrclam-dataset6"
KEYS = ("landmark_rmse_m", "landmark_nees_mean", "ape_rmse_m", "robot_nees_mean", "landmarks_mapped",
        "landmarks_true", "false_landmarks", "data_association_errors")


def run(recording: Path, pipeline: str, out: Path, config: dict[str, Any] | None = None) -> dict[str, Any]:
    """One run (reused when its metrics already exist); metrics, timings and the association rate."""
    if not (out / "metrics.json").exists():
        run_recording(recording, pipeline, out, seed=0, config=config)
    metrics = {k: v["value"] for k, v in json.loads((out / "metrics.json").read_text())["metrics"].items()}
    timings = json.loads((out / "manifest.json").read_text())["timings"]
    found = re.search(r"data association: (\d+) wrong of (\d+) checked", (out / "log.txt").read_text())
    if found:
        metrics["association_error_rate"] = int(found.group(1)) / max(1, int(found.group(2)))
    metrics["scan_step_mean_ms"] = 1e3 * timings.get("pipeline_scan_step_mean_s", float("nan"))
    return metrics


def observed(recording: Path) -> int:
    """Distinct landmark ids in the recording's scans (what any SLAM could map)."""
    ids: set[int] = set()
    for env in RecordingReader(recording).messages([TOPIC_RANGE_BEARING]):
        ids.update(env.msg.landmark_ids.tolist())  # type: ignore[union-attr]
    ids.discard(-1)
    return len(ids)


def fmt(value: Any) -> str:
    return f"{value:.4g}" if isinstance(value, float) else str(value)


def table(title: str, rows: list[tuple[str, dict[str, Any]]], keys: tuple[str, ...]) -> None:
    print(f"\n## {title}\n")
    print("| run | " + " | ".join(keys) + " |")
    print("|---" * (len(keys) + 1) + "|")
    for name, m in rows:
        print(f"| {name} | " + " | ".join(fmt(m.get(k, "-")) for k in keys) + " |")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--seeds", type=int, nargs="*", default=[1, 2, 3, 4, 5])
    parser.add_argument("--robots", type=int, nargs="*", default=[1, 2, 3, 4, 5])
    parser.add_argument("--duration-s", type=float, default=1800.0)
    parser.add_argument("--associations", nargs="*", choices=("known", "unknown"), default=["known", "unknown"],
                        help="association modes of the paper-scenario runs")
    parser.add_argument("--skip-sim", action="store_true")
    parser.add_argument("--composite", action="store_true",
                        help="MRCLAM: also run D-SLAM with composite scans (composite_max_scans 400)")
    parser.add_argument("--skip-mrclam", action="store_true")
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    summary: dict[str, Any] = {"sim": {}, "mrclam": {}}
    if not args.skip_sim:
        rows = []
        for assoc in args.associations:  # every seed in known-id mode first
            for seed, pipeline in ((s, p) for s in args.seeds for p in ("dslam", "ekfslam")):
                rec = args.out / f"sim-seed{seed}.mcap"
                if not rec.exists():
                    simulate_landmarks(rec, LandmarkSimConfig(duration_s=args.duration_s), seed=seed)
                name = f"seed{seed}-{pipeline}-{assoc}"
                m = run(rec, pipeline, args.out / name, {"association": assoc})
                m["landmarks_observed"] = observed(rec)
                rows.append((name, m))
                summary["sim"][name] = m
                table_row = " ".join(f"{k}={fmt(m.get(k, '-'))}" for k in (*KEYS, "landmarks_observed"))
                print(f"{name}: {table_row}", flush=True)
                (args.out / "summary.json").write_text(json.dumps(summary, indent=1, sort_keys=True))
        table("Paper scenario", rows, (*KEYS, "landmarks_observed", "association_error_rate", "scan_step_mean_ms"))
    if not args.skip_mrclam:
        rows = []
        for robot in args.robots:
            rec = args.out / f"mrclam-robot{robot}.mcap"
            if not rec.exists():
                import_mrclam(DATA, robot, rec)
            # default settings: the noise comes from the sensor model measured at import (`record mrclam`)
            runs = [("odometry", "odometry", None), ("dslam", "dslam", None), ("ekfslam", "ekfslam", None)]
            if args.composite:
                runs.append(("dslam-composite", "dslam", {"composite_max_scans": 400}))
            for label, pipeline, config in runs:
                name = f"robot{robot}-{label}"
                m = run(rec, pipeline, args.out / name, config)
                rows.append((name, m))
                summary["mrclam"][name] = m
                print(f"{name}: " + " ".join(f"{k}={fmt(m.get(k, '-'))}" for k in KEYS), flush=True)
        table("MRCLAM Dataset 6", rows, ("ape_rmse_m", "robot_final_error_m", *KEYS[:2], "robot_nees_mean",
                                         "landmarks_mapped", "scan_step_mean_ms"))
    (args.out / "summary.json").write_text(json.dumps(summary, indent=1, sort_keys=True))


if __name__ == "__main__":
    main()
