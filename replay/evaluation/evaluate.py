"""Trajectory error in the vocabulary of evo: absolute pose error with a chosen alignment, relative pose error.

Definitions follow evo (Grupp, https://github.com/MichaelGrupp/evo), planar (SE(2)), so that a run's
``trajectory.tum`` and ``truth.tum`` give the same figures in ``evo_ape``/``evo_rpe`` (``--align``: ``se2``
here; ``--align_origin``: ``origin``) as here:

- **APE** (absolute pose error, translation part): ``|t_est,i - t_ref,i|`` after aligning the estimate by
  ``alignment``: ``none`` (the estimate is already in the reference frame; slamreplay's runs start at the
  true initial pose, so this counts every error, including the first pose's), ``origin`` (the transform
  taking the first estimated pose onto the first reference pose), ``se2`` (the rigid motion minimising the
  squared position errors: Umeyama/Kabsch without scale). The rotation part is ``|wrap(yaw_est - yaw_ref)|``.
- **RPE** (relative pose error): for pose pairs ``(i, j)``, ``E = (Q_i^-1 Q_j)^-1 (P_i^-1 P_j)`` with Q the
  reference and P the estimate; its translation norm and its rotation angle (evo's ``--pose_relation
  trans_part`` and ``angle_deg``). Pairs as evo makes them without ``--all_pairs``: consecutive,
  non-overlapping segments of ``delta`` poses (``unit="step"``), or of at least ``delta`` metres of the
  estimate's path (``unit="m"``: ``evo_rpe --delta 1 --delta_unit m``, whose pairs come from the estimate
  unless ``--pairs_from_reference``; ``pairs_from_reference=True`` here measures the reference's path, as
  KITTI's devkit does).

Both are statistics over poses at the estimate's times; the reference is the ground truth interpolated
there (``truth_at``), so estimate and reference pair one to one (as in KITTI's files).
``tests/replay/test_evo_parity.py`` runs evo itself on the same poses and checks every figure.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.typing import NDArray

from slamreplay.algorithms.common import se2
from slamreplay.replay.metric_registry import RPE_METRE_DELTA_M, MetricSpec, specs

F64 = NDArray[np.float64]
Alignment = Literal["none", "origin", "se2"]
DeltaUnit = Literal["step", "m"]
ALIGNMENTS: tuple[Alignment, ...] = ("none", "origin", "se2")
# How far a pose file's rotation may be from a rotation: |norm - 1| of a quaternion, and each entry of R^T R - I of
# a matrix. Rounding a unit quaternion's components to d decimals moves its norm by at most 2 * 0.5e-d (1e-4 at 4
# decimals, 1e-3 at 3), and a rotation matrix's entries by at most 2 sqrt(3) * 0.5e-d in R^T R (1.7e-4 at 4): 1e-3
# accepts quaternions written with 3 or more decimals and matrices with 4 or more (KITTI's own files: 7 digits).
# What it refuses is no rounded rotation at all: zeros, Euler angles or positions in the rotation's columns, a
# column order mixed up. evo normalises silently (an all-zero quaternion becomes the identity); its
# `evo_traj --full_check` calls a norm off by more than ~1e-5 invalid, which refuses files written with 4 decimals.
ROTATION_TOL = 1e-3


@dataclass(frozen=True, slots=True)
class ErrorStats:
    """Statistics of one error series (evo's ``rmse``, ``mean``, ``median``, ``max``, and the count)."""

    rmse: float
    mean: float
    median: float
    max: float
    n: int

    @classmethod
    def of(cls, e: F64) -> ErrorStats:
        """Statistics of ``e`` (NaN for an empty series)."""
        if len(e) == 0:
            return cls(math.nan, math.nan, math.nan, math.nan, 0)
        return cls(float(np.sqrt(np.mean(e * e))), float(np.mean(e)), float(np.median(e)), float(np.max(e)), len(e))


def _check(est: F64, ref: F64) -> tuple[F64, F64]:
    est, ref = np.asarray(est, np.float64), np.asarray(ref, np.float64)
    if est.ndim != 2 or est.shape[1] != 3 or est.shape != ref.shape:
        raise ValueError(f"est and ref must be (n, 3) x, y, yaw of the same length, got {est.shape} and {ref.shape}")
    return est, ref


def alignment_transform(est: F64, ref: F64, alignment: Alignment) -> F64:
    """The pose ``T`` (x, y, yaw) such that ``T (+) est`` is the aligned estimate.

    ``se2``: the closed-form least-squares rigid motion of the positions (Umeyama 1991 without scale, in 2D:
    the rotation angle is ``atan2`` of the cross-covariance's antisymmetric and symmetric parts).
    """
    est, ref = _check(est, ref)
    if alignment == "none" or len(est) == 0:
        return np.zeros(3)
    if alignment == "origin":
        return se2.compose(ref[0], se2.inverse(est[0]))
    if alignment != "se2":
        raise ValueError(f"alignment must be one of {', '.join(ALIGNMENTS)}, got {alignment!r}")
    pe, pr = est[:, :2], ref[:, :2]
    ce, cr = pe.mean(axis=0), pr.mean(axis=0)
    a, b = pe - ce, pr - cr
    theta = math.atan2(float(np.sum(a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0])), float(np.sum(a[:, 0] * b[:, 0] +
                                                                                       a[:, 1] * b[:, 1])))
    t = cr - se2.rot(theta) @ ce
    return np.array([t[0], t[1], theta])


