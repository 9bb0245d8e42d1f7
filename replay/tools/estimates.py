"""Trajectories estimated elsewhere: reading TUM, KITTI and pose topics, and a replay that scores one.

An estimate made by another program enters slamreplay as a trajectory ``(t_ns (n,), poses (n, 3))`` in
the world frame (metres, x y yaw). :class:`EstimateReplay` is the pipeline both ``slamreplay evaluate``
(a file) and external pipelines (a program's output) run through ``run_recording``: it replays the
recording's ground truth (drawn as it goes), is handed the estimate at the end (``estimate()``), and then
draws the estimate against the truth and the position error over time; the engine writes
``trajectory.tum``/``truth.tum`` and ``evaluation.score`` adds the trajectory metrics, exactly as for a
built-in pipeline's trajectory.
"""

from __future__ import annotations

import math
import re
from abc import abstractmethod
from dataclasses import dataclass
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
from slamreplay.replay.evaluation.evaluate import Alignment, alignment_transform
from slamreplay.replay.evaluation.metrics import truth_at
from slamreplay.replay.metric_registry import specs

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]
EstimateFormat = Literal["tum", "kitti", "topic"]
_DECIMAL = re.compile(r"^([+-]?)(\d*)(?:\.(\d*))?(?:[eE]([+-]?\d+))?$")


def seconds_to_ns(text: str) -> int:
    """A decimal time in seconds (``1700000000.123456789``) as int nanoseconds, exactly (no float on the way:
    float64 seconds of a Unix time are only good to ~0.2 us); ValueError when it is not a number."""
    m = _DECIMAL.match(text.strip())
    if not m or not (m.group(2) or m.group(3)):
        raise ValueError(f"not a time in seconds: {text!r}")
    sign, whole, frac, exp = m.group(1), m.group(2) or "0", m.group(3) or "", int(m.group(4) or 0)
    digits, point = whole + frac, len(whole) + exp  # value = 0.digits * 10^point ... as an integer of ns
    shift = point + 9 - len(digits)
    if shift >= 0:
        ns: int = int(digits) * 10**shift
    else:  # more digits than ns: round half up, in integers (a float would lose the ns of a Unix time)
        q, r = divmod(int(digits), 10 ** (-shift))
        ns = q + int(2 * r >= 10 ** (-shift))
    return -ns if sign == "-" else ns


def read_tum_ns(text: str, what: str = "TUM file") -> tuple[I64, F64]:
    """(t_ns (n,), poses (n, 3)) of TUM text (``timestamp x y z qx qy qz qw``; ``#`` comments), the yaw taken
    from the quaternion about +z, times exact to the ns; ReplayError naming the line that is malformed."""
    t, rows = [], []
    for i, line in enumerate(text.splitlines(), 1):
        parts = line.replace(",", " ").split()
        if not parts or parts[0].startswith("#"):
            continue
        try:
            if len(parts) != 8:
                raise ValueError(f"expected 8 fields (timestamp x y z qx qy qz qw), got {len(parts)}")
            x, y, _z, qx, qy, qz, qw = map(float, parts[1:])
            t.append(seconds_to_ns(parts[0]))
        except ValueError as err:
            raise ReplayError(f"{what}, line {i}: {err}") from None
        if not all(map(math.isfinite, (x, y, qx, qy, qz, qw))):
            raise ReplayError(f"{what}, line {i}: a value is not finite")
        rows.append((x, y, math.atan2(2 * (qw * qz + qx * qy), 1 - 2 * (qy * qy + qz * qz))))
    if not rows:
        raise ReplayError(f"{what} holds no pose")
    return _sorted(np.asarray(t, np.int64), np.asarray(rows, np.float64), what)


def read_kitti_ns(text: str, times_text: str, what: str = "KITTI file") -> tuple[I64, F64]:
    """KITTI poses (3x4 matrices, a line each) with the times of KITTI's ``times.txt`` (seconds, a line each)."""
    from slamreplay.replay.evaluation.evaluate import read_kitti

    try:
        poses = read_kitti(text)
        t = np.asarray([seconds_to_ns(s) for s in times_text.split()], np.int64)
    except ValueError as err:
        raise ReplayError(f"{what}: {err}") from None
    if len(t) != len(poses):
        raise ReplayError(f"{what} holds {len(poses)} poses and its times file {len(t)} times: one time a pose")
    if not len(poses):
        raise ReplayError(f"{what} holds no pose")
    return _sorted(t, poses, what)


