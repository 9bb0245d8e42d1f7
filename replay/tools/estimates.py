"""Trajectories estimated elsewhere: reading TUM, KITTI and pose topics, and a replay that scores one.

An estimate made by another program enters slamreplay as a trajectory ``(t_ns (n,), poses (n, 3))`` in
the world frame (metres, x y yaw). :class:`EstimateReplay` is the pipeline both ``slamreplay evaluate``
(a file) and external pipelines (a program's output) run through ``run_recording``: it replays the
recording's ground truth (drawn as it goes), is handed the estimate at the end (``estimate()``), and then
draws the estimate against the truth and the position error over time; the engine writes
``trajectory.tum``/``truth.tum`` and ``evaluation.score`` adds the trajectory metrics, exactly as for a
built-in pipeline's trajectory.

Every reader refuses, naming the line (or message), what evo would read silently and score wrongly: times that
do not increase strictly (evo keeps a file's order, so an unsorted file's RPE pairs jump in time), a rotation that
is not one within ``ROTATION_TOL`` (evo turns an all-zero quaternion into the identity), a value that is not
finite. Files are read a line at a time after a size check (:func:`text_lines`). A run whose estimate covers less
than ``min_coverage`` of the ground truth's time span fails (:class:`CoverageConfig`): a clock offset otherwise
gives a "succeeded" run that scored nothing.
"""

from __future__ import annotations

import math
import re
from abc import abstractmethod
from array import array
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar, Literal

import numpy as np
import rerun.blueprint as rrb
from numpy.typing import NDArray

from slamreplay.algorithms.common import se2
from slamreplay.algorithms.observe import Pose
from slamreplay.recorder.messages import TOPIC_GROUND_TRUTH_POSE, GroundTruthPose
from slamreplay.replay.engine import views
from slamreplay.replay.engine.pipeline import Pipeline, ReplayContext
from slamreplay.replay.engine.reader import Envelope
from slamreplay.replay.engine.trajectory import TrajectoryLog
from slamreplay.replay.errors import ReplayError
from slamreplay.replay.evaluation.evaluate import (
    ROTATION_TOL,
    Alignment,
    alignment_transform,
    check_quaternion,
    quaternion_yaw,
    read_kitti,
)
from slamreplay.replay.evaluation.metrics import associate as inside_truth_span
from slamreplay.replay.evaluation.metrics import time_coverage, truth_at
from slamreplay.replay.metric_registry import specs

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]
EstimateFormat = Literal["tum", "kitti", "topic"]
_DECIMAL = re.compile(r"^([+-]?)(\d*)(?:\.(\d*))?(?:[eE]([+-]?\d+))?$")
# The largest estimate file `evaluate` reads (TUM, KITTI, KITTI's times), checked before reading: 256 MiB is about
# 3 million TUM lines (a pose every 10 ms for 8 hours), read in ~15 s into ~100 MB. Larger: `max_bytes`.
MAX_ESTIMATE_BYTES = 256 * 1024 * 1024
# The longest line a pose file may have: a TUM line of 8 numbers at full float precision is under 200 bytes, a
# KITTI line under 300. A longer "line" is not a pose file (a NUL-filled or binary file has no line breaks).
MAX_LINE_BYTES = 4096
# The least fraction of the ground truth's time span an estimate's times must cover, by default (min_coverage).
# Half: an estimate that starts late (a SLAM system initialising) or stops early still passes; one whose clock
# is off by more than half the recording, or that lost track for most of it, fails. Any shorter overlap makes the
# accuracy metrics describe a part of the run as if it were the whole.
MIN_COVERAGE = 0.5
MIN_COVERAGE_HELP = ("fail the run when the estimate's times cover less than this fraction of the ground truth's "
                     "time span (first to last estimate time inside it; 0: any overlap; none at all always fails)")
_INT64 = (-(2**63), 2**63 - 1)
_MAX_EXPONENT = 2 * MAX_LINE_BYTES  # beyond it a time is 0 or out of range whatever its digits (a line's at most)