def ape(est: F64, ref: F64, alignment: Alignment = "none") -> tuple[ErrorStats, ErrorStats]:
    """(translation error stats in the estimate's unit, rotation error stats in degrees) after ``alignment``."""
    est, ref = _check(est, ref)
    aligned = se2.compose(alignment_transform(est, ref, alignment), est) if len(est) else est
    d = aligned - ref
    return ErrorStats.of(np.hypot(d[:, 0], d[:, 1])), ErrorStats.of(np.degrees(np.abs(se2.wrap_angle(d[:, 2]))))


def pairs(poses: F64, delta: float, unit: DeltaUnit) -> list[tuple[int, int]]:
    """evo's consecutive pose pairs (``filters.filter_pairs_by_path``/``_by_index``, ``all_pairs=False``): every
    ``delta`` poses, or each time at least ``delta`` metres of ``poses``' own path have been driven since the
    last pair's end (the path summed step by step and restarted from 0 there, as evo does)."""
    n = len(poses)
    if unit == "step":
        if delta < 1 or delta != int(delta):
            raise ValueError(f"delta in steps must be a whole number >= 1, got {delta}")
        ids = list(range(0, n, int(delta)))
    elif unit == "m":
        if not delta > 0:
            raise ValueError(f"delta in metres must be > 0, got {delta}")
        ids = [0] if n else []
        path = 0.0
        d = np.diff(np.asarray(poses, np.float64)[:, :2], axis=0) if n > 1 else np.zeros((0, 2))
        for i, s in enumerate(np.sqrt(d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1]).tolist(), start=1):
            path += s
            if path >= delta:
                ids.append(i)
                path = 0.0
    else:
        raise ValueError(f"delta unit must be 'step' or 'm', got {unit!r}")
    return list(itertools.pairwise(ids))


def rpe(est: F64, ref: F64, delta: float = 1, unit: DeltaUnit = "step", *,
        pairs_from_reference: bool = False) -> tuple[ErrorStats, ErrorStats]:
    """(translation stats, rotation stats in degrees) of the relative pose error over :func:`pairs` of the
    estimate's path (evo's default), or of the reference's with ``pairs_from_reference`` (evo's
    ``--pairs_from_reference``); the two differ for ``unit="m"`` only."""
    est, ref = _check(est, ref)
    ij = pairs(ref if pairs_from_reference else est, delta, unit)
    if not ij:
        return ErrorStats.of(np.zeros(0)), ErrorStats.of(np.zeros(0))
    i, j = np.array(ij).T
    e = se2.between(se2.between(ref[i], ref[j]), se2.between(est[i], est[j]))
    return ErrorStats.of(np.hypot(e[:, 0], e[:, 1])), ErrorStats.of(np.degrees(np.abs(se2.wrap_angle(e[:, 2]))))


# The trajectory metrics every pipeline with an estimated trajectory and ground truth reports, one name each
# (replay.metric_registry). Runs start at the true pose, so evo's --align_origin would repeat ape_rmse_m:
# it is not among them (`slamreplay trajectory` prints it for estimates made elsewhere).
TRAJECTORY_METRICS: dict[str, MetricSpec] = specs(
    "ape_rmse_m", "ape_se2_rmse_m", "ape_rot_rmse_deg", "rpe_step_trans_rmse_m", "rpe_step_rot_rmse_deg",
    "rpe_m_trans_rmse_m", "rpe_m_rot_rmse_deg")
