"""Pipeline ``cv-filter``: the constant-velocity Kalman filter of :mod:`my_pipeline.filter` over ``/odom``.

It reads the cumulative odometry pose, turns each pair of samples into a body-frame increment,
and feeds the filter; it draws the estimated trajectory with its 2-sigma position ellipse,
scores the pose against ``/ground_truth/pose`` like the built-in ``odometry`` pipeline, and
scores the speed and turn rate it estimates against those of the ground truth, next to the raw
odometry's (the ``odom_*`` metrics: the baseline the filter should beat).
"""

from __future__ import annotations

import io
import math
from dataclasses import dataclass, field

import numpy as np

from my_pipeline.filter import ConstantVelocityFilter, CvNoise, mean_velocity
from slamreplay.algorithms.common.motion import between1
from slamreplay.algorithms.observe import CovarianceEllipses, Pose, Scalar
from slamreplay.recorder.messages import TOPIC_GROUND_TRUTH_POSE, TOPIC_ODOM, GroundTruthPose, OdometryPose
from slamreplay.replay.engine.pipeline import MetricSpec, Pipeline, ReplayContext
from slamreplay.replay.engine.reader import Envelope
from slamreplay.replay.engine.trajectory import TrajectoryLog
from slamreplay.replay.evaluation.metrics import position_errors, rmse
from slamreplay.replay.metric_registry import specs


def _help(text: str) -> dict[str, str]:
    return {"help": text}