def seconds_to_ns(text: str) -> int:
    """A decimal time in seconds (``1700000000.123456789``) as int nanoseconds, exactly (no float on the way:
    float64 seconds of a Unix time are only good to ~0.2 us); ValueError when it is not a number."""
    text = text.strip()
    whole, _, frac = text.partition(".")
    if len(frac) <= 9 and (whole + frac).isascii() and whole.isdigit() and (frac.isdigit() or not frac):
        return int(whole) * 1_000_000_000 + int(frac.ljust(9, "0"))  # the common case, exact without rounding
    m = _DECIMAL.match(text)
    if not m or not (m.group(2) or m.group(3)):
        raise ValueError(f"not a time in seconds: {text!r}")
    sign, whole, frac, exp = m.group(1), m.group(2) or "0", m.group(3) or "", int(m.group(4) or 0)
    digits = whole + frac
    if abs(exp) > _MAX_EXPONENT:  # 10**exp would take minutes and gigabytes: decide without it
        if exp < 0 or int(digits) == 0:
            return 0
        raise ValueError(f"time {text} s is out of range (int64 nanoseconds: within 292 years of 1970)")
    point = len(whole) + exp  # value = 0.digits * 10^point ... as an integer of ns
    shift = point + 9 - len(digits)
    if shift >= 0:
        ns: int = int(digits) * 10**shift
    else:  # more digits than ns: round half up, in integers (a float would lose the ns of a Unix time)
        q, r = divmod(int(digits), 10 ** (-shift))
        ns = q + int(2 * r >= 10 ** (-shift))
    return -ns if sign == "-" else ns


def text_lines(path: Path, what: str, max_bytes: int = MAX_ESTIMATE_BYTES) -> Iterator[str]:
    """The lines of the text file ``path``, read one at a time (never the whole file at once); ReplayError, before
    anything is read, when it is larger than ``max_bytes``, and naming the line that is longer than
    :data:`MAX_LINE_BYTES` or not UTF-8."""
    try:
        size = path.stat().st_size
    except OSError as err:
        raise ReplayError(f"{what} cannot be read: {err.strerror or err}") from None
    if size > max_bytes:
        raise ReplayError(f"{what} is {size:,} bytes, more than the {max_bytes:,} an estimate may have "
                          f"(MAX_ESTIMATE_BYTES; --max-bytes N reads a larger one)")
    return _lines(path, what)


def _lines(path: Path, what: str) -> Iterator[str]:
    with path.open("rb") as f:
        for i, raw in enumerate(iter(lambda: f.readline(MAX_LINE_BYTES + 1), b""), 1):
            if len(raw) > MAX_LINE_BYTES and not raw.endswith(b"\n"):
                raise ReplayError(f"{what}, line {i}: longer than {MAX_LINE_BYTES:,} bytes: not a pose file")
            try:
                yield raw.decode()
            except UnicodeDecodeError:
                raise ReplayError(f"{what}, line {i}: not UTF-8 text: not a pose file") from None


def _time_ns(text: str) -> int:
    ns = seconds_to_ns(text)
    if not _INT64[0] <= ns <= _INT64[1]:
        raise ValueError(f"time {text} s is out of range (int64 nanoseconds: within 292 years of 1970)")
    return ns


def _increasing(ns: int, prev: int | None, text: str, here: str, there: str) -> str | None:
    """Why time ``ns`` (``text`` s, at ``here``) cannot follow ``prev`` (at ``there``); None when it is later."""
    if prev is None or ns > prev:
        return None
    if ns == prev:
        return f"time {text} s repeats {there}'s: two poses share a timestamp"
    return (f"time {text} s is before {there}'s ({prev / 1e9:.9f} s): times must increase (sort the file; slamreplay "
            f"does not reorder it, evo would score it in this order)")