RUN_ALIGNMENTS: tuple[Alignment, ...] = ("none", "se2")


def trajectory_metrics(est: F64, ref: F64) -> dict[str, float]:
    """The :data:`TRAJECTORY_METRICS` of an estimate against the ground truth at its times (``truth_at``), those
    that apply: none without a pose; the RPE per metre only once the robot has moved that far."""
    est, ref = _check(est, ref)
    if len(ref) == 0:
        return {}
    out: dict[str, float] = {}
    for alignment in RUN_ALIGNMENTS:
        trans, rot = ape(est, ref, alignment)
        out["ape_rmse_m" if alignment == "none" else f"ape_{alignment}_rmse_m"] = trans.rmse
        if alignment == "none":
            out["ape_rot_rmse_deg"] = rot.rmse
    for key, delta, unit in (("step", 1.0, "step"), ("m", RPE_METRE_DELTA_M, "m")):
        trans, rot = rpe(est, ref, delta, unit)  # type: ignore[arg-type]
        if trans.n:
            out[f"rpe_{key}_trans_rmse_m"], out[f"rpe_{key}_rot_rmse_deg"] = trans.rmse, rot.rmse
    return out


def to_kitti(poses: F64) -> bytes:
    """Planar poses (n, 3) as KITTI odometry text: the top 3x4 of each SE(3) pose matrix, row-major, a line each
    (z = 0, rotation about +z). KITTI files carry no time: write estimate and truth at the same times."""
    lines = []
    for x, y, th in np.asarray(poses, np.float64).reshape(-1, 3).tolist():
        c, s = math.cos(th), math.sin(th)
        lines.append(" ".join(f"{v:.9g}" for v in (c, -s, 0.0, x, s, c, 0.0, y, 0.0, 0.0, 1.0, 0.0)))
    return ("\n".join(lines) + ("\n" if lines else "")).encode()


def read_kitti(lines: str | Iterable[str]) -> F64:
    """Planar poses (n, 3) of KITTI text (or its lines); ValueError naming the line that is not 12 finite numbers
    or whose rotation is not one (:func:`check_rotation`). The yaw is that of the matrix's first column."""
    rows = []
    for i, line in enumerate(lines.splitlines() if isinstance(lines, str) else lines, 1):
        if not line.strip():
            continue
        try:
            m = np.array([float(v) for v in line.split()], np.float64)
        except ValueError as err:
            raise ValueError(f"line {i}: not 12 numbers ({err})") from err
        if m.shape != (12,):
            raise ValueError(f"line {i}: expected 12 numbers (a 3x4 pose matrix), got {m.size}")
        if not np.all(np.isfinite(m)):
            raise ValueError(f"line {i}: a value is not finite")
        problem = check_rotation(m.reshape(3, 4)[:, :3])
        if problem:
            raise ValueError(f"line {i}: {problem}")
        rows.append((m[3], m[7], math.atan2(m[4], m[0])))
    return np.array(rows, np.float64).reshape(-1, 3)


def check_rotation(r: F64) -> str | None:
    """What keeps the 3x3 matrix ``r`` from being a rotation: ``R^T R`` off the identity by more than
    :data:`ROTATION_TOL` in an entry, or a reflection (det < 0); None when it is one."""
    off = float(np.max(np.abs(r.T @ r - np.eye(3))))
    if off > ROTATION_TOL:
        return (f"the rotation part is not orthonormal (R^T R differs from the identity by {off:.3g} > "
                f"{ROTATION_TOL:g})")
    if np.linalg.det(r) < 0:
        return "the rotation part is a reflection (det = -1), not a rotation"
    return None


def check_quaternion(qx: float, qy: float, qz: float, qw: float) -> str | None:
    """What keeps ``(qx, qy, qz, qw)`` from being a unit quaternion within :data:`ROTATION_TOL`; None if it is."""
    norm = math.sqrt(qx * qx + qy * qy + qz * qz + qw * qw)
    if abs(norm - 1.0) > ROTATION_TOL:
        return f"the quaternion's norm is {norm:.6g}, not 1 (within {ROTATION_TOL:g})"
    return None


def quaternion_yaw(qx: float, qy: float, qz: float, qw: float) -> float:
    """The yaw (rad) of a quaternion about +z, independent of its norm (as evo normalises before use)."""
    return math.atan2(2 * (qw * qz + qx * qy), qw * qw + qx * qx - qy * qy - qz * qz)
