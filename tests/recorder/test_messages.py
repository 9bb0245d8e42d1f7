"""The message model validates on construction: bad values never get past it."""

from __future__ import annotations

import numpy as np
import pytest

from slamreplay.recorder.messages import CameraCalibration, CameraImage, LandmarkMap, OdometryPose, RangeBearingScan


def test_pose_rejects_nan_and_bad_stamp() -> None:
    """NaN positions and negative or float stamps are refused with the field named."""
    with pytest.raises(ValueError, match="x_m is nan"):
        OdometryPose(1, float("nan"), 0, 0)
    with pytest.raises(ValueError, match="stamp_ns must be >= 0"):
        OdometryPose(-1, 0, 0, 0)
    with pytest.raises(ValueError, match="integer number of nanoseconds"):
        OdometryPose(1.5, 0, 0, 0)  # type: ignore[arg-type]


def test_scan_validation() -> None:
    """Scans need equal lengths, finite non-negative ranges and ids >= -1."""
    with pytest.raises(ValueError, match="same length"):
        RangeBearingScan(1, [1, 2], [0], [1, 2])
    with pytest.raises(ValueError, match="NaN or infinite"):
        RangeBearingScan(1, [np.inf], [0], [1])
    with pytest.raises(ValueError, match="ranges_m must be >= 0"):
        RangeBearingScan(1, [-1], [0], [1])
    with pytest.raises(ValueError, match="landmark_ids must be >= 0, or -1"):
        RangeBearingScan(1, [1], [0], [-2])


def test_messages_are_immutable_copies() -> None:
    """Arrays are copied and read-only: changing the input later changes nothing."""
    r = np.array([1.0, 2.0])
    scan = RangeBearingScan(1, r, [0, 0], [1, 2])
    r[0] = 99
    assert scan.ranges_m[0] == 1.0
    with pytest.raises(ValueError):
        scan.ranges_m[0] = 5


def test_landmark_map_and_images_validation() -> None:
    """Duplicate landmark ids, non-uint8 or empty images and bad K are refused."""
    with pytest.raises(ValueError, match="unique"):
        LandmarkMap(0, [1, 1], [[0, 0], [1, 1]])
    with pytest.raises(ValueError, match="uint8"):
        CameraImage(0, np.zeros((2, 2), np.float32))
    with pytest.raises(ValueError, match="empty"):
        CameraImage(0, np.zeros((0, 2), np.uint8))
    with pytest.raises(ValueError, match=r"\(3, 3\)"):
        CameraCalibration(0, 10, 10, np.eye(2))
