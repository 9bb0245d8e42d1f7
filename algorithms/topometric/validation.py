"""Geometric validation of a loop-closure candidate: a 2D image motion by 2-point RANSAC.

Section III-B of [1]_ replaces the 4-point homography by "a simpler computation of a 2D motion
using two couples of points through RANSAC" [2]_, and accepts a loop closure only with enough
matching points and with translation, rotation and scale below thresholds; navigation mode drops
the translation threshold (section IV-A). The motion is an image-plane similarity about the image
centre ``c`` taking a map (reference) image point ``p`` to the current image:

    p' = c + t + s R(theta) (p - c).

With complex numbers ``z = p - c``, ``w = p' - c``: ``w = a z + t`` with ``a = s e^{i theta}``, so two
matches fix it exactly, and the refit on the inliers is a linear least-squares problem.

Sign: ``t_x > 0`` means the scene appears to the right in the current image, i.e. the camera
turned left (counter-clockwise) relative to the map image.

References
----------
.. [1] E. Battesti, S. Bazeille, D. Filliat, "Qualitative localization using vision and odometry for
   path following in topo-metric maps", ECMR 2011, sections III-B and IV-B.
.. [2] M. A. Fischler, R. C. Bolles, "Random sample consensus", Comm. ACM 24(6), 1981.
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass, replace

import cv2
import numpy as np
from numpy.typing import NDArray

from slamreplay.algorithms.topometric.features import Features

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]
B = NDArray[np.bool_]


class ValidationStatus(enum.Enum):
    """Outcome of a validation; never an exception."""

    ACCEPTED = "accepted"
    TOO_FEW_MATCHES = "too_few_matches"
    TOO_FEW_INLIERS = "too_few_inliers"
    TRANSLATION = "translation_above_threshold"
    ROTATION = "rotation_above_threshold"
    SCALE = "scale_above_threshold"


@dataclass(frozen=True, slots=True)
class ValidationConfig:
    """Attributes
    ----------
    max_match_distance_bits : Hamming distance above which a (cross-checked) match is dropped.
    iterations : RANSAC hypotheses (log(0.01)/log(1 - w^2): 72 for an inlier ratio w = 0.25).
    inlier_threshold_px : reprojection distance of an inlier (320x240 pixels).
    min_inliers : fewer inliers reject the candidate.
    max_translation_px : |t| threshold; None switches it off (navigation mode, section IV-A).
    max_rotation_deg : |theta| threshold (a ground robot's camera does not roll: only noise).
    max_scale : the scale must lie in [1 / max_scale, max_scale]. Images are taken every 0.5 m, so a
        revisit along the same track passes within 0.25 m of a location; at the 2.5-4 m depths of a
        corridor seen lengthwise that is a scale of 1.07-1.11, and with 1.07 a revisit whose images
        fall midway between locations closes no loop at all (sim-corridor seed 2: five images in a
        row at 1.075). 1.10 accepts them; the along-track error it allows (about 0.3 m) is what
        ``MapperConfig.loop_sigma_xy_m`` covers.
    """

    max_match_distance_bits: int = 64
    iterations: int = 128
    inlier_threshold_px: float = 3.0
    min_inliers: int = 12
    max_translation_px: float | None = 40.0
    max_rotation_deg: float = 8.0
    max_scale: float = 1.10

    def __post_init__(self) -> None:
        if not 0 < self.max_match_distance_bits <= 256:
            raise ValueError(f"max_match_distance_bits must be in (0, 256], got {self.max_match_distance_bits}")
        if self.iterations < 1 or self.min_inliers < 2:
            raise ValueError("iterations must be >= 1 and min_inliers >= 2")
        if not self.inlier_threshold_px > 0:
            raise ValueError(f"inlier_threshold_px must be > 0, got {self.inlier_threshold_px}")
        if self.max_translation_px is not None and not self.max_translation_px > 0:
            raise ValueError(f"max_translation_px must be > 0 or None, got {self.max_translation_px}")
        if not (self.max_rotation_deg > 0 and self.max_scale >= 1.0):
            raise ValueError("max_rotation_deg must be > 0 and max_scale >= 1")

    def navigation(self) -> ValidationConfig:
        """The same thresholds with the translation one off (section IV-A)."""
        return replace(self, max_translation_px=None)


@dataclass(frozen=True, slots=True, eq=False)
class Motion2D:
    """An image-plane similarity from the map image to the current one (module docstring).

    Attributes
    ----------
    tx_px, ty_px : translation of the image centre (px at the working resolution; x right, y down).
    rotation_rad : in-plane rotation (image axes: clockwise on screen for theta > 0).
    scale : > 1 when the current image is zoomed in (the robot is ahead of the map image).
    inliers : (k,) bool over the matches.
    """

    tx_px: float
    ty_px: float
    rotation_rad: float
    scale: float
    inliers: B

    @property
    def n_inliers(self) -> int:
        return int(self.inliers.sum())

    @property
    def translation_px(self) -> float:
        return math.hypot(self.tx_px, self.ty_px)

    def apply(self, xy: F64, center: tuple[float, float]) -> F64:
        """Map (n, 2) reference-image points into the current image."""
        c = complex(*center)
        z = xy[:, 0] + 1j * xy[:, 1] - c
        w = self.scale * np.exp(1j * self.rotation_rad) * z + complex(self.tx_px, self.ty_px) + c
        return np.stack([w.real, w.imag], axis=1)


@dataclass(frozen=True, slots=True, eq=False)
class Validation:
    """A candidate's validation: matches (k, 2) as (reference index, current index), motion or None."""

    status: ValidationStatus
    matches: I64
    motion: Motion2D | None

    @property
    def accepted(self) -> bool:
        return self.status is ValidationStatus.ACCEPTED


def match(reference: Features, current: Features, max_distance_bits: int) -> I64:
    """Cross-checked nearest-neighbour Hamming matches (k, 2) = (reference index, current index)."""
    if len(reference) == 0 or len(current) == 0:
        return np.zeros((0, 2), np.int64)
    matcher = cv2.BFMatcher(cv2.NORM_HAMMING, crossCheck=True)  # about 1 us to make: no shared module state
    ms = matcher.match(reference.descriptors, current.descriptors)
    pairs = sorted((m.queryIdx, m.trainIdx) for m in ms if m.distance <= max_distance_bits)
    return np.array(pairs, np.int64).reshape(-1, 2)


def _fit(z: NDArray[np.complex128], w: NDArray[np.complex128]) -> tuple[complex, complex]:
    """Least-squares w = a z + t."""
    zm, wm = z.mean(), w.mean()
    dz = z - zm
    den = float(np.vdot(dz, dz).real)
    a = complex(np.vdot(dz, w - wm)) / den if den > 0 else 1.0 + 0j
    return a, complex(wm - a * zm)


def estimate_motion(src: F64, dst: F64, center: tuple[float, float], rng: np.random.Generator,
                    iterations: int = 128, threshold_px: float = 3.0) -> Motion2D | None:
    """2-point RANSAC similarity taking ``src`` (k, 2) onto ``dst`` (k, 2) about ``center``.

    All hypotheses are drawn at once from ``rng``; the first with the most inliers wins, then two
    least-squares refits on its inliers. None with fewer than two matches or no valid sample.
    """
    if src.shape != dst.shape or src.ndim != 2 or src.shape[1] != 2:
        raise ValueError(f"src and dst must be the same (k, 2) shape, got {src.shape} and {dst.shape}")
    k = len(src)
    if k < 2:
        return None
    c = complex(*center)
    z = src[:, 0] + 1j * src[:, 1] - c
    w = dst[:, 0] + 1j * dst[:, 1] - c
    pick = rng.integers(0, k, size=(iterations, 2))
    dz = z[pick[:, 1]] - z[pick[:, 0]]
    ok = np.abs(dz) > 1.0
    if not ok.any():
        return None
    pick, dz = pick[ok], dz[ok]
    a = (w[pick[:, 1]] - w[pick[:, 0]]) / dz
    t = w[pick[:, 0]] - a * z[pick[:, 0]]
    res = np.abs(a[:, None] * z[None, :] + t[:, None] - w[None, :])
    inl = res < threshold_px
    best = int(np.argmax(inl.sum(axis=1)))
    mask = inl[best]
    a_b, t_b = complex(a[best]), complex(t[best])
    for _ in range(2):  # refit on the inliers while that does not lose any
        a_ls, t_ls = _fit(z[mask], w[mask])
        refit = np.abs(a_ls * z + t_ls - w) < threshold_px
        if refit.sum() < mask.sum():
            break
        mask, a_b, t_b = refit, a_ls, t_ls
    return Motion2D(float(t_b.real), float(t_b.imag), float(np.angle(a_b)), float(abs(a_b)), mask.copy())


def validate(reference: Features, current: Features, cfg: ValidationConfig, rng: np.random.Generator,
             center: tuple[float, float] = (159.5, 119.5)) -> Validation:
    """Match two images and check the 2D motion against the thresholds of ``cfg``."""
    pairs = match(reference, current, cfg.max_match_distance_bits)
    if len(pairs) < cfg.min_inliers:
        return Validation(ValidationStatus.TOO_FEW_MATCHES, pairs, None)
    motion = estimate_motion(reference.xy[pairs[:, 0]], current.xy[pairs[:, 1]], center, rng,
                             cfg.iterations, cfg.inlier_threshold_px)
    if motion is None or motion.n_inliers < cfg.min_inliers:
        return Validation(ValidationStatus.TOO_FEW_INLIERS, pairs, motion)
    if cfg.max_translation_px is not None and motion.translation_px > cfg.max_translation_px:
        return Validation(ValidationStatus.TRANSLATION, pairs, motion)
    if abs(math.degrees(motion.rotation_rad)) > cfg.max_rotation_deg:
        return Validation(ValidationStatus.ROTATION, pairs, motion)
    if not 1.0 / cfg.max_scale <= motion.scale <= cfg.max_scale:
        return Validation(ValidationStatus.SCALE, pairs, motion)
    return Validation(ValidationStatus.ACCEPTED, pairs, motion)
