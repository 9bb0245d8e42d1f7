"""Pipeline ``ekfslam``: full EKF-SLAM, the baseline D-SLAM is compared with, on the same inputs.

Same configuration keys (noise models, association), drawing and metrics as ``dslam``
(:mod:`replay.pipelines.landmark_slam`), without the D-SLAM-only parts (measurement pose, CI,
anchors, information matrix).
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from algorithms.ekfslam import EkfSlam, EkfSlamConfig
from replay.pipeline import register
from replay.pipelines.landmark_slam import METRICS, LandmarkSlamConfig, LandmarkSlamPipeline


@dataclass(frozen=True, slots=True)
class EkfSlamPipelineConfig(LandmarkSlamConfig):
    """The parameters shared with ``dslam``."""

    def algorithm(self, mode: str) -> EkfSlamConfig:
        return EkfSlamConfig(odometry_noise=self.odometry_noise(), default_range_sigma_m=self.range_sigma_m,
                             default_bearing_sigma_rad=self.bearing_sigma_rad, association=mode,  # type: ignore[arg-type]
                             association_params=self.association_params())


@register
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
