"""Pipeline ``odometry``: dead reckoning scored against ground truth.

The estimate starts at the ground-truth pose at the first ``/odom`` message (identity
without ground truth) and then composes odometry only. It proves the whole path from
recording to ``.rrd`` and is the baseline every SLAM pipeline must beat.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from slamreplay.algorithms.deadreckoning import DeadReckoning
from slamreplay.algorithms.observe import Pose
from slamreplay.recorder.messages import TOPIC_GROUND_TRUTH_POSE, TOPIC_ODOM, GroundTruthPose, OdometryPose
from slamreplay.replay.engine.pipeline import Pipeline, ReplayContext
from slamreplay.replay.engine.reader import Envelope
from slamreplay.replay.engine.trajectory import TrajectoryLog
from slamreplay.replay.evaluation.metrics import position_errors
from slamreplay.replay.metric_registry import specs


@dataclass(frozen=True, slots=True)
class OdometryConfig:
    """Dead reckoning has no parameters."""


class OdometryPipeline(Pipeline):
    name = "odometry"
    summary = "dead reckoning from /odom, scored against /ground_truth/pose"
    required_topics = (TOPIC_ODOM,)
    optional_topics = (TOPIC_GROUND_TRUTH_POSE,)
    start_topic = TOPIC_ODOM
    Config = OdometryConfig
    # the ATE and the heading RMSE are ape_rmse_m and ape_rot_rmse_deg (replay.evaluate)
    metrics = specs("robot_final_error_m", "robot_max_error_m", "path_length_m", "poses_scored")

    def __init__(self, config: OdometryConfig, ctx: ReplayContext) -> None:
        super().__init__(config, ctx)
        start = ctx.T_world_start if ctx.T_world_start is not None else np.zeros(3)
        self.dead_reckoning = DeadReckoning(start)
        self.estimate = TrajectoryLog(ctx.observer, "world/trajectory/estimate")
        self.truth = TrajectoryLog(ctx.observer, "world/trajectory/truth")
        self.t_est: list[int] = []
        self.steps: list[int] = []
        self.est: list[np.ndarray] = []
        self.t_gt: list[int] = []
        self.gt: list[np.ndarray] = []

    def step(self, env: Envelope) -> None:
        msg = env.msg
        if isinstance(msg, OdometryPose):
            pose = self.dead_reckoning.step(msg.xy_yaw)
            self.t_est.append(env.log_time_ns)
            self.steps.append(env.index)
            self.est.append(pose)
            self.ctx.observer.log("world/robot", Pose(pose))
            self.estimate.append(float(pose[0]), float(pose[1]))
        elif isinstance(msg, GroundTruthPose):
            truth = msg.xy_yaw
            self.t_gt.append(env.log_time_ns)
            self.gt.append(truth)
            self.ctx.observer.log("world/robot_truth", Pose(truth))
            self.truth.append(msg.x_m, msg.y_m)

    def finish(self) -> dict[str, float]:
        t_est = np.asarray(self.t_est, np.int64)
        est = np.asarray(self.est, np.float64).reshape(-1, 3)
        t_gt = np.asarray(self.t_gt, np.int64)
        gt = np.asarray(self.gt, np.float64).reshape(-1, 3)
        self.estimate.finish()
        self.truth.finish()
        pos_err, _ = position_errors(t_est, est, t_gt, gt)
        path = float(np.sum(np.hypot(*np.diff(est[:, :2], axis=0).T))) if len(est) > 1 else 0.0
        metrics = {"path_length_m": path, "poses_scored": float(len(pos_err))}
        if not len(pos_err):
            self.ctx.log("no ground truth overlaps the odometry: the accuracy metrics do not apply")
            return metrics
        inside = (t_est >= t_gt[0]) & (t_est <= t_gt[-1])
        self.ctx.observer.send_series("metrics/robot_position_error_m", np.asarray(self.steps)[inside],
                                      t_est[inside], pos_err)
        return {
            **metrics,
            "robot_final_error_m": float(pos_err[-1]),
            "robot_max_error_m": float(pos_err.max()),
        }
