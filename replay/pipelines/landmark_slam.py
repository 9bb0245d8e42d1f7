"""What the ``dslam`` and ``ekfslam`` pipelines share: adapting messages, drawing, scoring.

Odometry messages become increments ``⊖o_{k-1} ⊕ o_k`` for the filter's prediction; scans go to
its update with their ids (known-id mode) or without (unknown-id mode; the true ids, when the
recording has them, are kept for scoring only). The filter works in its map frame, the initial
robot frame of the paper; everything is drawn and scored in the world frame through the known
transform ``T_world_start`` (the ground-truth pose at the first odometry message): no fitted
alignment, so every error the filter makes, including in its first pose, is counted.

Landmarks are matched with the truth by id in known-id mode, and one-to-one by position (a
linear assignment within ``match_radius_m``) in unknown-id mode; a mapped feature with no
match is a false landmark. NEES values are the plain squared Mahalanobis error, whose
expected value for a consistent estimate is 2 for a landmark and 3 for the robot pose. The robot NEES at
each scan and its band are also written to the run's ``nees.json`` (``replay.evaluation.nees_series``).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any, ClassVar, Literal, cast

import numpy as np
import rerun.blueprint as rrb
from scipy.optimize import linear_sum_assignment

from slamreplay.algorithms.common import se2
from slamreplay.algorithms.common.association import AssociationConfig
from slamreplay.algorithms.common.motion import OdometryNoise, between1, compose1
from slamreplay.algorithms.observe import CovarianceEllipses, Points, Pose, Scalar, Segments
from slamreplay.recorder.messages import (
    TOPIC_GROUND_TRUTH_LANDMARKS,
    TOPIC_GROUND_TRUTH_POSE,
    TOPIC_ODOM,
    TOPIC_RANGE_BEARING,
    GroundTruthPose,
    LandmarkMap,
    OdometryPose,
    RangeBearingScan,
)
from slamreplay.recorder.sensor_model import SensorModel
from slamreplay.replay.engine import views
from slamreplay.replay.engine.pipeline import Pipeline, ReplayContext, ground_truth_is_estimate
from slamreplay.replay.engine.reader import Envelope
from slamreplay.replay.engine.trajectory import TrajectoryLog
from slamreplay.replay.errors import ReplayError
from slamreplay.replay.evaluation.metrics import mean_nees_band, position_errors
from slamreplay.replay.evaluation.nees_series import NEES_ARTIFACT, NeesSeries, chi2_band, nees_artifact
from slamreplay.replay.metric_registry import specs

Association = Literal["auto", "known", "unknown"]


def world_pose(T: np.ndarray, pose: np.ndarray) -> np.ndarray:
    """A pose of the filter's frame in the world frame (``T``: the filter frame's world pose)."""
    return compose1(T, pose)


def world_xy(T: np.ndarray, xy: np.ndarray) -> np.ndarray:
    return se2.transform_points(T, np.asarray(xy, dtype=np.float64).reshape(-1, 2))


def world_cov(T: np.ndarray, cov: np.ndarray) -> np.ndarray:
    rot = se2.rot(T[2])
    return cast(np.ndarray, rot @ cov @ rot.T)


def truth_pose_at(t: int, t_gt: list[int], gt: list[np.ndarray], clamp: bool = False) -> np.ndarray | None:
    """Ground truth at ``t``, interpolated between the samples around it; outside their span None, or with
    ``clamp`` the nearest sample (a start a few ms before the first truth message)."""
    if not t_gt:
        return None
    if not clamp and (t < t_gt[0] or t > t_gt[-1]):
        return None
    tg = np.asarray(t_gt, dtype=np.int64)
    k = int(np.searchsorted(tg, t))
    if k >= len(tg):
        return np.asarray(gt[-1], dtype=np.float64)
    if tg[k] == t or k == 0:
        return np.asarray(gt[k], dtype=np.float64)
    pose: np.ndarray = se2.interpolate([float(t - tg[k - 1])], [0.0, float(tg[k] - tg[k - 1])],
                                       np.stack([gt[k - 1], gt[k]]))[0]
    return pose


def landmark_scores(world_xy: np.ndarray, truth_xy: np.ndarray, pairs: list[tuple[int, int]],
                    world_covs: Any) -> dict[str, float]:
    """``false_landmarks``, and for the (feature, truth) ``pairs`` the landmark RMSE and mean NEES;
    ``world_covs(f_idx)`` gives the paired features' world-frame covariances (k, 2, 2)."""
    out = {"false_landmarks": float(len(world_xy) - len(pairs))}
    if pairs:
        f_idx, t_idx = np.array(pairs).T
        err = world_xy[f_idx] - truth_xy[t_idx]
        covs = world_covs(f_idx)
        out["landmark_rmse_m"] = float(np.sqrt(np.mean(np.sum(err**2, axis=1))))
        out["landmark_nees_mean"] = float(np.mean(np.einsum("ni,nij,nj->n", err, np.linalg.inv(covs), err)))
    return out