def read_tum_ns(text: str | Iterable[str], what: str = "TUM file") -> tuple[I64, F64]:
    """(t_ns (n,), poses (n, 3)) of TUM text or its lines (``timestamp x y z qx qy qz qw``; ``#`` comments), the
    yaw taken from the quaternion about +z, times exact to the ns; ReplayError naming the first line that is
    malformed, holds a value that is not finite or a quaternion that is not a unit one (:data:`ROTATION_TOL`), or
    a time that is not after the previous line's."""
    t, values, where = array("q"), array("d"), array("q")  # values: x y z qx qy qz qw a line
    for i, line in enumerate(text.splitlines() if isinstance(text, str) else text, 1):
        parts = line.replace(",", " ").split()
        if not parts or parts[0].startswith("#"):
            continue
        try:
            if len(parts) != 8:
                raise ValueError(f"expected 8 fields (timestamp x y z qx qy qz qw), got {len(parts)}")
            values.extend(map(float, parts[1:]))
            t.append(_time_ns(parts[0]))
        except ValueError as err:
            raise ReplayError(f"{what}, line {i}: {err}") from None
        where.append(i)
    if not t:
        raise ReplayError(f"{what} holds no pose")
    t_ns, v = np.frombuffer(t, np.int64), np.frombuffer(values, np.float64).reshape(-1, 7)  # no copy
    # the checks on whole columns, then the first line any of them refuses, with its message
    bad = {int(k): "a value is not finite" for k in np.flatnonzero(~np.isfinite(v).all(axis=1))[:1]}
    late = np.flatnonzero(np.diff(t_ns) <= 0)[:1] + 1
    for k in late.tolist():
        bad.setdefault(k, str(_increasing(int(t_ns[k]), int(t_ns[k - 1]), _seconds(t_ns[k]), "",
                                          f"line {where[k - 1]}")))
    norm = np.sqrt(np.sum(v[:, 3:] ** 2, axis=1))
    for k in np.flatnonzero(np.abs(norm - 1.0) > ROTATION_TOL)[:1].tolist():
        bad.setdefault(k, str(check_quaternion(*v[k, 3:].tolist())))
    if bad:
        k = min(bad)
        raise ReplayError(f"{what}, line {where[k]}: {bad[k]}")
    qx, qy, qz, qw = v[:, 3:].T
    yaw = np.arctan2(2 * (qw * qz + qx * qy), qw * qw + qx * qx - qy * qy - qz * qz)  # quaternion_yaw, per row
    return t_ns, np.column_stack([v[:, 0], v[:, 1], yaw])


def _seconds(ns: int | np.integer) -> str:
    return f"{int(ns) / 1e9:.9f}"


def read_kitti_ns(text: str | Iterable[str], times_text: str | Iterable[str], what: str = "KITTI file",
                  times_what: str = "times file") -> tuple[I64, F64]:
    """KITTI poses (3x4 matrices, a line each; rotations checked as :func:`read_kitti` does) with the times of
    KITTI's ``times.txt`` (seconds, a line each, increasing strictly); ReplayError naming the file and line."""
    try:
        poses = read_kitti(text)
    except ValueError as err:
        raise ReplayError(f"{what}, {err}") from None
    t = array("q")
    prev: tuple[int, int] | None = None
    for i, line in enumerate(times_text.splitlines() if isinstance(times_text, str) else times_text, 1):
        parts = line.split()
        if not parts or parts[0].startswith("#"):
            continue
        try:
            if len(parts) != 1:
                raise ValueError(f"expected one time in seconds, got {len(parts)} fields")
            ns = _time_ns(parts[0])
        except ValueError as err:
            raise ReplayError(f"{times_what}, line {i}: {err}") from None
        problem = _increasing(ns, prev[0] if prev else None, parts[0], f"line {i}", f"line {prev[1]}" if prev else "")
        if problem:
            raise ReplayError(f"{times_what}, line {i}: {problem}")
        prev = (ns, i)
        t.append(ns)
    if len(t) != len(poses):
        raise ReplayError(f"{what} holds {len(poses)} poses and its times file {len(t)} times: one time a pose")
    if not len(poses):
        raise ReplayError(f"{what} holds no pose")
    return np.frombuffer(t, np.int64).copy(), poses


