"""Pipeline ``dslam``: D-SLAM (Wang, Huang, Dissanayake 2005) over odometry and range-bearing scans.

Draws, per scan: the odometry prediction, the measurement-based pose (eq. 12) and the CI result,
each with its 2-sigma ellipse; the anchors f_1, f_2 of the recast measurement; the associations;
the observed landmarks' ellipses; NEES, CI weight and solver iterations as time series. Every
``info_every_scans`` scans, and at the end: the links of the information matrix as segments
between features (the paper's Fig. 3c) and its block sparsity pattern as an image (Fig. 3d).
Metrics add ``info_nnz_blocks`` and ``info_nnz_blocks_per_landmark`` to the shared ones
(:mod:`slamreplay.replay.pipelines.landmark_slam`).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any, ClassVar, Literal

import numpy as np
import rerun.blueprint as rrb

from slamreplay.algorithms.dslam import DSlam, DSlamConfig, ScanStatus
from slamreplay.algorithms.dslam.localization import PoseStatus
from slamreplay.algorithms.observe import CovarianceEllipses, Image, Points, Pose, Scalar, Segments, State
from slamreplay.replay.engine import views
from slamreplay.replay.engine.pipeline import ReplayContext
from slamreplay.replay.metric_registry import specs
from slamreplay.replay.pipelines.landmark_slam import METRICS, LandmarkSlamConfig, LandmarkSlamPipeline


@dataclass(frozen=True, slots=True)
class DSlamPipelineConfig(LandmarkSlamConfig):
    """The shared parameters plus D-SLAM's (algorithms/dslam/filter.py DSlamConfig)."""

    ci_criterion: Literal["det", "trace"] = field(default="det", metadata={"help": (
        "Covariance Intersection (localization) weight minimising the fused pose covariance's det or trace")})
    recovery: Literal["local", "pcg", "direct"] = field(default="local", metadata={"help": (
        "map recovery x = I^-1 i: local solves with periodic global PCG, pcg (whole map every update) or direct")})
    global_every_scans: int = field(default=100, metadata={"help": (
        "recovery=local: a global PCG solve every this many map updates; 0: only when local solves fall short")})
    covariance_refresh_scans: int = field(default=0, metadata={"help": (
        "recompute nearby features' joint covariance exactly every this many scans; 0: when a scan sees < 2 of them")})
    loop_closure_gap_scans: int = field(default=300, metadata={"help": (
        "re-seeing a feature unseen for this many scans is a loop closure: a global solve then is direct, not PCG")})
    localization_gate_probability: float = field(default=0.9999, metadata={"help": (
        "beyond the paper: do not fuse a measurement pose failing this chi-square gate (its fit, or vs the "
        "prediction); 1: off")})
    map_gate_probability: float = field(default=0.9999, metadata={"help": (
        "beyond the paper: skip a recast map update whose innovation fails this chi-square gate; 1: off")})
    final_relinearization_iterations: int = field(default=10, metadata={"help": (
        "beyond the paper: Gauss-Newton steps relinearising every map measurement at the end; 0: the EIF estimate")})
    composite_max_scans: int = field(default=0, metadata={"help": (
        "beyond the paper, known ids: map the readings of up to this many consecutive scans as one; 0: off")})
    composite_max_distance_m: float = field(default=3.0, metadata={"help": (
        "composite scans: a scan leaves the window once this much travel (m) lies behind it")})
    composite_max_heading_sigma_rad: float = field(default=0.4, metadata={"help": (
        "composite scans: ... or once the odometry heading sigma (rad) accrued since it exceeds this")})
    info_every_scans: int = field(default=100, metadata={"help": (
        "draw the information matrix's links and sparsity image every this many scans (and at the end)")})

    def __post_init__(self) -> None:
        LandmarkSlamConfig.__post_init__(self)
        if self.info_every_scans < 1:
            raise ValueError(f"info_every_scans must be >= 1, got {self.info_every_scans}")
        self.algorithm("known")

    def algorithm(self, mode: str) -> DSlamConfig:
        return DSlamConfig(odometry_noise=self.odometry_noise(), default_range_sigma_m=self.range_sigma_m,
                           default_bearing_sigma_rad=self.bearing_sigma_rad, association=mode,  # type: ignore[arg-type]
                           association_params=self.association_params(), ci_criterion=self.ci_criterion,
                           recovery=self.recovery, global_every_scans=self.global_every_scans,
                           covariance_refresh_scans=self.covariance_refresh_scans,
                           loop_closure_gap_scans=self.loop_closure_gap_scans,
                           localization_gate_probability=self.localization_gate_probability,
                           map_gate_probability=self.map_gate_probability,
                           final_relinearization_iterations=self.final_relinearization_iterations,
                           composite_max_scans=self.composite_max_scans,
                           composite_max_distance_m=self.composite_max_distance_m,
                           composite_max_heading_sigma_rad=self.composite_max_heading_sigma_rad)