@dataclass(frozen=True, slots=True)
class LandmarkSlamConfig:
    """Inputs and noise models shared by the landmark SLAM pipelines."""

    association: Association = field(default="auto", metadata={"help": (
        "pair readings by landmark id (known), by the gates below (unknown), or auto: known when the first "
        "non-empty scan has all ids")})
    # odometry noise (algorithms/common/motion.py): Var(dx) = Var(dy) = s_t^2 d, Var(dtheta) = s_h^2 d + s_r^2 |dtheta|
    translation_sigma_per_sqrt_m: float = field(default=0.02, metadata={"help": (
        "odometry x and y noise sigma per sqrt(metre) driven (m/sqrt(m)); 0: none")})
    heading_sigma_per_sqrt_m: float = field(default=0.02, metadata={"help": (
        "odometry heading noise sigma per sqrt(metre) driven (rad/sqrt(m)); 0: none")})
    heading_sigma_per_sqrt_rad: float = field(default=0.05, metadata={"help": (
        "odometry heading noise sigma per sqrt(radian) turned (rad/sqrt(rad)); 0: none")})
    range_sigma_m: float = field(default=0.15, metadata={"help": (
        "range noise sigma (m) of scans that state none (0); a value the user sets overrides every scan's")})
    bearing_sigma_rad: float = field(default=0.02, metadata={"help": (
        "bearing noise sigma (rad) of scans that state none (0); a value the user sets overrides every scan's")})
    gate_probability: float = field(default=0.99, metadata={"help": (
        "unknown ids: chi-square gate probability for pairing a reading with a mapped or tentative feature")})
    new_feature_probability: float = field(default=0.9999, metadata={"help": (
        "unknown ids: an unpaired reading starts a tentative feature only outside this gate of every mapped one")})
    confirm_hits: int = field(default=3, metadata={"help": (
        "unknown ids: sightings that move a tentative feature into the map")})
    tentative_window_scans: int = field(default=25, metadata={"help": (
        "unknown ids: a tentative feature not seen again within this many scans is forgotten")})
    outlier_probability: float = field(default=1.0, metadata={"help": (
        "beyond the paper, known ids: drop a reading outside this chi-square gate of its prediction; 1: keep all")})
    map_every_scans: int = field(default=25, metadata={"help": (
        "draw every landmark with its 2-sigma ellipse every this many scans (and at the end)")})
    match_radius_m: float = field(default=1.0, metadata={"help": (
        "scoring, unknown ids: features pair one-to-one with true landmarks within this (m); unpaired ones are false")})

    def __post_init__(self) -> None:
        if self.map_every_scans < 1:
            raise ValueError(f"map_every_scans must be >= 1, got {self.map_every_scans}")
        if not self.match_radius_m > 0:
            raise ValueError(f"match_radius_m must be > 0, got {self.match_radius_m}")
        self.odometry_noise()
        self.association_params()

    def odometry_noise(self) -> OdometryNoise:
        return OdometryNoise(self.translation_sigma_per_sqrt_m, self.heading_sigma_per_sqrt_m,
                             self.heading_sigma_per_sqrt_rad)

    def association_params(self) -> AssociationConfig:
        return AssociationConfig(self.gate_probability, self.new_feature_probability, self.confirm_hits,
                                 self.tentative_window_scans, self.outlier_probability)


