"""STAR (CenSurE) keypoints with BRIEF-32 binary descriptors at a fixed working resolution.

Section III-B of Bazeille, Battesti, Filliat (ECMR 2011) [1]_ replaces SIFT by STAR keypoints [2]_
("more than 20 times" faster). The paper names no descriptor for them; we use BRIEF-32 (256 bits,
Hamming distance), the binary descriptor OpenCV pairs with STAR, which the incremental binary
vocabulary (:mod:`slamreplay.algorithms.topometric.vocabulary`) and the matcher need.

References
----------
.. [1] E. Battesti, S. Bazeille, D. Filliat, "Qualitative localization using vision and odometry for
   path following in topo-metric maps", ECMR 2011, section III-B.
.. [2] M. Agrawal, K. Konolige, M. Blas, "CenSurE: Center surround extremas for realtime feature
   detection and matching", ECCV 2008.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

F64 = NDArray[np.float64]
U8 = NDArray[np.uint8]
DESCRIPTOR_BYTES = 32


@dataclass(frozen=True, slots=True)
class FeatureConfig:
    """STAR + BRIEF settings.

    Attributes
    ----------
    width, height : working resolution (px); images of another size are resized to it (the paper
        works at 320x240 [1]_, which is what its 0.016 s/image is for).
    star_max_size, star_response_threshold, star_line_threshold_projected,
    star_line_threshold_binarized, star_suppress_nonmax_size : ``cv2.xfeatures2d.StarDetector_create``
        arguments; OpenCV's defaults (45, 30, 10, 8, 5) give 15-45 keypoints on the RTAB-Map samples
        at 320x240, too few for a 2-point RANSAC on a real corridor; these give 70-220.
    max_keypoints : strongest keypoints kept (by |response|, ties by position: deterministic).
    """

    width: int = 320
    height: int = 240
    star_max_size: int = 32
    star_response_threshold: int = 10
    star_line_threshold_projected: int = 20
    star_line_threshold_binarized: int = 15
    star_suppress_nonmax_size: int = 3
    max_keypoints: int = 300

    def __post_init__(self) -> None:
        if not (64 <= self.width <= 4096 and 64 <= self.height <= 4096):
            raise ValueError(f"width, height must be in [64, 4096], got {self.width}x{self.height}")
        if self.star_max_size not in (4, 6, 8, 11, 12, 16, 22, 23, 32, 45, 46, 64, 90, 128):
            raise ValueError(f"star_max_size must be one of OpenCV's STAR sizes, got {self.star_max_size}")
        if self.max_keypoints < 2:
            raise ValueError(f"max_keypoints must be >= 2, got {self.max_keypoints}")


@dataclass(frozen=True, slots=True, eq=False)
class Features:
    """Keypoints of one image at the working resolution.

    Attributes
    ----------
    xy : (n, 2) float64 pixel coordinates (x right, y down, origin at the top-left pixel centre).
    descriptors : (n, 32) uint8 BRIEF-32 descriptors.
    """

    xy: F64
    descriptors: U8

    def __len__(self) -> int:
        return int(self.xy.shape[0])

    @staticmethod
    def empty() -> Features:
        """No keypoints (a blank or featureless image)."""
        return Features(np.zeros((0, 2)), np.zeros((0, DESCRIPTOR_BYTES), np.uint8))


class FeatureExtractor:
    """STAR detector + BRIEF-32 extractor, built once (OpenCV objects hold no per-image state)."""

    def __init__(self, cfg: FeatureConfig = FeatureConfig()) -> None:
        self.cfg = cfg
        # cv2's bundled stubs omit the contrib xfeatures2d factories (present at run time)
        self._star = cv2.xfeatures2d.StarDetector_create(  # type: ignore[attr-defined]
            cfg.star_max_size, cfg.star_response_threshold, cfg.star_line_threshold_projected,
            cfg.star_line_threshold_binarized, cfg.star_suppress_nonmax_size)
        self._brief = cv2.xfeatures2d.BriefDescriptorExtractor_create(  # type: ignore[attr-defined]
            DESCRIPTOR_BYTES, False)

    def prepare(self, image: NDArray[np.generic]) -> U8:
        """The image as (height, width) uint8 grey at the working resolution."""
        img = np.asarray(image)
        if img.ndim == 3 and img.shape[2] == 3:
            img = cv2.cvtColor(np.ascontiguousarray(img, dtype=np.uint8), cv2.COLOR_RGB2GRAY)
        if img.ndim != 2 or img.size == 0:
            raise ValueError(f"image must be (H, W) or (H, W, 3), got shape {img.shape}")
        if img.dtype != np.uint8:
            if not np.all(np.isfinite(img)):
                raise ValueError("image must be finite")
            img = np.clip(img, 0, 255).astype(np.uint8)
        if img.shape != (self.cfg.height, self.cfg.width):
            img = cv2.resize(img, (self.cfg.width, self.cfg.height), interpolation=cv2.INTER_AREA)
        return np.ascontiguousarray(img)

    def extract(self, image: NDArray[np.generic]) -> Features:
        """Keypoints and descriptors of ``image`` ((H, W) or (H, W, 3) RGB, any size: resized).

        Returns :meth:`Features.empty` for a blank or featureless image; never raises for content.
        """
        gray = self.prepare(image)
        kps = self._star.detect(gray)
        if not kps:
            return Features.empty()
        kps, desc = self._brief.compute(gray, kps)  # drops keypoints too close to the border
        if desc is None or not kps:
            return Features.empty()
        xy = np.array([k.pt for k in kps], np.float64).reshape(-1, 2)
        resp = np.abs(np.array([k.response for k in kps], np.float64))
        order = np.lexsort((xy[:, 0], xy[:, 1], -resp))[: self.cfg.max_keypoints]
        order.sort()  # keep OpenCV's order among the kept ones
        return Features(xy[order], np.ascontiguousarray(desc[order], dtype=np.uint8))