class DSlamPipeline(LandmarkSlamPipeline):
    name = "dslam"
    summary = "D-SLAM: decoupled EIF mapping (recast measurements) and Covariance Intersection localization"
    prefix = "dslam"
    Config = DSlamPipelineConfig
    # Configuration layers that run D-SLAM a named way. "paper": every extra over [Wang, Huang,
    # Dissanayake 2005] off; ``preset_notes`` says per key what the extra does and why it exists.
    presets: ClassVar[dict[str, dict[str, Any]]] = {
        "paper": {
            "final_relinearization_iterations": 0,
            "composite_max_scans": 0,
            "outlier_probability": 1.0,
            "map_gate_probability": 1.0,
            "localization_gate_probability": 1.0,
        },
    }
    preset_notes: ClassVar[dict[str, str]] = {
        "final_relinearization_iterations": "the paper's map is the EIF estimate I^-1 i; the extra relinearises "
                                            "every measurement (an O(map) summary of them) at the final estimate "
                                            "by Gauss-Newton, removing the rotation left by measurements "
                                            "linearised mid-run (algorithms/dslam/relinearize.py)",
        "composite_max_scans": "the paper maps a scan only when it sees two mapped features; the extra pools "
                               "readings over scans (algorithms/dslam/composite.py); off by default",
        "outlier_probability": "known ids: the paper uses every reading; the extra drops a reading outside this "
                               "gate of its prediction (range outliers of real sensors); off by default",
        "map_gate_probability": "the paper applies every recast update; the extra skips one whose z_map "
                                "innovation fails this chi-square gate against the map (a wrong association)",
        "localization_gate_probability": "the paper fuses every measurement pose by CI; the extra leaves out one "
                                         "whose fit fails this chi-square gate or that disagrees with the "
                                         "prediction (a wrong association)",
    }
    metrics = {**METRICS, **specs("info_nnz_blocks", "info_nnz_blocks_per_landmark")}

    def __init__(self, config: DSlamPipelineConfig, ctx: ReplayContext) -> None:
        super().__init__(config, ctx)
        self.statuses: dict[ScanStatus, int] = {}

    def make_filter(self, mode: str) -> DSlam:
        return DSlam(self.config.algorithm(mode), observer=self.ctx.observer, clock=time.perf_counter)

    def observed_covariances(self, features: list[int]) -> np.ndarray | None:
        cov = self.filter.covariance
        return cov.marginals(features) if cov.known(features) else None

    def observed_joint_covariance(self, features: list[int]) -> np.ndarray | None:
        cov = self.filter.covariance
        return cov.block(features) if features and all(f in cov.position for f in features) else None

    def draw_scan(self, result: Any, world_xy: np.ndarray) -> None:
        obs = self.ctx.observer
        self.statuses[result.status] = self.statuses.get(result.status, 0) + 1
        obs.log("dslam/scan_status", State(result.status.value))
        m = result.measurement
        if m is not None and m.status is PoseStatus.OK:
            pose_w = self.to_world_pose(m.pose)
            obs.log("world/robot/measurement", Pose(pose_w))
            obs.log("world/robot/measurement/covariance",
                    CovarianceEllipses(pose_w[None, :2], self.to_world_cov(m.cov[:2, :2])[None]))
        if result.omega is not None:
            obs.log("metrics/ci_omega", Scalar(result.omega))
        if result.anchors is not None:
            f1, f2 = result.anchors
            obs.log("world/landmarks/anchors", Points(world_xy[[f1, f2]], labels=(f"f1 #{f1}", f"f2 #{f2}"),
                                                      radius=0.12))
        if result.recovery is not None:
            obs.log("metrics/cg_iterations", Scalar(result.recovery.iterations))
        if self.scans % self.config.info_every_scans == 0:
            self.draw_information(world_xy)

    def draw_information(self, world_xy: np.ndarray) -> None:
        """Fig. 3(c): links as segments between the features; Fig. 3(d): the block sparsity pattern."""
        links = self.filter.info.links()
        self.ctx.observer.log("world/information/links", Segments(world_xy[links[:, 0]], world_xy[links[:, 1]]))
        self.ctx.observer.log("dslam/information/sparsity", Image(self.filter.info.sparsity_image()))

    def finalize(self) -> None:
        report = self.filter.finalize()
        self.draw_information(self.to_world_xy(self.filter.estimates()))
        self.ctx.log(f"final recovery: {report.method}; {self.filter.n} features")
        counts = ", ".join(f"{status.value} {n}" for status, n in self.statuses.items())
        self.ctx.log(f"scans by status: {counts}")
        alone = self.statuses.get(ScanStatus.LOCALIZATION_ONLY, 0)
        if self.config.composite_max_scans == 0 and alone > self.scans // 4:
            self.ctx.log(f"{alone} of {self.scans} scans saw fewer than two mapped features and were not used for "
                         f"the map (the paper's rule); composite scans (config composite_max_scans, e.g. 400) map "
                         f"such scans together: see the README's D-SLAM section for what they gain and cost")

    @classmethod
    def internals(cls) -> tuple[rrb.View | rrb.Container, ...]:
        return (views.image_view("Information matrix sparsity (paper Fig. 3d)", "/dslam/information"),
                rrb.Vertical(views.state_view("Scan status: how each scan was used", "dslam/scan_status"),
                             views.series_view("Covariance-intersection weight ω (eq. 14)", "metrics/ci_omega"),
                             views.series_view("Covariance recovery: CG iterations", "metrics/cg_iterations"),
                             row_shares=[1, 2, 2]))

    def extra_metrics(self) -> dict[str, float]:
        n = self.filter.n
        blocks = float(self.filter.info.nnz_blocks)
        return {"info_nnz_blocks": blocks, **({"info_nnz_blocks_per_landmark": blocks / n} if n else {})}