def read_pose_topic(path: Path, topic: str) -> tuple[I64, F64]:
    """Poses of ``topic`` in a ROS 2 bag (folder, ``.db3`` or ``.mcap``): ``geometry_msgs/PoseStamped``,
    ``PoseWithCovarianceStamped`` or ``nav_msgs/Odometry``, at their header stamps."""
    from slamreplay.recorder.errors import RecorderError
    from slamreplay.recorder.importers.ros2bag import open_bag

    t: list[int] = []
    rows: list[tuple[float, float, float]] = []
    try:  # every byte rosbags reads is checked first; what it raises is one BagError line (recorder/importers)
        with open_bag(path) as bag:
            conns = [c for c in bag.reader.connections if c.topic == topic]
            if not conns:
                have = ", ".join(sorted({c.topic for c in bag.reader.connections}))
                raise ReplayError(f"{path} has no topic {topic} (its topics: {have})")
            for conn, _, raw in bag.messages(conns):
                k = len(t) + 1
                try:
                    msg: Any = bag.reader.deserialize(raw, conn.msgtype)
                except Exception as err:  # noqa: BLE001 -- a damaged message: rosbags' CDR errors vary
                    raise ReplayError(f"{path} {topic}, message {k}: not a readable {conn.msgtype} "
                                      f"({type(err).__name__})") from None
                pose = getattr(msg, "pose", None)
                pose = getattr(pose, "pose", pose)  # PoseWithCovarianceStamped and Odometry nest one more level
                if pose is None or not hasattr(pose, "orientation"):
                    raise ReplayError(f"{path}: topic {topic} is {conn.msgtype}, not a pose (PoseStamped, "
                                      f"PoseWithCovarianceStamped or Odometry)")
                q = pose.orientation
                values = (pose.position.x, pose.position.y, pose.position.z, q.x, q.y, q.z, q.w)
                ns = int(msg.header.stamp.sec) * 1_000_000_000 + int(msg.header.stamp.nanosec)
                problem = ("a value is not finite" if not all(map(math.isfinite, values)) else
                           _increasing(ns, t[-1] if t else None, f"{ns / 1e9:.9f}", f"message {k}",
                                       f"message {k - 1}") or check_quaternion(q.x, q.y, q.z, q.w))
                if problem:
                    raise ReplayError(f"{path} {topic}, message {k} (stamp {ns / 1e9:.9f} s): {problem}")
                t.append(ns)
                rows.append((pose.position.x, pose.position.y, quaternion_yaw(q.x, q.y, q.z, q.w)))
    except RecorderError as err:
        raise ReplayError(str(err)) from None
    if not rows:
        raise ReplayError(f"{path}: topic {topic} has no messages")
    return np.asarray(t, np.int64), np.asarray(rows, np.float64)


def anchor_at(t_ns: I64, poses: F64, T_world_start: F64 | None) -> F64:
    """Poses of a program that starts at its own origin moved so that the first one is ``T_world_start`` (the
    true pose at the start, which built-in pipelines start from too); unchanged when it is None."""
    if T_world_start is None or not len(poses):
        return poses
    return se2.compose(se2.compose(np.asarray(T_world_start, np.float64), se2.inverse(poses[0])), poses)


@dataclass(frozen=True, slots=True)
class Association:
    """How estimate times meet the ground truth's.

    ``t_offset_ns`` is added to every estimate time (evo's ``--t_offset``). The truth is interpolated at
    the estimate's times (as runs are scored); with ``t_max_diff_ns`` an estimate further than that from
    the nearest ground-truth message is left out (evo's ``--t_max_diff``). ``alignment`` is applied to the
    estimate before it is scored: the run's ``ape_rmse_m`` is then the APE after that alignment.
    """

    t_offset_ns: int = 0
    t_max_diff_ns: int | None = None
    alignment: Alignment = "none"

    def as_dict(self) -> dict[str, Any]:
        return {"t_offset_ns": self.t_offset_ns, "t_max_diff_ns": self.t_max_diff_ns, "alignment": self.alignment}


