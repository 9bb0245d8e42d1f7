"""Configuration of topo-metric mapping (and, with the translation threshold off, navigation)."""

from __future__ import annotations

from dataclasses import dataclass, field, fields
from typing import Any

from slamreplay.algorithms.topometric.bayes import FilterConfig
from slamreplay.algorithms.topometric.features import FeatureConfig
from slamreplay.algorithms.topometric.validation import ValidationConfig
from slamreplay.algorithms.topometric.vocabulary import VocabularyConfig

ROBUST_KERNELS = ("none", "dcs")  # MapperConfig.relax_robust


@dataclass(frozen=True, slots=True)
class MapperConfig:
    """Attributes
    ----------
    sample_distance_m, sample_angle_deg : an image is taken after this much odometry (paper: 50 cm, 10 deg).
    recent_images : locations created from the last this many taken images are no loop-closure
        hypotheses (they look like the current image; Angeli et al. exclude them the same way). A
        location re-visited by one of them stays a hypothesis: it is validated against its own,
        older reference image, and excluding it dropped correct loop closures a few images later.
    candidate_threshold : posterior above which a location is a potential loop closure.
    max_candidates : most probable candidates validated per image.
    odometry_sigma_xy_m_per_m, odometry_sigma_theta_rad_per_m, odometry_sigma_theta_rad_per_rad,
    odometry_sigma_floor : standard deviations of an odometry edge, growing with its length and turn.
    loop_sigma_along_m, loop_sigma_xy_m, loop_sigma_theta_deg : added to a loop edge, in the matched
        location's frame: along its view direction (large: an image scale cannot give a distance
        without depth), across it, and on the heading (read off the image x-translation).
    hfov_deg : the camera's horizontal field of view; a loop edge's heading is the matched location's
        plus ``tx_px * hfov / width`` (section IV-B's linear rule, the one navigation uses).
    relax_iterations : Gauss-Newton iterations per relaxation (per stage, doubled, with ``relax_robust``).
    gate_m, gate_m_per_m, gate_deg, gate_deg_per_m : beyond the paper, a location is a hypothesis only
        within ``gate_m + gate_m_per_m * d`` metres and ``gate_deg + gate_deg_per_m * d`` degrees of the
        current odometry estimate, d the distance driven since the last loop closure (a generous bound
        on the drift). Places that look alike (repeated posters, twin corridors) pass the paper's
        geometric test perfectly; odometry can still tell them apart. Inactive without odometry.
    odometry_gate : False turns the gate above off completely (the paper has none; the ``gate_*``
        values are then unused).
    relax_robust : "none" (the paper: every validated loop closure is trusted, plain least squares)
        or "dcs" (beyond the paper): each relaxation is a batch solve with Dynamic Covariance Scaling
        on the loop edges, then a chi-square gate at that solution
        (:func:`slamreplay.algorithms.common.posegraph.optimize`, as ``slamreplay graph optimize``); a
        loop edge it drops is a *rejected* loop closure. The edges of images after a loop-closing one
        then start from the last location created (see :mod:`.mapper`).
    relax_gate_probability : the chi-square (3 dof) probability of that gate.
    """

    features: FeatureConfig = field(default_factory=FeatureConfig)
    vocabulary: VocabularyConfig = field(default_factory=VocabularyConfig)
    filter: FilterConfig = field(default_factory=FilterConfig)
    validation: ValidationConfig = field(default_factory=ValidationConfig)
    sample_distance_m: float = 0.5
    sample_angle_deg: float = 10.0
    recent_images: int = 10
    candidate_threshold: float = 0.1
    max_candidates: int = 3
    odometry_sigma_xy_m_per_m: float = 0.05
    odometry_sigma_theta_rad_per_m: float = 0.02
    odometry_sigma_theta_rad_per_rad: float = 0.05
    odometry_sigma_floor: float = 0.01
    loop_sigma_along_m: float = 0.5
    loop_sigma_xy_m: float = 0.2
    loop_sigma_theta_deg: float = 2.0
    hfov_deg: float = 46.0
    relax_iterations: int = 10
    gate_m: float = 2.0
    gate_m_per_m: float = 0.1
    gate_deg: float = 30.0
    gate_deg_per_m: float = 0.5
    odometry_gate: bool = True
    relax_robust: str = "none"
    relax_gate_probability: float = 0.999

    def __post_init__(self) -> None:
        if not (self.sample_distance_m > 0 and self.sample_angle_deg > 0):
            raise ValueError("sample_distance_m and sample_angle_deg must be > 0")
        if self.recent_images < 0 or self.max_candidates < 1 or self.relax_iterations < 1:
            raise ValueError("recent_images must be >= 0, max_candidates and relax_iterations >= 1")
        if not 0.0 < self.candidate_threshold <= 1.0:
            raise ValueError(f"candidate_threshold must be in (0, 1], got {self.candidate_threshold}")
        sig = (self.odometry_sigma_xy_m_per_m, self.odometry_sigma_theta_rad_per_m,
               self.odometry_sigma_theta_rad_per_rad, self.loop_sigma_along_m, self.loop_sigma_xy_m,
               self.loop_sigma_theta_deg)
        if not (all(s >= 0 for s in sig) and self.odometry_sigma_floor > 0):
            raise ValueError("odometry and loop sigmas must be >= 0, odometry_sigma_floor > 0")
        if not (self.gate_m > 0 and self.gate_m_per_m >= 0 and self.gate_deg > 0 and self.gate_deg_per_m >= 0):
            raise ValueError("gate_m and gate_deg must be > 0, gate_m_per_m and gate_deg_per_m >= 0")
        if not isinstance(self.odometry_gate, bool):
            raise ValueError(f"odometry_gate must be a bool, got {self.odometry_gate!r}")
        if self.relax_robust not in ROBUST_KERNELS:
            raise ValueError(f"relax_robust must be one of {', '.join(ROBUST_KERNELS)}, got {self.relax_robust!r}")
        if not 0.0 < self.relax_gate_probability < 1.0:
            raise ValueError(f"relax_gate_probability must be in (0, 1), got {self.relax_gate_probability}")
        if not 0.0 < self.hfov_deg < 180.0:
            raise ValueError(f"hfov_deg must be in (0, 180), got {self.hfov_deg}")


def mapper_config_from_dict(values: dict[str, Any]) -> MapperConfig:
    """Rebuild a MapperConfig from ``dataclasses.asdict`` output; ValueError naming a bad key."""
    nested = {"features": FeatureConfig, "vocabulary": VocabularyConfig, "filter": FilterConfig,
              "validation": ValidationConfig}
    known = {f.name for f in fields(MapperConfig)}
    kwargs: dict[str, Any] = {}
    for key, value in values.items():
        if key not in known:
            raise ValueError(f"config: unknown key {key!r}")
        if key in nested:
            if not isinstance(value, dict):
                raise ValueError(f"config: {key} must be a mapping, got {type(value).__name__}")
            sub = {f.name for f in fields(nested[key])}
            bad = sorted(set(value) - sub)
            if bad:
                raise ValueError(f"config: unknown key {key}.{bad[0]}")
            value = nested[key](**value)
        kwargs[key] = value
    return MapperConfig(**kwargs)