@dataclass(frozen=True, slots=True)
class CvFilterConfig:
    """The filter's noise. The three odometry keys share their names with the recording's sensor model,
    so a recording that states its odometry noise sets them (``Pipeline.config_from_sensor_model``)."""

    accel_sigma_mps2: float = field(default=0.05, metadata=_help(
        "white acceleration density of the speed, m/s^2/sqrt(Hz): larger follows odometry more closely"))
    yaw_accel_sigma_radps2: float = field(default=0.05, metadata=_help(
        "white acceleration density of the turn rate, rad/s^2/sqrt(Hz)"))
    translation_sigma_per_sqrt_m: float = field(default=0.02, metadata=_help(
        "odometry translation noise, m per sqrt(m) travelled (from the recording when it says)"))
    heading_sigma_per_sqrt_m: float = field(default=0.02, metadata=_help(
        "odometry heading noise, rad per sqrt(m) travelled (from the recording when it says)"))
    heading_sigma_per_sqrt_rad: float = field(default=0.05, metadata=_help(
        "odometry heading noise, rad per sqrt(rad) turned (from the recording when it says)"))
    speed_sigma_floor_mps: float = field(default=0.002, metadata=_help(
        "least speed noise of one odometry sample, m/s: keeps a robot standing still from freezing the filter"))
    yaw_rate_sigma_floor_radps: float = field(default=0.002, metadata=_help(
        "least turn-rate noise of one odometry sample, rad/s"))

    def __post_init__(self) -> None:
        for name in ("accel_sigma_mps2", "yaw_accel_sigma_radps2"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be finite and > 0, got {value}")
        for name in ("translation_sigma_per_sqrt_m", "heading_sigma_per_sqrt_m", "heading_sigma_per_sqrt_rad",
                     "speed_sigma_floor_mps", "yaw_rate_sigma_floor_radps"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise ValueError(f"{name} must be finite and >= 0, got {value}")
        if self.speed_sigma_floor_mps == 0 and self.translation_sigma_per_sqrt_m == 0:
            raise ValueError("speed_sigma_floor_mps and translation_sigma_per_sqrt_m are both 0: "
                             "odometry would be exact and the filter singular; give either a positive value")
        if self.yaw_rate_sigma_floor_radps == 0 and self.heading_sigma_per_sqrt_m == 0 == \
                self.heading_sigma_per_sqrt_rad:
            raise ValueError("yaw_rate_sigma_floor_radps and both heading sigmas are 0: the filter would be singular")

    def noise(self) -> CvNoise:
        return CvNoise(self.accel_sigma_mps2, self.yaw_accel_sigma_radps2, self.translation_sigma_per_sqrt_m,
                       self.heading_sigma_per_sqrt_m, self.heading_sigma_per_sqrt_rad, self.speed_sigma_floor_mps,
                       self.yaw_rate_sigma_floor_radps)


class CvFilterPipeline(Pipeline):
    name = "cv-filter"
    summary = "constant-velocity Kalman filter over /odom (example plugin), scored against /ground_truth/pose"
    required_topics = (TOPIC_ODOM,)
    optional_topics = (TOPIC_GROUND_TRUTH_POSE,)
    start_topic = TOPIC_ODOM
    Config = CvFilterConfig
    # Metrics the built-ins also report come from slamreplay's registry, by name, so `slamreplay diff` lines
    # them up with an odometry run's. The ATE and heading RMSE (ape_rmse_m, ape_rot_rmse_deg...) need no code:
    # slamreplay computes them from the trajectory kept in self.t_est / self.est. Metrics of the plugin's own
    # say which way is better (or the target value a consistent filter gives), the unit, and the tolerance.
    metrics = {
        **specs("robot_final_error_m", "poses_scored"),
        "speed_rmse_mps": MetricSpec.measured("lower", "m/s", "RMS error of the estimated speed against ground truth"),
        "yaw_rate_rmse_degps": MetricSpec.measured("lower", "deg/s", "RMS error of the estimated turn rate"),
        "odom_speed_rmse_mps": MetricSpec.measured("none", "m/s", "the same for raw odometry: the baseline"),
        "odom_yaw_rate_rmse_degps": MetricSpec.measured("none", "deg/s", "the same for raw odometry: the baseline"),
        "mean_nis": MetricSpec.measured("target", "", "mean normalised innovation squared (2 when the noise is right)",
                                        target=2.0),
    }
    # `--preset follow-odometry`: acceleration so loose that the filter reproduces dead reckoning.
    presets = {"paper": {}, "follow-odometry": {"accel_sigma_mps2": 1e3, "yaw_accel_sigma_radps2": 1e3}}

    def __init__(self, config: CvFilterConfig, ctx: ReplayContext) -> None:
        super().__init__(config, ctx)
        start = ctx.T_world_start if ctx.T_world_start is not None else np.zeros(3)
        self.filter = ConstantVelocityFilter(start, config.noise())
        self.trail = TrajectoryLog(ctx.observer, "world/trajectory/estimate")
        self.truth = TrajectoryLog(ctx.observer, "world/trajectory/truth")
        self.last: tuple[int, np.ndarray] | None = None
        self.t_est: list[int] = []  # Pipeline.trajectory() reads t_est and est: trajectory.tum
        self.est: list[np.ndarray] = []
        self.vel: list[tuple[float, float, float, float]] = []  # estimated v, w; measured v, w (per interval)
        self.nis: list[float] = []
        self.t_gt: list[int] = []
        self.gt: list[np.ndarray] = []

    def step(self, env: Envelope) -> None:
        msg, obs = env.msg, self.ctx.observer
        if isinstance(msg, GroundTruthPose):
            self.t_gt.append(env.log_time_ns)
            self.gt.append(msg.xy_yaw)
            self.truth.append(msg.x_m, msg.y_m)
            return
        if not isinstance(msg, OdometryPose):
            return
        if self.last is None:
            self.last = (env.log_time_ns, msg.xy_yaw)
            self._record(env.log_time_ns)
            return
        t_prev, pose_prev = self.last
        dt = (env.log_time_ns - t_prev) * 1e-9
        if dt <= 0:
            self.ctx.log(f"odometry at {env.log_time_ns} ns does not advance in time: skipped")
            return
        u = between1(pose_prev, msg.xy_yaw)
        result = self.filter.step(u, dt)
        self.last = (env.log_time_ns, msg.xy_yaw)
        measured = mean_velocity(float(u[0]), float(u[1]), float(u[2]), dt)
        self.vel.append((float(result.mean[3]), float(result.mean[4]), *measured))
        self.nis.append(result.nis)
        self._record(env.log_time_ns)
        obs.log("cv/speed_mps", Scalar(float(result.mean[3])))
        obs.log("cv/yaw_rate_radps", Scalar(float(result.mean[4])))
        obs.log("cv/nis", Scalar(result.nis))
        obs.log("world/robot/covariance", CovarianceEllipses(result.mean[None, :2], result.cov[None, :2, :2]))

    def _record(self, t_ns: int) -> None:
        pose = self.filter.mean[:3].copy()
        self.t_est.append(t_ns)
        self.est.append(pose)
        self.ctx.observer.log("world/robot", Pose(pose))
        self.trail.append(float(pose[0]), float(pose[1]))

    def finish(self) -> dict[str, float]:
        self.trail.finish()
        self.truth.finish()
        metrics: dict[str, float] = {}
        if self.nis:
            metrics["mean_nis"] = float(np.mean(self.nis))
        t_est = np.asarray(self.t_est, np.int64)
        est = np.asarray(self.est, np.float64).reshape(-1, 3)
        t_gt = np.asarray(self.t_gt, np.int64)
        gt = np.asarray(self.gt, np.float64).reshape(-1, 3)
        pos_err, _ = position_errors(t_est, est, t_gt, gt)
        metrics["poses_scored"] = float(len(pos_err))
        if not len(pos_err):
            self.ctx.log("no ground truth overlaps the odometry: the accuracy metrics do not apply")
            return metrics
        metrics["robot_final_error_m"] = float(pos_err[-1])
        metrics.update(self._velocity_errors(t_est, t_gt, gt))
        return metrics

    def _velocity_errors(self, t_est: np.ndarray, t_gt: np.ndarray, gt: np.ndarray) -> dict[str, float]:
        """Speed and turn-rate errors over the odometry intervals inside the ground truth's span."""
        if len(gt) < 2 or not self.vel:
            return {}
        inside = (t_est[:-1] >= t_gt[0]) & (t_est[1:] <= t_gt[-1])
        if not inside.any():
            return {}
        t0 = t_gt[0]
        tg, te = (t_gt - t0).astype(np.float64), (t_est - t0).astype(np.float64)
        yaw = np.unwrap(gt[:, 2])
        ref = np.column_stack([np.interp(te, tg, gt[:, 0]), np.interp(te, tg, gt[:, 1]), np.interp(te, tg, yaw)])
        incs = [between1(ref[k], ref[k + 1]) for k in range(len(te) - 1)]
        truth = np.array([mean_velocity(float(u[0]), float(u[1]), float(u[2]), (te[k + 1] - te[k]) * 1e-9)
                          for k, u in enumerate(incs)])
        vel = np.asarray(self.vel)
        est_err, odo_err = vel[:, :2] - truth, vel[:, 2:] - truth
        return {"speed_rmse_mps": rmse(est_err[inside, 0]),
                "yaw_rate_rmse_degps": math.degrees(rmse(est_err[inside, 1])),
                "odom_speed_rmse_mps": rmse(odo_err[inside, 0]),
                "odom_yaw_rate_rmse_degps": math.degrees(rmse(odo_err[inside, 1]))}

    def artifacts(self) -> dict[str, bytes]:
        """``velocity.csv``: per odometry interval, the estimated and the measured speed and turn rate."""
        out = io.StringIO()
        out.write("t_ns,speed_mps,yaw_rate_radps,odom_speed_mps,odom_yaw_rate_radps\n")
        for t, row in zip(self.t_est[1:], self.vel, strict=True):
            out.write(f"{t}," + ",".join(f"{x:.9g}" for x in row) + "\n")
        return {"velocity.csv": out.getvalue().encode()}