def read_pose_topic(path: Path, topic: str) -> tuple[I64, F64]:
    """Poses of ``topic`` in a ROS 2 bag (folder, ``.db3`` or ``.mcap``): ``geometry_msgs/PoseStamped``,
    ``PoseWithCovarianceStamped`` or ``nav_msgs/Odometry``, at their header stamps."""
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS2_HUMBLE)  # for types a bag does not define
    try:
        try:
            reader = AnyReader([path], default_typestore=store)
            reader.open()
        except Exception:  # a metadata.yaml rosbags cannot read: read its one storage file alone
            files = sorted([*path.glob("*.db3"), *path.glob("*.mcap")]) if path.is_dir() else []
            if len(files) != 1:
                raise
            reader = AnyReader([files[0]], default_typestore=store)
            reader.open()
        try:
            conns = [c for c in reader.connections if c.topic == topic]
            if not conns:
                have = ", ".join(sorted({c.topic for c in reader.connections}))
                raise ReplayError(f"{path} has no topic {topic} (its topics: {have})")
            t, rows = [], []
            for conn, _, raw in reader.messages(connections=conns):
                msg: Any = reader.deserialize(raw, conn.msgtype)
                pose = getattr(msg, "pose", None)
                pose = getattr(pose, "pose", pose)  # PoseWithCovarianceStamped and Odometry nest one more level
                if pose is None or not hasattr(pose, "orientation"):
                    raise ReplayError(f"{path}: topic {topic} is {conn.msgtype}, not a pose (PoseStamped, "
                                      f"PoseWithCovarianceStamped or Odometry)")
                q = pose.orientation
                t.append(int(msg.header.stamp.sec) * 1_000_000_000 + int(msg.header.stamp.nanosec))
                rows.append((pose.position.x, pose.position.y,
                             math.atan2(2 * (q.w * q.z + q.x * q.y), 1 - 2 * (q.y * q.y + q.z * q.z))))
        finally:
            reader.close()
    except ReplayError:
        raise
    except Exception as err:  # noqa: BLE001 -- rosbags raises its own errors for what is not a bag
        raise ReplayError(f"{path} is not a readable ROS 2 bag: {type(err).__name__}: {err}") from None
    if not rows:
        raise ReplayError(f"{path}: topic {topic} has no messages")
    return _sorted(np.asarray(t, np.int64), np.asarray(rows, np.float64), f"{path} {topic}")


def _sorted(t: I64, poses: F64, what: str) -> tuple[I64, F64]:
    if np.any(np.diff(t) < 0):
        order = np.argsort(t, kind="stable")
        t, poses = t[order], poses[order]
    if np.any(np.diff(t) == 0):
        raise ReplayError(f"{what}: two poses share a timestamp")
    return t, poses


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


class EstimateReplay(Pipeline):
    """A pipeline whose trajectory comes whole at the end (``estimate``): from a file or another program.

    It replays the ground truth (drawn as it goes, kept for the error series) and the subclass's
    ``required_topics``; ``finish`` asks ``estimate()`` for the trajectory in the world frame, draws it
    against the truth with the position error over time, and returns the registry's metrics of it.
    """

    optional_topics: ClassVar[tuple[str, ...]] = (TOPIC_GROUND_TRUTH_POSE,)
    metrics = specs("robot_final_error_m", "robot_max_error_m", "path_length_m", "poses_scored")

    def __init__(self, config: Any, ctx: ReplayContext) -> None:
        super().__init__(config, ctx)
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
        self.result = (t_est, est)
        estimate_log = TrajectoryLog(self.ctx.observer, "world/trajectory/estimate")
        for x, y in est[:, :2].tolist():
            estimate_log.append(x, y)
        estimate_log.finish()
        self.ctx.observer.log("world/robot", Pose(est[-1]))
        path = float(np.sum(np.hypot(*np.diff(est[:, :2], axis=0).T))) if len(est) > 1 else 0.0
        mask, ref = truth_at(t_est, t_gt, gt)
        metrics = {"path_length_m": path, "poses_scored": float(len(ref))}
        if not len(ref):
            self.ctx.log("no estimate time falls inside the ground truth's time span: the accuracy metrics do not "
                         "apply (another time base? `slamreplay evaluate --t-offset-s`)")
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
