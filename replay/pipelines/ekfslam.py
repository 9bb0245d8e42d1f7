"""Pipeline ``ekfslam``: full EKF-SLAM, the baseline D-SLAM is compared with, on the same inputs.

Same configuration keys (noise models, association), drawing and metrics as ``dslam``
(:mod:`slamreplay.replay.pipelines.landmark_slam`), without the D-SLAM-only parts (measurement pose, CI,
anchors, information matrix).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
import rerun.blueprint as rrb

from slamreplay.algorithms.ekfslam import EkfSlam, EkfSlamConfig
from slamreplay.algorithms.observe import Image
from slamreplay.replay.engine import views
from slamreplay.replay.pipelines.landmark_slam import METRICS, LandmarkSlamConfig, LandmarkSlamPipeline


@dataclass(frozen=True, slots=True)
class EkfSlamPipelineConfig(LandmarkSlamConfig):
    """The parameters shared with ``dslam``, and where the EKF linearises.

    ``jacobians``: ``"standard"`` (at the latest estimates, the textbook EKF-SLAM the D-SLAM paper
    compares with) or ``"first_estimates"`` (FEJ-EKF, Huang, Mourikis, Roumeliotis 2010: at each
    landmark's first estimate and the propagated pose, so that the map's global rotation stays
    unobservable, as it is; the consistent baseline of benchmarks/dslam_consistency.py).
    """

    jacobians: Literal["standard", "first_estimates"] = field(default="standard", metadata={"help": (
        "EKF Jacobians at the latest estimates (standard: the paper's baseline) or, beyond the paper, at "
        "first estimates (first_estimates: FEJ-EKF)")})

    def __post_init__(self) -> None:
        LandmarkSlamConfig.__post_init__(self)
        self.algorithm("known")

    def algorithm(self, mode: str) -> EkfSlamConfig:
        return EkfSlamConfig(odometry_noise=self.odometry_noise(), default_range_sigma_m=self.range_sigma_m,
                             default_bearing_sigma_rad=self.bearing_sigma_rad, association=mode,  # type: ignore[arg-type]
                             association_params=self.association_params(), jacobians=self.jacobians)


class EkfSlamPipeline(LandmarkSlamPipeline):
    name = "ekfslam"
    summary = "EKF-SLAM (full covariance): the traditional-SLAM baseline of the D-SLAM paper"
    prefix = "ekfslam"
    Config = EkfSlamPipelineConfig
    metrics = dict(METRICS)

    def make_filter(self, mode: str) -> EkfSlam:
        return EkfSlam(self.config.algorithm(mode), observer=self.ctx.observer, clock=time.perf_counter)

    def observed_covariances(self, features: list[int]) -> np.ndarray | None:
        return self.filter.marginal_covariances()[features] if features else None

    def observed_joint_covariance(self, features: list[int]) -> np.ndarray | None:
        if not features:
            return None
        idx = (3 + 2 * np.asarray(features)[:, None] + np.arange(2)).reshape(-1)
        return np.array(self.filter.P[np.ix_(idx, idx)])

    def draw_map(self, world_xy: np.ndarray) -> None:
        super().draw_map(world_xy)
        self.ctx.observer.log("ekfslam/covariance/correlation", Image(correlation_image(self.filter.P)))

    @classmethod
    def internals(cls) -> tuple[rrb.View | rrb.Container, ...]:
        return (views.image_view("Covariance |correlation| (robot, then landmarks; white = 1)",
                                 "/ekfslam/covariance"),)


def correlation_image(p: np.ndarray, max_pixels: int = 512) -> np.ndarray:
    """|correlation| of a covariance matrix as a uint8 image (255 = fully correlated); larger
    matrices are reduced to ``max_pixels`` a side, each pixel the largest value of its block."""
    d = np.sqrt(np.maximum(np.diag(p), 1e-300))
    corr = np.abs(p) / np.outer(d, d)
    scale = max(1, -(-len(p) // max_pixels))
    if scale > 1:
        n = -(-len(p) // scale) * scale
        padded = np.zeros((n, n))
        padded[: len(p), : len(p)] = corr
        corr = padded.reshape(n // scale, scale, n // scale, scale).max(axis=(1, 3))
    return np.asarray(np.clip(corr, 0.0, 1.0) * 255.0 + 0.5, dtype=np.uint8)