METRICS = specs("landmark_rmse_m", "landmark_nees_mean", "robot_final_error_m", "robot_nees_mean",
                "landmarks_mapped", "landmarks_true", "false_landmarks", "data_association_errors", "steps")


# A recording whose sensor model states outliers gets this known-id outlier gate: a consistent observation
# fails it with probability 1e-4, far below any real outlier rate (MRCLAM: 1-3 % beyond 0.5 m).
OUTLIER_GATE_PROBABILITY = 0.9999


ROBOT_NEES_BAND = chi2_band(3)  # one pose NEES, 3 dof, 95 %: the .rrd's band and nees.json's


def pose_nees(T: np.ndarray, truth: np.ndarray, pose: np.ndarray, cov: np.ndarray) -> float | None:
    """NEES of a map-frame ``pose`` with covariance ``cov`` against the world-frame ``truth`` (``T``: the map
    frame's world pose); None when ``cov`` is not positive definite."""
    if not np.all(np.linalg.eigvalsh(cov) > 0):
        return None
    e = se2.between(T, truth) - pose
    e[2] = se2.wrap_angle(e[2])
    return float(e @ np.linalg.solve(cov, e))


class LandmarkSlamPipeline(Pipeline):
    """Shared adapter; subclasses build the filter and add their own drawing and metrics."""

    required_topics = (TOPIC_ODOM, TOPIC_RANGE_BEARING)
    optional_topics = (TOPIC_GROUND_TRUTH_POSE, TOPIC_GROUND_TRUTH_LANDMARKS)
    start_topic = TOPIC_ODOM
    prefix: ClassVar[str]

    def __init__(self, config: LandmarkSlamConfig, ctx: ReplayContext) -> None:
        super().__init__(config, ctx)
        self.T = ctx.T_world_start if ctx.T_world_start is not None else np.zeros(3)
        self.filter: Any = None  # built at the first scan, once the association mode is known
        self.mode: str | None = None if config.association == "auto" else config.association
        self.traj = {k: TrajectoryLog(ctx.observer, f"world/trajectory/{k}") for k in ("estimate", "odometry", "truth")}
        self.prev_odom: np.ndarray | None = None
        self.first_odom: np.ndarray | None = None
        self.pending: list[np.ndarray] = []  # increments that arrived before the filter was built
        self.t_est: list[int] = []
        self.est: list[np.ndarray] = []
        self.t_gt: list[int] = []
        self.gt: list[np.ndarray] = []
        self.truth_ids: np.ndarray | None = None
        self.truth_xy: np.ndarray | None = None
        self.scan_poses: list[tuple[int, np.ndarray, np.ndarray]] = []
        self.scans = 0
        self.dropped_unknown = 0
        self.labels: list[int] = []  # true id of the observation that created each feature (unknown mode)
        self.da_errors = 0
        self.da_checked = 0
        self.step_s: list[float] = []  # per scan: the filter's observe()
        self.predict_s: list[float] = []
        # The ground truth is an estimate from the same measurements (Victoria Park's batch optimum): a consistent
        # filter's error from it has covariance P - P_opt (the optimum is efficient), so its NEES against it lies
        # between 0 and the upper end of the band it would have against the truth.
        self.estimated_truth = ground_truth_is_estimate(ctx.info)
        self.said_estimated = False
        self.robot_nees_t: list[int] = []  # per scan with ground truth: what robot_nees_mean averages (nees.json)
        self.robot_nees: list[float] = []

    @classmethod
    def config_from_sensor_model(cls, model: SensorModel) -> dict[str, Any]:
        """The odometry and range-bearing noise keys by name, and the outlier gate when outliers are stated."""
        values = super().config_from_sensor_model(model)
        if model.outlier_rate:
            values["outlier_probability"] = OUTLIER_GATE_PROBABILITY
        return values

    # -- to be provided by subclasses
    def make_filter(self, mode: str) -> Any:
        raise NotImplementedError

    def observed_covariances(self, features: list[int]) -> np.ndarray | None:
        """Marginal covariances (k, 2, 2) of observed features in the map frame, or None."""
        return None

    def observed_joint_covariance(self, features: list[int]) -> np.ndarray | None:
        """Joint covariance (2k, 2k) of observed features in the map frame, or None (the NEES band then
        treats them as independent)."""
        return None

    def draw_scan(self, result: Any, world_xy: np.ndarray) -> None:
        """Subclass drawing at each scan (``world_xy``: all feature estimates in the world frame)."""

    def extra_metrics(self) -> dict[str, float]:
        return {}

    # -- frames
    def to_world_pose(self, pose: np.ndarray) -> np.ndarray:
        return world_pose(self.T, pose)

    def to_world_xy(self, xy: np.ndarray) -> np.ndarray:
        return world_xy(self.T, xy)

    def to_world_cov(self, cov: np.ndarray) -> np.ndarray:
        return world_cov(self.T, cov)

    # -- messages
    def step(self, env: Envelope) -> None:
        msg = env.msg
        if isinstance(msg, OdometryPose):
            self._odometry(env.log_time_ns, msg.xy_yaw)
        elif isinstance(msg, RangeBearingScan):
            self._scan(env.log_time_ns, msg)
        elif isinstance(msg, GroundTruthPose):
            self.t_gt.append(env.log_time_ns)
            self.gt.append(msg.xy_yaw)
            self.traj["truth"].append(msg.x_m, msg.y_m)
        elif isinstance(msg, LandmarkMap):
            if self.estimated_truth and not self.said_estimated:
                self.said_estimated = True
                self.ctx.log("the ground truth is an estimate from these same measurements, not the truth: a "
                             "consistent filter's NEES against it lies between 0 and its band's upper end (the lower "
                             "end is drawn at 0)")
            self.truth_ids, self.truth_xy = np.asarray(msg.landmark_ids), np.asarray(msg.positions_m)
            labels = tuple(str(i) for i in self.truth_ids.tolist())
            self.ctx.observer.log_static("world/landmarks/truth", Points(self.truth_xy, labels=labels, radius=0.06))

    def _odometry(self, t: int, odom: np.ndarray) -> None:
        if self.first_odom is None:
            self.first_odom = odom
        if self.prev_odom is not None:
            u = between1(self.prev_odom, odom)
            if self.filter is None:
                self.pending.append(u)
            else:
                tic = time.perf_counter()
                self.filter.predict(u)
                self.predict_s.append(time.perf_counter() - tic)
        self.prev_odom = odom
        dead = self.to_world_pose(between1(self.first_odom, odom))
        self.traj["odometry"].append(float(dead[0]), float(dead[1]))
        pose = self.to_world_pose(self.filter.pose) if self.filter is not None else dead
        self.t_est.append(t)
        self.est.append(pose)
        self.traj["estimate"].append(float(pose[0]), float(pose[1]))

    def _scan(self, t: int, msg: RangeBearingScan) -> None:
        ids = np.asarray(msg.landmark_ids)
        if self.mode is None:
            if not len(ids):
                return
            self.mode = "known" if np.all(ids >= 0) else "unknown"
            self.ctx.log(f"association mode: {self.mode} ids (chosen from the first non-empty scan)")
        if self.filter is None:
            self.filter = self.make_filter(self.mode)
            for u in self.pending:
                self.filter.predict(u)
        if self.mode == "known" and len(ids) and not np.any(ids >= 0) and self.ctx.user_set("association"):
            raise ReplayError(f"association=known was set, but the scan at {t} ns carries no landmark ids (-1): "
                              f"its observations cannot be used; set association=unknown (or auto)")
        keep = ids >= 0 if self.mode == "known" else np.ones(len(ids), dtype=bool)
        self.dropped_unknown += int(np.sum(~keep))
        r, b, ids = msg.ranges_m[keep], msg.bearings_rad[keep], ids[keep]
        tic = time.perf_counter()
        # a sigma the scan states is used unless the user set one (which always wins); 0 means "not stated",
        # and the filter falls back to the config's value
        sr = self.config.range_sigma_m if self.ctx.user_set("range_sigma_m") else msg.range_sigma_m
        sb = self.config.bearing_sigma_rad if self.ctx.user_set("bearing_sigma_rad") else msg.bearing_sigma_rad
        res = self.filter.observe(r, b, ids if self.mode == "known" else None, sr, sb)
        self.step_s.append(time.perf_counter() - tic)
        self.scans += 1
        self._score_association(res, ids)
        self._draw(t, res)

    def _score_association(self, res: Any, ids: np.ndarray) -> None:
        if self.mode != "unknown":
            return
        created = set(res.new_features)
        for j, f in enumerate(res.features.tolist()):
            if f < 0:
                continue
            if f in created:
                self.labels.extend([-1] * (f + 1 - len(self.labels)))
                self.labels[f] = int(ids[j])
            elif ids[j] >= 0 and self.labels[f] >= 0:
                self.da_checked += 1
                self.da_errors += int(self.labels[f] != ids[j])

    def _draw(self, t: int, res: Any) -> None:
        obs = self.ctx.observer
        pose_w = self.to_world_pose(res.pose)
        self.scan_poses.append((t, res.pose, res.pose_cov))
        obs.log("world/robot", Pose(pose_w))
        obs.log("world/robot/covariance",
                CovarianceEllipses(pose_w[None, :2], self.to_world_cov(res.pose_cov[:2, :2])[None]))
        pred_w = self.to_world_pose(res.prediction)
        obs.log("world/robot/prediction", Pose(pred_w))
        obs.log("world/robot/prediction/covariance",
                CovarianceEllipses(pred_w[None, :2], self.to_world_cov(res.prediction_cov[:2, :2])[None]))
        world_xy = self.to_world_xy(self.filter.estimates())
        seen = [f for f in res.features.tolist() if f >= 0]
        obs.log("world/associations", Segments(np.repeat(pose_w[None, :2], len(seen), 0), world_xy[seen]))
        covs = self.observed_covariances(seen)
        if covs is not None and seen:
            obs.log("world/landmarks/observed", CovarianceEllipses(world_xy[seen], self.to_world_cov(covs)))
            self._landmark_nees(seen, world_xy, covs, res)
        tent = self.tentative_means()
        if tent is not None:
            obs.log("world/landmarks/tentative", Points(self.to_world_xy(tent), radius=0.05))
        self._robot_nees(t, res)
        if self.scans % self.config.map_every_scans == 0:
            self.draw_map(world_xy)
        self.draw_scan(res, world_xy)

    def tentative_means(self) -> np.ndarray | None:
        tentative = getattr(self.filter, "tentative", None)
        return None if tentative is None or self.mode != "unknown" else tentative.means

    def draw_map(self, world_xy: np.ndarray) -> None:
        """Every landmark with its 2-sigma ellipse (exact marginals: costly, hence the interval)."""
        labels = tuple(str(i) for i in self.filter.feature_ids) if self.mode == "known" else None
        self.ctx.observer.log("world/landmarks/estimate", Points(world_xy, labels=labels, radius=0.07))
        if len(world_xy):
            covs = self.to_world_cov(self.filter.marginal_covariances())
            self.ctx.observer.log("world/landmarks/estimate/covariance", CovarianceEllipses(world_xy, covs))

    def _truth_pose_at(self, t: int) -> np.ndarray | None:
        return truth_pose_at(t, self.t_gt, self.gt)

    def robot_nees_band(self) -> tuple[float, float]:
        """The band of a consistent filter's robot NEES, drawn in the .rrd and written to nees.json: its lower end
        0 when the ground truth is an estimate from the same measurements."""
        return (0.0 if self.estimated_truth else ROBOT_NEES_BAND[0]), ROBOT_NEES_BAND[1]

    def _robot_nees(self, t: int, res: Any) -> None:
        truth = self._truth_pose_at(t)
        nees = None if truth is None else pose_nees(self.T, truth, res.pose, res.pose_cov)
        if nees is None:
            return
        obs = self.ctx.observer
        low, high = self.robot_nees_band()
        obs.log("metrics/robot_nees", Scalar(nees))
        obs.log("metrics/nees_band/robot_95_low", Scalar(low))
        obs.log("metrics/nees_band/robot_95_high", Scalar(high))

    def _landmark_nees(self, seen: list[int], world_xy: np.ndarray, covs: np.ndarray, res: Any) -> None:
        truth = self._truth_of(seen)
        if truth is None:
            return
        ok = ~np.isnan(truth[:, 0])
        if ok.any():
            e = (world_xy[seen] - truth)[ok]
            c = self.to_world_cov(covs[ok])
            obs = self.ctx.observer
            obs.log("metrics/landmark_nees", Scalar(float(np.mean(np.einsum("ni,nij,nj->n", e, np.linalg.inv(c), e)))))
            # The band of the mean NEES of a consistent filter: from the features' joint covariance (they
            # share errors, replay.metrics.mean_nees_band), else chi2(2k) / k as if they were independent.
            k = int(ok.sum())
            joint = self.observed_joint_covariance([f for f, good in zip(seen, ok.tolist(), strict=True) if good])
            if joint is not None:
                low, high = mean_nees_band(joint)
            else:
                low, high = (v / k for v in chi2_band(2 * k))
            obs.log("metrics/nees_band/landmark_95_low", Scalar(0.0 if self.estimated_truth else low))
            obs.log("metrics/nees_band/landmark_95_high", Scalar(high))

    def _truth_of(self, features: list[int]) -> np.ndarray | None:
        """True world positions (k, 2) of features by id or label (NaN where unknown); None without a truth map."""
        if self.truth_xy is None or self.truth_ids is None:
            return None
        lookup = {int(i): k for k, i in enumerate(self.truth_ids.tolist())}
        keys = self.filter.feature_ids if self.mode == "known" else self.labels
        out = np.full((len(features), 2), np.nan)
        for j, f in enumerate(features):
            k = lookup.get(keys[f]) if f < len(keys) else None
            if k is not None:
                out[j] = self.truth_xy[k]
        return out

    # -- the end
    def finish(self) -> dict[str, float]:
        for traj in self.traj.values():
            traj.finish()
        metrics: dict[str, float] = {"steps": float(self.scans)}
        if self.dropped_unknown:
            self.ctx.log(f"known-id mode: {self.dropped_unknown} observations without an id were dropped")
        if self.filter is None:
            self.ctx.log("no scan with observations: nothing was mapped")
            return metrics
        if self.filter.rejected:
            self.ctx.log(f"known ids: {self.filter.rejected} observations failed the outlier gate and were not used")
        self.finalize()
        world_xy = self.to_world_xy(self.filter.estimates())
        self.draw_map(world_xy)
        metrics.update(self._robot_metrics())
        metrics.update(self._landmark_metrics(world_xy))
        if self.mode == "unknown" and self.da_checked:
            metrics["data_association_errors"] = float(self.da_errors)
            self.ctx.log(f"data association: {self.da_errors} wrong of {self.da_checked} checked "
                         f"({100.0 * self.da_errors / self.da_checked:.3f} %)")
        metrics.update(self.extra_metrics())
        return metrics

    def finalize(self) -> None:
        """Last exact solve before scoring (D-SLAM); nothing by default."""

    def _robot_metrics(self) -> dict[str, float]:
        t_est, est = np.asarray(self.t_est, dtype=np.int64), np.asarray(self.est).reshape(-1, 3)
        t_gt, gt = np.asarray(self.t_gt, dtype=np.int64), np.asarray(self.gt).reshape(-1, 3)
        pos_err, _ = position_errors(t_est, est, t_gt, gt)
        if not len(pos_err):
            return {}
        out = {"robot_final_error_m": float(pos_err[-1])}  # the ATE is ape_rmse_m (replay.evaluate)
        # Against the whole ground truth (at a scan the replay may not have read the truth after it yet, so the
        # .rrd's series can miss a few): these values are nees.json's, and the metric is their mean.
        self.robot_nees_t, self.robot_nees = [], []
        for t, pose, cov in self.scan_poses:
            truth = self._truth_pose_at(t)
            nees = None if truth is None else pose_nees(self.T, truth, pose, cov)
            if nees is not None:
                self.robot_nees_t.append(t)
                self.robot_nees.append(nees)
        if self.robot_nees:
            out["robot_nees_mean"] = float(np.mean(self.robot_nees))
        return out

    def artifacts(self) -> dict[str, bytes]:
        """``nees.json``: the robot pose NEES at each scan with ground truth and its band, when there is one."""
        if not self.robot_nees:
            return {}
        series = NeesSeries("robot pose NEES at each scan (3 when consistent)", 3, self.robot_nees_band(),
                            np.asarray(self.robot_nees_t, np.int64), np.asarray(self.robot_nees, np.float64),
                            metric="robot_nees_mean")
        return {NEES_ARTIFACT: nees_artifact({"robot": series})}

    def _landmark_metrics(self, world_xy: np.ndarray) -> dict[str, float]:
        n = len(world_xy)
        out = {"landmarks_mapped": float(n)}
        if self.truth_xy is None or self.truth_ids is None:
            return out
        out["landmarks_true"] = float(len(self.truth_ids))
        if self.mode == "known":
            lookup = {int(i): k for k, i in enumerate(self.truth_ids.tolist())}
            pairs = [(f, lookup[i]) for f, i in enumerate(self.filter.feature_ids) if i in lookup]
        else:
            d = np.hypot(*(world_xy[:, None, :] - self.truth_xy[None, :, :]).transpose(2, 0, 1))
            rows, cols = linear_sum_assignment(np.where(d <= self.config.match_radius_m, d, 1e9))
            pairs = [(int(f), int(k)) for f, k in zip(rows, cols, strict=True) if d[f, k] <= self.config.match_radius_m]
        out.update(landmark_scores(world_xy, self.truth_xy, pairs,
                                   lambda f: self.to_world_cov(self.filter.marginal_covariances()[f])))
        return out

    def timings(self) -> dict[str, float]:
        if not self.step_s:
            return {}
        steps = np.asarray(self.step_s)
        out = {"scan_step_mean_s": float(steps.mean()), "scan_step_p95_s": float(np.percentile(steps, 95)),
               "algorithm_total_s": float(steps.sum() + sum(self.predict_s))}
        if self.predict_s:
            out["predict_mean_s"] = float(np.mean(self.predict_s))
        profile = getattr(self.filter, "profile", {})
        for stage, values in sorted(profile.items()):
            out[f"{stage}_mean_s"] = float(np.mean(values))
            out[f"{stage}_total_s"] = float(np.sum(values))
        return out

    @classmethod
    def blueprint(cls, bounds: views.Bounds | None = None) -> rrb.Blueprint:
        nees = ("metrics/landmark_nees", "metrics/nees_band/landmark_95_low", "metrics/nees_band/landmark_95_high")
        robot = ("metrics/robot_nees", "metrics/nees_band/robot_95_low", "metrics/nees_band/robot_95_high")
        return views.layout(
            views.summary_tab(bounds, nees, "Landmark NEES (2 when consistent) and its 95 % band"),
            views.tab("Map over time", views.map_view("Map: estimate, truth, 2-sigma ellipses", "world", bounds),
                      rrb.Vertical(views.series_view("Landmark NEES of the observed features", *nees),
                                   views.series_view("Robot NEES (3 when consistent)", *robot)), columns=[3, 2]),
            views.tab("Filter internals", *cls.internals()),
            views.tab("Data", views.data_view()),
            views.tab("Log", views.log_view("Log", "log", cls.prefix)),
        )

    @classmethod
    def internals(cls) -> tuple[rrb.View | rrb.Container, ...]:
        """The views of the ``Filter internals`` tab."""
        return (views.image_view("Information matrix sparsity", f"/{cls.prefix}/information"),)
