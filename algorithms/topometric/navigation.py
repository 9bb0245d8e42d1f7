"""Navigation mode: visual localization in a saved topo-metric map, nothing learned.

Section III-B and IV-A of [1]_: "the incremental part of the system that adds new words in the
dictionary, new locations in the graph and that relaxes the topo-metrical map is disabled", and
loop closures "are accepted whatever the translation between images is". The filter keeps running
with the odometry evolution model over the map's relaxed poses, its "new" hypothesis now meaning
"not at a mapped place". A validated match gives the map location and the 2D image motion; the
caller turns ``motion.tx_px`` into a heading correction (section IV-B).

References
----------
.. [1] E. Battesti, S. Bazeille, D. Filliat, "Qualitative localization using vision and odometry for
   path following in topo-metric maps", ECMR 2011, sections III-B, IV-A, IV-B.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from slamreplay.algorithms.topometric.bayes import FilterConfig, FilterStep, LocationFilter
from slamreplay.algorithms.topometric.features import FeatureExtractor, Features
from slamreplay.algorithms.topometric.topomap import TopoMap
from slamreplay.algorithms.topometric.validation import Motion2D, Validation, ValidationConfig, validate
from slamreplay.algorithms.topometric.vocabulary import Vocabulary

F64 = NDArray[np.float64]


@dataclass(frozen=True, slots=True)
class NavigationConfig:
    """Attributes
    ----------
    validation : None: the map's thresholds with the translation one off.
    filter : None: the map's filter settings.
    candidate_threshold, max_candidates : as in mapping.
    """

    validation: ValidationConfig | None = None
    filter: FilterConfig | None = None
    candidate_threshold: float = 0.1
    max_candidates: int = 3

    def __post_init__(self) -> None:
        if not 0.0 < self.candidate_threshold <= 1.0 or self.max_candidates < 1:
            raise ValueError("candidate_threshold must be in (0, 1] and max_candidates >= 1")


@dataclass(frozen=True, slots=True, eq=False)
class Localization:
    """A validated match of the current image to a map location.

    Attributes
    ----------
    location : index of the map node.
    probability : its posterior in the filter.
    motion : the 2D image motion from the map image to the current one (``tx_px`` > 0: the scene
        appears to the right, the robot points left of the map heading); ``motion.n_inliers``.
    n_matches : descriptor matches before RANSAC.
    """

    location: int
    probability: float
    motion: Motion2D
    n_matches: int


@dataclass(frozen=True, slots=True, eq=False)
class LocalizerStep:
    """Everything one :meth:`Localizer.localize` looked at (for logging)."""

    features: Features
    filter: FilterStep | None
    candidates: tuple[tuple[int, float, Validation], ...]
    result: Localization | None


class Localizer:
    """Navigation-mode loop-closure detector on a fixed map.

    Parameters
    ----------
    topomap : the map (never modified).
    cfg : NavigationConfig.
    start_location : the known starting node (the paper's navigation needs it); None: uniform.
    """

    def __init__(self, topomap: TopoMap, cfg: NavigationConfig = NavigationConfig(),
                 start_location: int | None = None) -> None:
        n = topomap.n_locations
        if start_location is not None and not 0 <= start_location < n:
            raise ValueError(f"start_location must be in [0, {n}), got {start_location}")
        self.map = topomap
        self.cfg = cfg
        self.validation = cfg.validation or topomap.config.validation.navigation()
        self.extractor = FeatureExtractor(topomap.config.features)
        self.vocabulary = topomap.vocabulary()
        p0 = np.full(n + 1, 1.0 / max(n, 1))
        p0[n] = 0.0
        if start_location is not None:
            p0[:] = 0.0
            p0[start_location] = 1.0
        self.filter = LocationFilter(cfg.filter or topomap.config.filter, p0 if n else None)
        self._edges = (topomap.edge_i, topomap.edge_j)
        self.last: LocalizerStep | None = None

    def localize(self, image: NDArray[np.generic], motion: ArrayLike | None, rng: np.random.Generator
                 ) -> Localization | None:
        """Match ``image`` to the map, or None (no features, no candidate, none validated).

        Parameters
        ----------
        image : (H, W) grey or (H, W, 3) RGB uint8, any size (resized to the map's resolution).
        motion : (3,) odometry displacement ``[dx, dy, dtheta]`` since the previous call's image,
            in the robot frame at that image (m, m, rad); None without odometry.
        rng : generator of the RANSAC samples.
        """
        feats = self.extractor.extract(image)
        n = self.map.n_locations
        if len(feats) == 0 or n == 0:
            self.last = LocalizerStep(feats, None, (), None)
            return None
        words, counts = Vocabulary.histogram(self.vocabulary.quantize(feats.descriptors, learn=False))
        scores = self.vocabulary.scores(words, counts)
        step = self.filter.step(self.map.poses, motion, scores, np.ones(n, bool), self._edges)
        p = step.posterior[:n]
        idx = np.flatnonzero(p >= self.cfg.candidate_threshold)
        idx = idx[np.argsort(-p[idx], kind="stable")][: self.cfg.max_candidates]
        fc = self.map.config.features
        centre = ((fc.width - 1) / 2.0, (fc.height - 1) / 2.0)
        cands = tuple((int(i), float(p[i]), validate(self.map.features(int(i)), feats, self.validation, rng, centre))
                      for i in idx)
        ok = [c for c in cands if c[2].accepted and c[2].motion is not None]
        post = step.posterior.copy()
        result = None
        if ok:
            loc, prob, val = min(ok, key=lambda c: c[2].motion.translation_px if c[2].motion else 0.0)
            assert val.motion is not None
            result = Localization(loc, prob, val.motion, len(val.matches))
            post[loc] += post[n]
            post[n] = 0.0
        self.filter.commit(post)
        self.last = LocalizerStep(feats, step, cands, result)
        return result
