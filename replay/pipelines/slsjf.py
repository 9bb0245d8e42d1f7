"""Pipeline ``slsjf``: the Sparse Local Submap Joining Filter, D-SLAM's authors' answer to sparse sightings.

D-SLAM (``dslam``) maps through measurements recast between features seen together; where scans see
one feature at a time (Victoria Park: nine in ten scans) it maps almost nothing. Its authors' next
algorithm (Huang, Wang, Dissanayake, IEEE T-RO 24(5), 2008) keeps D-SLAM's exactly sparse
information map but feeds it small local maps built by EKF-SLAM instead of single scans: every
sighting counts, and the global information matrix stays sparse because each local map only links
its start pose, end pose and its features (``algorithms/slsjf``). ``linearization=iterated`` is
I-SLSJF (Huang, Wang, Dissanayake, Frese, ACRA 2008): every local map re-linearized at the current
estimate at each join, for consistency; ``--preset paper`` is the 2008 filter, linearized once.
``local_map_estimate=smoothed`` (beyond the papers) re-solves each local map by least squares over its own scans
before it is joined.

Same noise keys, drawing and metrics as ``dslam`` and ``ekfslam``
(:mod:`slamreplay.replay.pipelines.landmark_slam`), plus the local maps' size and how often they are joined.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any, ClassVar, Literal

import numpy as np
import rerun.blueprint as rrb

from slamreplay.algorithms.common import se2
from slamreplay.algorithms.ekfslam import EkfSlamConfig
from slamreplay.algorithms.observe import Image, LineStrips, Points, Scalar
from slamreplay.algorithms.slsjf import Slsjf, SlsjfConfig
from slamreplay.algorithms.slsjf.joining import sparsity_image
from slamreplay.replay.engine import views
from slamreplay.replay.metric_registry import specs
from slamreplay.replay.pipelines.landmark_slam import METRICS, LandmarkSlamConfig, LandmarkSlamPipeline


@dataclass(frozen=True, slots=True)
class SlsjfPipelineConfig(LandmarkSlamConfig):
    """The parameters shared with ``dslam`` and ``ekfslam``, the local maps' size and the linearization."""

    local_map_scans: int = field(default=30, metadata={"help": (
        "a local map ends after this many scans (or local_map_distance_m, whichever comes first) and is "
        "joined into the global map")})
    local_map_distance_m: float = field(default=30.0, metadata={"help": (
        "a local map ends after the robot drove this far (m) (or local_map_scans)")})
    linearization: Literal["once", "iterated"] = field(default="iterated", metadata={"help": (
        "once: each local map linearized when it is joined (SLSJF, the 2008 paper); iterated: every local map "
        "re-linearized at each join until Gauss-Newton converges (I-SLSJF, beyond the paper)")})
    max_iterations: int = field(default=10, metadata={"help": (
        "Gauss-Newton iterations at most per join (linearization=iterated)")})
    robot_estimate: Literal["joined", "tracked", "composed"] = field(default="joined", metadata={"help": (
        "composed: the robot is its local map's start frame composed with the local estimate (the 2008 paper, "
        "eq. 13), so it sees the global map only at joins; joined: the robot as joining the current local map now "
        "would place it, the local map fused with the global map's marginal over its start frame and the features "
        "both hold (beyond the paper, exact to first order); tracked: a pose filter in the global frame, updated at "
        "every scan by the sightings of features already in the global map and fused with the composed estimate, "
        "both by Covariance Intersection (beyond the paper, conservative). The maps are the same either way")})
    local_map_estimate: Literal["ekf", "smoothed"] = field(default="ekf", metadata={"help": (
        "ekf: a local map is joined with its EKF's estimate and covariance (the paper); smoothed: at its join the "
        "local map is re-solved by least squares over all its scans' poses and its features, from the EKF's "
        "estimate and with the EKF's associations, and joined with the covariance at that optimum (beyond the "
        "paper: the EKF's linearization errors stay out of the global map; better on simulated data and on two "
        "MRCLAM robots, worse on two others: docs/dslam.md)")})
    state_recovery: Literal["direct", "pcg"] = field(default="direct", metadata={"help": (
        "direct: the global estimate and the covariance columns the robot and the gates need come from a sparse "
        "factorization of the information matrix, redone at each join (the paper); pcg: from preconditioned "
        "conjugate gradients started at the previous join's values, as D-SLAM recovers its map (no factor held; "
        "the same map to micrometres; its cost: docs/dslam.md)")})

    def __post_init__(self) -> None:
        LandmarkSlamConfig.__post_init__(self)
        self.algorithm("known")

    def algorithm(self, mode: str) -> SlsjfConfig:
        local = EkfSlamConfig(odometry_noise=self.odometry_noise(), default_range_sigma_m=self.range_sigma_m,
                              default_bearing_sigma_rad=self.bearing_sigma_rad, association=mode,  # type: ignore[arg-type]
                              association_params=self.association_params())
        return SlsjfConfig(local, self.local_map_scans, self.local_map_distance_m, self.linearization,
                           self.max_iterations, self.robot_estimate, self.local_map_estimate, self.state_recovery)


