"""``slamreplay trajectory RUN``: a finished run's APE and RPE with a chosen alignment, and KITTI export.

Reads the run's ``trajectory.tum`` (the estimate) and ``truth.tum`` (the ground truth at the same times,
written when the recording has ground truth), so its figures are those ``evo_ape``/``evo_rpe`` give on
the same two files (definitions in :mod:`slamreplay.replay.evaluation.evaluate`).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from slamreplay.recorder.files import atomic_write
from slamreplay.replay.engine.trajectory import TRUTH_TUM_ARTIFACT, TUM_ARTIFACT, paired_with_truth, read_tum
from slamreplay.replay.errors import ReplayError
from slamreplay.replay.evaluation.evaluate import Alignment, DeltaUnit, ErrorStats, ape, rpe, to_kitti
from slamreplay.replay.runs.diff import load_run

KITTI_ESTIMATE, KITTI_TRUTH = "estimate.kitti", "truth.kitti"


@dataclass(frozen=True, slots=True)
class TrajectoryReport:
    """APE and RPE of one run (each: translation stats in metres, rotation stats in degrees)."""

    run: Path
    pipeline: str
    alignment: Alignment
    delta: float
    delta_unit: DeltaUnit
    poses: int
    ape_trans: ErrorStats
    ape_rot: ErrorStats
    rpe_trans: ErrorStats
    rpe_rot: ErrorStats
    pairs_from_reference: bool = False

    def to_json(self) -> dict[str, Any]:
        """Plain JSON of the report (NaN as null)."""

        def stats(s: ErrorStats) -> dict[str, Any]:
            return {k: (None if isinstance(v, float) and np.isnan(v) else v)
                    for k, v in (("rmse", s.rmse), ("mean", s.mean), ("median", s.median), ("max", s.max),
                                 ("n", s.n))}

        return {"run": str(self.run), "pipeline": self.pipeline, "alignment": self.alignment, "poses": self.poses,
                "rpe_delta": self.delta, "rpe_delta_unit": self.delta_unit,
                "rpe_pairs_from": "reference" if self.pairs_from_reference else "estimate",
                "ape": {"translation_m": stats(self.ape_trans), "rotation_deg": stats(self.ape_rot)},
                "rpe": {"translation_m": stats(self.rpe_trans), "rotation_deg": stats(self.rpe_rot)}}

    def table(self) -> str:
        """The report as aligned text."""
        unit = ("step" + ("s" if self.delta != 1 else "") if self.delta_unit == "step" else
                "m of truth" if self.pairs_from_reference else "m")
        lines = [f"{self.run}: {self.pipeline}, {self.poses:,} poses against ground truth",
                 f"{'':<34} {'rmse':>10} {'mean':>10} {'median':>10} {'max':>10}"]
        for label, s in ((f"APE translation (m), align {self.alignment}", self.ape_trans),
                         ("APE rotation (deg)", self.ape_rot),
                         (f"RPE translation (m), {self.delta:g} {unit}", self.rpe_trans),
                         (f"RPE rotation (deg), {self.delta:g} {unit}", self.rpe_rot)):
            lines.append(f"{label:<34} " + " ".join(f"{v:>10.4g}" for v in (s.rmse, s.mean, s.median, s.max)))
        if self.rpe_trans.n == 0:
            lines.append(f"(no pose pairs {self.delta:g} {unit} apart: the RPE is empty)")
        return "\n".join(lines)


def read_run_trajectories(run_dir: Path) -> tuple[str, np.ndarray, np.ndarray, np.ndarray | None]:
    """(pipeline, times s, estimate (n, 3), truth (n, 3) or None) of a finished run, the estimate cut to the
    truth's times when there is one (estimates outside the ground truth's time span have no truth); ReplayError
    saying what is missing."""
    manifest, _ = load_run(run_dir)
    pipeline = str(manifest.get("pipeline"))
    est_file, truth_file = run_dir / TUM_ARTIFACT, run_dir / TRUTH_TUM_ARTIFACT
    if not est_file.is_file():
        raise ReplayError(f"{run_dir} has no {TUM_ARTIFACT}: pipeline {pipeline} exports no trajectory")
    try:
        t, est = read_tum(est_file.read_text())
        truth = None
        if truth_file.is_file():
            t_truth, truth = read_tum(truth_file.read_text())
            paired = paired_with_truth(t, est, t_truth)
            if paired is None:
                raise ReplayError(f"{truth_file} holds times that {est_file} does not (another run's file?)")
            t, est = t_truth, paired
    except ValueError as err:
        raise ReplayError(f"{run_dir}: a trajectory file is malformed: {err}") from err
    return pipeline, t, est, truth


def evaluate_run(run_dir: Path, alignment: Alignment = "none", delta: float = 1.0, delta_unit: DeltaUnit = "step",
                 pairs_from_reference: bool = False) -> TrajectoryReport:
    """APE with ``alignment`` and RPE over pairs ``delta`` steps or metres apart (metres of the estimate's path, as
    ``evo_rpe`` measures them, or of the truth's with ``pairs_from_reference``), of a finished run."""
    pipeline, _, est, truth = read_run_trajectories(run_dir)
    if truth is None:
        raise ReplayError(f"{run_dir} has no {TRUTH_TUM_ARTIFACT}: its recording has no /ground_truth/pose to "
                          f"score the trajectory against")
    try:
        at, ar = ape(est, truth, alignment)
        rt, rr = rpe(est, truth, delta, delta_unit, pairs_from_reference=pairs_from_reference)
    except ValueError as err:
        raise ReplayError(str(err)) from err
    return TrajectoryReport(run_dir, pipeline, alignment, delta, delta_unit, len(est), at, ar, rt, rr,
                            pairs_from_reference)


def export_kitti(run_dir: Path, out_dir: Path) -> list[Path]:
    """Write ``estimate.kitti`` (and ``truth.kitti``, line for line at the same times, when the run has ground
    truth: the estimate is then cut to the truth's time span) into ``out_dir``; the paths written. Each file is
    written whole or not at all."""
    _, _, est, truth = read_run_trajectories(run_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    written = [out_dir / KITTI_ESTIMATE]
    atomic_write(written[0], to_kitti(est))
    if truth is not None:
        written.append(out_dir / KITTI_TRUTH)
        atomic_write(written[1], to_kitti(truth))
    return written