def associate(t_ns: I64, poses: F64, t_gt: I64, gt: F64, assoc: Association) -> tuple[I64, F64]:
    """The estimate with ``assoc`` applied: times shifted, far ones left out, poses aligned to the truth."""
    t_ns = t_ns + assoc.t_offset_ns
    if assoc.t_max_diff_ns is not None and len(t_gt):
        idx = np.clip(np.searchsorted(t_gt, t_ns), 1, max(len(t_gt) - 1, 1))
        near = np.minimum(np.abs(t_ns - t_gt[idx - 1]), np.abs(t_gt[np.minimum(idx, len(t_gt) - 1)] - t_ns))
        keep = near <= assoc.t_max_diff_ns
        t_ns, poses = t_ns[keep], poses[keep]
    if assoc.alignment != "none" and len(t_gt):
        mask, ref = truth_at(t_ns, t_gt, gt)
        if not len(ref):
            raise ReplayError("no estimate time falls inside the ground truth's time span: nothing to align "
                              "(wrong time base? see --t-offset-s)")
        poses = se2.compose(alignment_transform(poses[mask], ref, assoc.alignment), poses)
    return t_ns, poses


@dataclass(frozen=True, slots=True)
class CoverageConfig:
    """The setting every pipeline whose trajectory is an estimate made elsewhere has (``EstimateReplay``): a base
    of their ``Config`` dataclasses, so that ``slamreplay pipelines NAME`` lists it and ``--set`` sets it."""

    min_coverage: float = field(default=MIN_COVERAGE, metadata={"help": MIN_COVERAGE_HELP})

    def __post_init__(self) -> None:
        if not 0.0 <= self.min_coverage <= 1.0:
            raise ValueError(f"min_coverage must be a fraction in [0, 1], got {self.min_coverage}")


def coverage_field() -> tuple[str, type, Any]:
    """``min_coverage`` as a field of ``dataclasses.make_dataclass`` (a Config made at run time, without
    :class:`CoverageConfig` as its base; EstimateReplay then checks the value)."""
    return "min_coverage", float, field(default=MIN_COVERAGE, metadata={"help": MIN_COVERAGE_HELP})


def _s(ns: int | np.integer) -> str:
    return f"{int(ns) / 1e9:.3f}"


def coverage_problem(t_est: I64, t_gt: I64, min_coverage: float, hint: str) -> str | None:
    """Why an estimate at times ``t_est`` cannot be scored against a ground truth at ``t_gt`` (not empty): no
    time inside the truth's span, or less than ``min_coverage`` of it covered; None when it can. One line."""
    truth = f"the truth from t={_s(t_gt[0])} to {_s(t_gt[-1])} s"
    if not len(t_est) or not inside_truth_span(t_est, t_gt).any():
        where = f"the estimate runs from t={_s(t_est.min())} to {_s(t_est.max())} s" if len(t_est) else "it is empty"
        return f"no estimate time falls inside the ground truth's time span ({where}, {truth}): {hint}"
    fraction, first, last = time_coverage(t_est, t_gt)
    if fraction >= min_coverage:
        return None
    percent = math.floor(fraction * 1000) / 10  # rounded down: 49.96 % is not 50 %
    return (f"the estimate covers {percent:g} % of the ground truth's {(t_gt[-1] - t_gt[0]) / 1e9:.1f} s "
            f"({(last - first) / 1e9:.1f} s, from t={_s(first)} to {_s(last)} s; {truth}); min_coverage = "
            f"{min_coverage:g}: {hint}")


