"""Cross-check of `slamreplay trajectory` against evo on the same files (figures, not speed).

For each run directory given (a finished run with ``trajectory.tum`` and ``truth.tum``), computes APE
(translation, each alignment; rotation) and RPE (per step; per metre of path) with slamreplay
(``slamreplay.replay.runs.trajectory_eval``) and with evo's own Python API on the same two TUM files (RPE pairs
as evo_rpe makes them: along the estimate's path), and prints both side by side with their ratio. evo is in
the dev extra (``tests/replay/test_evo_parity.py`` checks the same figures to 6 digits); another evo may be
used from another virtualenv with ``--evo-python``.

Run: ``.venv/bin/python benchmarks/evo_crosscheck.py RUN_DIR [RUN_DIR ...] [--json PATH]``
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path
from typing import Any

from slamreplay.replay.runs.trajectory_eval import evaluate_run

# (label, our alignment, delta, unit, evo's settings), evaluated by the snippet below in evo's interpreter
CASES: list[tuple[str, str, float, str]] = [
    ("ape_none", "none", 1, "step"),
    ("ape_origin", "origin", 1, "step"),
    ("ape_se2", "se2", 1, "step"),
    ("rpe_step", "none", 1, "step"),
    ("rpe_1m", "none", 1.0, "m"),
]

EVO = r"""
import copy, json, sys
from evo.core import metrics, sync
from evo.tools import file_interface
est_file, ref_file = sys.argv[1], sys.argv[2]
ref0 = file_interface.read_tum_trajectory_file(ref_file)
est0 = file_interface.read_tum_trajectory_file(est_file)
ref0, est0 = sync.associate_trajectories(ref0, est0, max_diff=1e-6)
out = {}
def stat(m):
    return m.get_statistic(metrics.StatisticsType.rmse)
for label, align in (("ape_none", None), ("ape_origin", "origin"), ("ape_se2", "se2")):
    ref, est = copy.deepcopy(ref0), copy.deepcopy(est0)
    if align == "origin":
        est.align_origin(ref)
    elif align == "se2":
        est.align(ref, correct_scale=False)
    t = metrics.APE(metrics.PoseRelation.translation_part); t.process_data((ref, est))
    r = metrics.APE(metrics.PoseRelation.rotation_angle_deg); r.process_data((ref, est))
    out[label] = [stat(t), stat(r)]
for label, delta, unit in (("rpe_step", 1, metrics.Unit.frames), ("rpe_1m", 1.0, metrics.Unit.meters)):
    t = metrics.RPE(metrics.PoseRelation.translation_part, delta, unit, all_pairs=False)
    r = metrics.RPE(metrics.PoseRelation.rotation_angle_deg, delta, unit, all_pairs=False)
    t.process_data((ref0, est0)); r.process_data((ref0, est0))
    out[label] = [stat(t), stat(r)]
print(json.dumps(out))
"""


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("runs", nargs="+", type=Path, help="finished run directories")
    parser.add_argument("--evo-python", default=sys.executable, help="a Python interpreter that imports evo")
    parser.add_argument("--json", type=Path, help="write the figures here")
    args = parser.parse_args()
    rows: list[dict[str, Any]] = []
    print(f"{'run':<28} {'figure':<22} {'slamreplay':>12} {'evo':>12} {'ratio':>10}")
    for run in args.runs:
        proc = subprocess.run([args.evo_python, "-c", EVO, str(run / "trajectory.tum"), str(run / "truth.tum")],
                              capture_output=True, text=True, check=False)
        if proc.returncode != 0:
            print(f"evo failed on {run}: {proc.stderr.strip().splitlines()[-1:]}", file=sys.stderr)
            return 2
        theirs = json.loads(proc.stdout)
        for label, alignment, delta, unit in CASES:
            rep = evaluate_run(run, alignment, delta, unit)  # type: ignore[arg-type]
            is_ape = label.startswith("ape")
            ours = ((rep.ape_trans if is_ape else rep.rpe_trans).rmse, (rep.ape_rot if is_ape else rep.rpe_rot).rmse)
            for k, (name, unit_name) in enumerate((("translation", "m"), ("rotation", "deg"))):
                row = {"run": str(run), "figure": f"{label} {name} rmse ({unit_name})", "slamreplay": ours[k],
                       "evo": theirs[label][k],
                       "ratio": ours[k] / theirs[label][k] if theirs[label][k] else float("nan")}
                rows.append(row)
                print(f"{run.name:<28} {row['figure'][:22]:<22} {ours[k]:>12.6g} {theirs[label][k]:>12.6g} "
                      f"{row['ratio']:>10.6f}")
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
