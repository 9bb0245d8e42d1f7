"""The topo-metric map that mapping produces and navigation loads.

A map is a graph of locations (relaxed poses in the map frame) linked by odometry and loop edges;
each location keeps the keypoints and BRIEF descriptors of the image that created it (what a
navigation image is validated against) and the word histogram of all its images, over the
dictionary built during mapping (section III of [1]_). All arrays are flat with offsets, so the map
saves as plain arrays (see ``slamreplay.replay.tools.topomap_io``).

References
----------
.. [1] E. Battesti, S. Bazeille, D. Filliat, "Qualitative localization using vision and odometry for
   path following in topo-metric maps", ECMR 2011.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from slamreplay.algorithms.topometric.config import MapperConfig
from slamreplay.algorithms.topometric.features import DESCRIPTOR_BYTES, Features
from slamreplay.algorithms.topometric.vocabulary import Vocabulary

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]
U8 = NDArray[np.uint8]


def _offsets(name: str, off: I64, total: int, n: int) -> None:
    if off.shape != (n + 1,) or off[0] != 0 or off[-1] != total or np.any(np.diff(off) < 0):
        raise ValueError(f"{name} must be ({n + 1},) non-decreasing offsets from 0 to {total}")


@dataclass(frozen=True, slots=True, eq=False)
class TopoMap:
    """A topo-metric map (arrays are read-only copies).

    Attributes
    ----------
    config : the MapperConfig it was built with (features, vocabulary, filter, validation).
    poses : (n, 3) relaxed location poses ``[x, y, theta]`` in the map frame (m, m, rad).
    edge_i, edge_j : (m,) int64 location indices; the edge measurement is the pose of j in i's frame.
    edge_measurements : (m, 3); edge_information : (m, 3, 3); edge_loop : (m,) bool, loop edges.
    keypoint_offsets : (n + 1,) int64; location k's keypoints are rows ``[off[k], off[k+1])`` of
        keypoints_xy (K, 2) float64 (px at the working resolution) and descriptors (K, 32) uint8.
    histogram_offsets : (n + 1,) int64; location k's words are rows ``[off[k], off[k+1])`` of
        histogram_words (H,) int64 (sorted) and histogram_counts (H,) int64.
    words : (W, 32) uint8, the dictionary.
    images_per_location : (n,) int64, images merged into each location (1 + its loop closures).
    truth_poses : (n, 3) float64 or None, evaluation only: the ground-truth pose ``[x, y, theta]``
        (world frame = map frame at the mapping start) of each location's reference image, NaN rows
        where the recording had no ground truth at that time; None when mapping had no ground truth
        at all. Navigation never reads it; evaluation scores a drive against it (the paper's
        Fig. 4 compares the replay and the mapping trajectories, both from laser SLAM).
    """

    config: MapperConfig
    poses: F64
    edge_i: I64
    edge_j: I64
    edge_measurements: F64
    edge_information: F64
    edge_loop: NDArray[np.bool_]
    keypoint_offsets: I64
    keypoints_xy: F64
    descriptors: U8
    histogram_offsets: I64
    histogram_words: I64
    histogram_counts: I64
    words: U8
    images_per_location: I64
    truth_poses: F64 | None = None

    def __post_init__(self) -> None:
        spec = {"poses": np.float64, "edge_i": np.int64, "edge_j": np.int64, "edge_measurements": np.float64,
                "edge_information": np.float64, "edge_loop": np.bool_, "keypoint_offsets": np.int64,
                "keypoints_xy": np.float64, "descriptors": np.uint8, "histogram_offsets": np.int64,
                "histogram_words": np.int64, "histogram_counts": np.int64, "words": np.uint8,
                "images_per_location": np.int64}
        for name, dtype in spec.items():
            a: NDArray[Any] = np.array(getattr(self, name), dtype=dtype, copy=True)
            a.setflags(write=False)
            object.__setattr__(self, name, a)
        n, m = len(self.poses), len(self.edge_i)
        if self.poses.shape != (n, 3) or not np.all(np.isfinite(self.poses)):
            raise ValueError(f"poses must be finite (n, 3), got {self.poses.shape}")
        if (self.edge_j.shape != (m,) or self.edge_measurements.shape != (m, 3)
                or self.edge_information.shape != (m, 3, 3) or self.edge_loop.shape != (m,)):
            raise ValueError(f"edge arrays must describe the same {m} edges")
        if m and (min(self.edge_i.min(), self.edge_j.min()) < 0 or max(self.edge_i.max(), self.edge_j.max()) >= n):
            raise ValueError(f"edge_i, edge_j must index the {n} locations")
        k, h, w = len(self.keypoints_xy), len(self.histogram_words), len(self.words)
        _offsets("keypoint_offsets", self.keypoint_offsets, k, n)
        _offsets("histogram_offsets", self.histogram_offsets, h, n)
        if self.keypoints_xy.shape != (k, 2) or self.descriptors.shape != (k, DESCRIPTOR_BYTES):
            raise ValueError(f"keypoints_xy must be (K, 2) and descriptors (K, {DESCRIPTOR_BYTES}) with the same K")
        if self.histogram_counts.shape != (h,) or (h and (self.histogram_words.min() < 0
                                                          or self.histogram_words.max() >= w)):
            raise ValueError(f"histogram_words must index the {w} words, with one count each")
        if self.words.shape != (w, DESCRIPTOR_BYTES) or self.images_per_location.shape != (n,):
            raise ValueError(f"words must be (W, {DESCRIPTOR_BYTES}) and images_per_location ({n},)")
        if self.truth_poses is not None:
            t = np.array(self.truth_poses, dtype=np.float64, copy=True)
            if t.shape != (n, 3):
                raise ValueError(f"truth_poses must be ({n}, 3) (NaN where unknown), got {t.shape}")
            t.setflags(write=False)
            object.__setattr__(self, "truth_poses", t)

    @classmethod
    def build(cls, config: MapperConfig, poses: F64, i: I64, j: I64, z: F64, info: F64, loop: NDArray[np.bool_],
              features: Sequence[Features], histograms: Sequence[tuple[I64, I64]], words: U8,
              images_per_location: I64) -> TopoMap:
        """Assemble a map from per-location lists."""
        kp_off = np.r_[0, np.cumsum([len(f) for f in features])].astype(np.int64)
        h_off = np.r_[0, np.cumsum([len(w) for w, _ in histograms])].astype(np.int64)
        cat = np.concatenate
        return cls(config, poses, i, j, z.reshape(-1, 3), info.reshape(-1, 3, 3), loop, kp_off,
                   cat([f.xy for f in features]) if features else np.zeros((0, 2)),
                   cat([f.descriptors for f in features]) if features else np.zeros((0, DESCRIPTOR_BYTES), np.uint8),
                   h_off, cat([w for w, _ in histograms]) if histograms else np.zeros(0, np.int64),
                   cat([c for _, c in histograms]) if histograms else np.zeros(0, np.int64), words,
                   images_per_location)

    @property
    def n_locations(self) -> int:
        return int(self.poses.shape[0])

    def features(self, location: int) -> Features:
        """Keypoints and descriptors of a location's reference image."""
        a, b = self.keypoint_offsets[location], self.keypoint_offsets[location + 1]
        return Features(self.keypoints_xy[a:b], self.descriptors[a:b])

    def histogram(self, location: int) -> tuple[I64, I64]:
        """Word ids and counts of a location."""
        a, b = self.histogram_offsets[location], self.histogram_offsets[location + 1]
        return self.histogram_words[a:b], self.histogram_counts[a:b]

    def vocabulary(self) -> Vocabulary:
        """A fresh dictionary and inverted index with this map's words and locations."""
        voc = Vocabulary(self.config.vocabulary, self.words)
        for k in range(self.n_locations):
            voc.add_location(*self.histogram(k))
        return voc
