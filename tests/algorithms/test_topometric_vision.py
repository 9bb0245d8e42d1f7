"""Topo-metric vision: STAR+BRIEF on blank images, the 2-point RANSAC motion, the incremental vocabulary."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from slamreplay.algorithms.topometric import (
    FeatureExtractor,
    Features,
    ValidationConfig,
    ValidationStatus,
    Vocabulary,
    validate,
)
from slamreplay.algorithms.topometric.validation import estimate_motion

CENTRE = (159.5, 119.5)


def texture(seed: int, h: int = 240, w: int = 320) -> np.ndarray:
    """A blobby procedural texture with plenty of STAR keypoints."""
    rng = np.random.default_rng(seed)
    img = cv2.resize(rng.integers(0, 256, (h // 8, w // 8), dtype=np.uint8), (w, h), interpolation=cv2.INTER_CUBIC)
    noise = cv2.GaussianBlur(rng.integers(0, 256, (h, w), dtype=np.uint8), (0, 0), 1.5)
    return cv2.addWeighted(img, 0.7, noise, 0.3, 0)


def warp(img: np.ndarray, angle_deg: float, scale: float, tx: float, ty: float) -> np.ndarray:
    """Similarity about the image centre, then a shift (OpenCV: angle counter-clockwise on screen)."""
    a = cv2.getRotationMatrix2D(CENTRE, angle_deg, scale)
    a[:, 2] += (tx, ty)
    return cv2.warpAffine(img, a, (img.shape[1], img.shape[0]), borderMode=cv2.BORDER_REFLECT)


def test_blank_image_has_no_keypoints() -> None:
    """A blank or constant image gives empty features, not an error."""
    ext = FeatureExtractor()
    for img in (np.zeros((240, 320), np.uint8), np.full((480, 640, 3), 128, np.uint8)):
        f = ext.extract(img)
        assert len(f) == 0 and f.descriptors.shape == (0, 32)


def test_bad_image_raises() -> None:
    """A 1-D array is not an image."""
    with pytest.raises(ValueError, match="image must be"):
        FeatureExtractor().extract(np.zeros(10, np.uint8))


@pytest.mark.parametrize(("angle", "scale", "tx", "ty"), [(0.0, 1.0, 12.0, -5.0), (4.0, 1.05, -20.0, 3.0),
                                                          (-6.0, 0.95, 30.0, 10.0)])
def test_validation_recovers_known_warp(angle: float, scale: float, tx: float, ty: float) -> None:
    """STAR+BRIEF matches and the 2-point RANSAC recover a known image similarity."""
    ext = FeatureExtractor()
    ref = texture(1)
    cur = warp(ref, angle, scale, tx, ty)
    v = validate(ext.extract(ref), ext.extract(cur), ValidationConfig(max_translation_px=None),
                 np.random.default_rng(0), CENTRE)
    assert v.status is ValidationStatus.ACCEPTED and v.motion is not None
    assert v.motion.n_inliers >= 20
    # getRotationMatrix2D turns counter-clockwise on screen: -angle in image (y down) coordinates.
    # STAR keypoints sit on whole pixels, +-1-2 px on this blobby texture: hence the tolerances.
    assert math.degrees(v.motion.rotation_rad) == pytest.approx(-angle, abs=1.5)
    assert v.motion.scale == pytest.approx(scale, rel=0.02)
    assert (v.motion.tx_px, v.motion.ty_px) == pytest.approx((tx, ty), abs=2.0)


def test_translation_threshold_only_in_mapping_mode() -> None:
    """A 60 px shift is rejected by the mapping thresholds and accepted in navigation mode."""
    ext = FeatureExtractor()
    ref = texture(2)
    a, b = ext.extract(ref), ext.extract(warp(ref, 0.0, 1.0, 60.0, 0.0))
    mapping = ValidationConfig()
    assert validate(a, b, mapping, np.random.default_rng(0), CENTRE).status is ValidationStatus.TRANSLATION
    nav = validate(a, b, mapping.navigation(), np.random.default_rng(0), CENTRE)
    assert nav.accepted and nav.motion is not None and nav.motion.tx_px == pytest.approx(60.0, abs=2.0)


def test_unrelated_images_are_rejected() -> None:
    """Two different textures give no valid motion."""
    ext = FeatureExtractor()
    v = validate(ext.extract(texture(3)), ext.extract(texture(4)), ValidationConfig(), np.random.default_rng(0),
                 CENTRE)
    assert not v.accepted
    assert validate(Features.empty(), ext.extract(texture(3)), ValidationConfig(), np.random.default_rng(0)
                    ).status is ValidationStatus.TOO_FEW_MATCHES


@settings(max_examples=40, deadline=None)
@given(theta=st.floats(-0.5, 0.5), scale=st.floats(0.7, 1.4), tx=st.floats(-80, 80), ty=st.floats(-60, 60),
       n_in=st.integers(12, 60), n_out=st.integers(0, 60), seed=st.integers(0, 2**31))
def test_ransac_recovers_motion_with_outliers(theta: float, scale: float, tx: float, ty: float, n_in: int,
                                              n_out: int, seed: int) -> None:
    """With at least as many inliers as outliers the exact similarity and the inlier set come back."""
    rng = np.random.default_rng(seed)
    src = rng.uniform([0, 0], [320, 240], (n_in + n_out, 2))
    c = complex(*CENTRE)
    z = src[:, 0] + 1j * src[:, 1] - c
    w = scale * np.exp(1j * theta) * z + complex(tx, ty) + c
    dst = np.stack([w.real, w.imag], axis=1)
    out = rng.uniform([0, 0], [320, 240], (n_out, 2))
    near = np.hypot(*(out - dst[n_in:]).T) < 5.0  # an "outlier" within the threshold is an inlier: move it away
    out[near] = dst[n_in:][near] + 50.0
    dst[n_in:] = out
    m = estimate_motion(src, dst, CENTRE, np.random.default_rng(seed + 1), iterations=256, threshold_px=1.0)
    assert m is not None
    assert m.inliers[:n_in].all()
    assert m.rotation_rad == pytest.approx(theta, abs=1e-6)
    assert m.scale == pytest.approx(scale, rel=1e-6)
    assert (m.tx_px, m.ty_px) == pytest.approx((tx, ty), abs=1e-4)


def test_vocabulary_adds_words_and_scores_identical_image_highest() -> None:
    """Words are added online; frozen quantization adds none; the same image scores highest."""
    ext = FeatureExtractor()
    voc = Vocabulary()
    feats = [ext.extract(texture(s)) for s in range(5)]
    counts = []
    for f in feats:
        before = voc.n_words
        voc.add_location(*Vocabulary.histogram(voc.quantize(f.descriptors, learn=True)))
        counts.append(voc.n_words - before)
    assert all(c > 0 for c in counts)
    n = voc.n_words
    for k, f in enumerate(feats):
        s = voc.scores(*Vocabulary.histogram(voc.quantize(f.descriptors, learn=False)))
        assert int(np.argmax(s)) == k
    assert voc.n_words == n
    # a slightly warped copy of image 2 still scores image 2 highest
    s = voc.scores(*Vocabulary.histogram(voc.quantize(ext.extract(warp(texture(2), 2.0, 1.03, 5, 3)).descriptors,
                                                      learn=False)))
    assert int(np.argmax(s)) == 2
    assert voc.quantize(np.zeros((0, 32), np.uint8), learn=True).shape == (0,)