class EstimateReplay(Pipeline):
    """A pipeline whose trajectory comes whole at the end (``estimate``): from a file or another program.

    It replays the ground truth (drawn as it goes, kept for the error series) and the subclass's
    ``required_topics``; ``finish`` asks ``estimate()`` for the trajectory in the world frame, checks that its
    times cover ``min_coverage`` of the ground truth's time span (a config key: :class:`CoverageConfig`; a
    Config without it gets :data:`MIN_COVERAGE`), draws it against the truth with the position error over time,
    and returns the registry's metrics of it.
    """

    optional_topics: ClassVar[tuple[str, ...]] = (TOPIC_GROUND_TRUTH_POSE,)
    metrics = specs("robot_final_error_m", "robot_max_error_m", "path_length_m", "poses_scored")
    coverage_hint: ClassVar[str] = ("a clock offset? the estimate's times must be the recording's log times "
                                    "(docs/external.md)")

    def __init__(self, config: Any, ctx: ReplayContext) -> None:
        super().__init__(config, ctx)
        self.min_coverage = float(getattr(config, "min_coverage", MIN_COVERAGE))
        if not 0.0 <= self.min_coverage <= 1.0:
            raise ReplayError(f"min_coverage must be a fraction in [0, 1], got {self.min_coverage}")
        self.truth_log = TrajectoryLog(ctx.observer, "world/trajectory/truth")
        self.t_gt: list[int] = []
        self.gt: list[F64] = []
        self.gt_steps: list[int] = []
        self.result: tuple[I64, F64] | None = None

    def step(self, env: Envelope) -> None:
        if isinstance(env.msg, GroundTruthPose):
            self.t_gt.append(env.log_time_ns)
            self.gt_steps.append(env.index)
            self.gt.append(env.msg.xy_yaw)
            self.ctx.observer.log("world/robot_truth", Pose(env.msg.xy_yaw))
            self.truth_log.append(env.msg.x_m, env.msg.y_m)

    @abstractmethod
    def estimate(self, t_gt: I64, gt: F64) -> tuple[I64, F64]:
        """The trajectory (t_ns (n,), poses (n, 3) in the world frame), given the ground truth replayed."""

    def finish(self) -> dict[str, float]:
        self.truth_log.finish()
        t_gt, gt = np.asarray(self.t_gt, np.int64), np.asarray(self.gt, np.float64).reshape(-1, 3)
        t_est, est = self.estimate(t_gt, gt)
        if len(t_gt):  # without ground truth nothing is scored, and nothing is missed
            problem = coverage_problem(t_est, t_gt, self.min_coverage, self.coverage_hint)
            if problem:
                raise ReplayError(problem)
            fraction = time_coverage(t_est, t_gt)[0]
            self.ctx.log(f"the estimate covers {math.floor(fraction * 1000) / 10:g} % of the ground truth's time "
                         f"span (min_coverage {self.min_coverage:g})")
        self.result = (t_est, est)
        estimate_log = TrajectoryLog(self.ctx.observer, "world/trajectory/estimate")
        for x, y in est[:, :2].tolist():
            estimate_log.append(x, y)
        estimate_log.finish()
        self.ctx.observer.log("world/robot", Pose(est[-1]))
        path = float(np.sum(np.hypot(*np.diff(est[:, :2], axis=0).T))) if len(est) > 1 else 0.0
        mask, ref = truth_at(t_est, t_gt, gt)
        metrics = {"path_length_m": path, "poses_scored": float(len(ref))}
        if not len(ref):  # no ground truth
            return metrics
        err = np.hypot(*(est[mask, :2] - ref[:, :2]).T)
        at = np.clip(np.searchsorted(t_gt, t_est[mask]), 0, len(t_gt) - 1)  # the step of the truth message there
        steps = np.asarray(self.gt_steps, np.int64)[at]
        self.ctx.observer.send_series("metrics/robot_position_error_m", steps, t_est[mask], err)
        return {**metrics, "robot_final_error_m": float(err[-1]), "robot_max_error_m": float(err.max())}

    def trajectory(self) -> tuple[np.ndarray, np.ndarray] | None:
        return self.result

    @classmethod
    def blueprint(cls, bounds: views.Bounds | None = None) -> rrb.Blueprint:
        """Summary (estimate against truth, metrics, error over time), then the map with the log beside it."""
        return views.layout(
            views.summary_tab(bounds, ("metrics/robot_position_error_m",), "Error over time"),
            views.tab("Trajectory and log", views.map_view("Map", "world", bounds),
                      rrb.Vertical(views.series_view("Error over time", "metrics/**"), views.log_view()),
                      columns=[3, 2]),
        )
