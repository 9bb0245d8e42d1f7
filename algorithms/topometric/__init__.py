"""Topo-metric visual mapping and navigation (Battesti, Bazeille, Filliat, ECMR 2011).

Mapping (:class:`TopoMetricMapper`): STAR + BRIEF keypoints, an incremental binary bag of words with
a tf-idf inverted index, a Bayes filter over locations with the odometry evolution model merged over
several time steps, 2-point RANSAC validation of a 2D image motion, and pose-graph relaxation at each
loop closure. The result is a :class:`TopoMap`; :meth:`TopoMap.localizer` gives the navigation-mode
detector (:class:`Localizer`).
"""

from slamreplay.algorithms.topometric.bayes import FilterConfig, FilterStep, LocationFilter
from slamreplay.algorithms.topometric.config import MapperConfig, mapper_config_from_dict
from slamreplay.algorithms.topometric.features import FeatureConfig, FeatureExtractor, Features
from slamreplay.algorithms.topometric.mapper import Candidate, MapperStep, Relaxation, StepStatus, TopoMetricMapper
from slamreplay.algorithms.topometric.navigation import Localization, Localizer, LocalizerStep, NavigationConfig
from slamreplay.algorithms.topometric.topomap import TopoMap
from slamreplay.algorithms.topometric.validation import (
           Motion2D,
           Validation,
           ValidationConfig,
           ValidationStatus,
           validate,
)
from slamreplay.algorithms.topometric.vocabulary import Vocabulary, VocabularyConfig

__all__ = ["Candidate", "FeatureConfig", "FeatureExtractor", "Features", "FilterConfig", "FilterStep",
           "Localization", "Localizer", "LocalizerStep", "LocationFilter", "MapperConfig", "MapperStep", "Motion2D",
           "NavigationConfig", "Relaxation", "StepStatus", "TopoMap", "TopoMetricMapper", "Validation",
           "ValidationConfig", "ValidationStatus", "Vocabulary", "VocabularyConfig", "mapper_config_from_dict",
           "validate"]