class SlsjfPipeline(LandmarkSlamPipeline):
    name = "slsjf"
    summary = ("SLSJF: EKF-SLAM local maps joined into a sparse information map (D-SLAM's authors, 2008); maps "
               "sparse sightings")
    prefix = "slsjf"
    Config = SlsjfPipelineConfig
    metrics = {**METRICS, **specs("local_maps")}
    summary_skip = (*views.SUMMARY_SKIP, "local_map")  # the local map being built is not part of the outcome
    presets: ClassVar[dict[str, dict[str, Any]]] = {"paper": {"linearization": "once", "robot_estimate": "composed"}}
    preset_notes: ClassVar[dict[str, str]] = {
        "linearization": "the 2008 paper linearizes each local map once, when it is joined; the default re-linearizes "
                         "all of them at each join (I-SLSJF, the authors' later paper), for consistency",
        "robot_estimate": "the paper's robot is its local map composed onto the start frame (eq. 13), which sees the "
                          "global map only at joins; the default fuses the local map with the global map's marginal "
                          "over its start frame and common features at every scan (the robot a join now would give), "
                          "which on sparse sightings keeps it closer",
    }

    def __init__(self, config: SlsjfPipelineConfig, ctx: Any) -> None:
        super().__init__(config, ctx)
        self.drawn_joins = 0

    def make_filter(self, mode: str) -> Slsjf:
        return Slsjf(self.config.algorithm(mode), observer=self.ctx.observer, clock=time.perf_counter)

    def tentative_means(self) -> np.ndarray | None:
        """Unknown ids: the local EKF's tentative features, in the global frame."""
        if self.mode != "unknown" or not len(self.filter.local.tentative.means):
            return None
        return np.asarray(se2.transform_points(self.filter.start_pose, self.filter.local.tentative.means))

    def observed_covariances(self, features: list[int]) -> np.ndarray | None:
        return self.filter.marginal_covariances(features) if features else None

    def observed_joint_covariance(self, features: list[int]) -> np.ndarray | None:
        return self.filter.joint_covariance(features) if features else None

    def draw_scan(self, result: Any, world_xy: np.ndarray) -> None:
        """The local map being built at every scan; the global map's frames, links and sparsity after a join."""
        sl, obs = self.filter, self.ctx.observer
        local = sl.local.estimates()
        if len(local):
            start_w = self.to_world_pose(sl.start_pose)
            obs.log("world/local_map/features", Points(self.to_world_xy(
                np.array([se2.transform_points(sl.start_pose, p[None])[0] for p in local])), radius=0.12))
            obs.log("world/local_map/start", Points(start_w[None, :2], radius=0.15))
        if len(sl.map.maps) != self.drawn_joins:
            self.draw_joins()

    def draw_joins(self) -> None:
        """Local-map frames (end poses) linked in order, the information matrix's sparsity, the join counters."""
        obs, gm = self.ctx.observer, self.filter.map
        self.drawn_joins = len(gm.maps)
        frames = np.array([self.to_world_pose(gm.pose(k)) for k in range(gm.n_poses)]).reshape(-1, 3)
        obs.log("world/graph/local_map_frames", Points(frames[:, :2], radius=0.08))
        obs.log("world/graph/local_map_links", LineStrips((np.vstack([self.T[None, :2], frames[:, :2]]),)))
        obs.log("slsjf/information", Image(sparsity_image(gm.information())))
        obs.log("metrics/slsjf/local_maps", Scalar(float(len(gm.maps))))
        obs.log("metrics/slsjf/gauss_newton_iterations", Scalar(float(gm.iterations[-1])))
        if gm.recovery == "pcg" and gm.pcg_iterations:  # the join's state solves, one per Gauss-Newton iteration
            obs.log("metrics/slsjf/pcg_iterations", Scalar(float(sum(gm.pcg_iterations[-gm.iterations[-1]:]))))

    def finalize(self) -> None:
        """Join the last local map, so that every sighting is in the global map that is scored."""
        self.filter.join()
        if len(self.filter.map.maps) != self.drawn_joins:
            self.draw_joins()
        if self.mode == "unknown":
            self.ctx.log(f"unknown ids: {self.filter.associated} local-map features matched to the global map's, "
                         f"{self.filter.ambiguous} ambiguous (left out of the global map)")
        gm = self.filter.map
        if gm.recovery == "pcg" and gm.pcg_iterations:
            cols = gm.column_iterations
            self.ctx.log(f"state_recovery=pcg: {len(gm.pcg_iterations)} state solves, {np.mean(gm.pcg_iterations):.1f} "
                         f"CG iterations each on average; {len(cols)} covariance solves"
                         + (f", {np.mean(cols):.1f} iterations each" if cols else "")
                         + f"; {gm.fallbacks} redone by a direct factorization (not converged in "
                         f"{gm.pcg_max_iterations} iterations)")

    def extra_metrics(self) -> dict[str, float]:
        return {"local_maps": float(len(self.filter.map.maps))}

    @classmethod
    def internals(cls) -> tuple[rrb.View | rrb.Container, ...]:
        return (views.image_view("Global information matrix sparsity (local-map end poses and features, in the order "
                                 "they were added)", "/slsjf/information"),
                rrb.Vertical(views.series_view("Local maps joined", "metrics/slsjf/local_maps"),
                             views.series_view("Iterations per join: Gauss-Newton (I-SLSJF), conjugate gradients "
                                               "(state_recovery=pcg)", "metrics/slsjf/gauss_newton_iterations",
                                               "metrics/slsjf/pcg_iterations")))
