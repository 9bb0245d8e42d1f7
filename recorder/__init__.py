"""Recording: the message model, the MCAP codec, the `Recorder`, simulators and importers.

The names below are loaded on first use (PEP 562): importing a light submodule such as
``slamreplay.recorder.errors`` (the command line does, to build its parser) must not pull in
numpy, protobuf and mcap through this package's ``__init__``.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from slamreplay.recorder.errors import CodecError, RecorderError
    from slamreplay.recorder.messages import (
        TOPIC_CAMERA_CALIBRATION,
        TOPIC_CAMERA_IMAGE,
        TOPIC_GROUND_TRUTH_LANDMARKS,
        TOPIC_GROUND_TRUTH_POSE,
        TOPIC_ODOM,
        TOPIC_RANGE_BEARING,
        TOPIC_TYPES,
        CameraCalibration,
        CameraImage,
        GroundTruthPose,
        LandmarkMap,
        Message,
        OdometryPose,
        RangeBearingScan,
        assert_msg_equal,
    )
    from slamreplay.recorder.writer import Recorder

_WHERE = {"CodecError": "errors", "RecorderError": "errors", "Recorder": "writer"}

__all__ = [
    "TOPIC_CAMERA_CALIBRATION", "TOPIC_CAMERA_IMAGE", "TOPIC_GROUND_TRUTH_LANDMARKS", "TOPIC_GROUND_TRUTH_POSE",
    "TOPIC_ODOM", "TOPIC_RANGE_BEARING", "TOPIC_TYPES", "CameraCalibration", "CameraImage", "CodecError",
    "GroundTruthPose", "LandmarkMap", "Message", "OdometryPose", "RangeBearingScan", "Recorder", "RecorderError",
    "assert_msg_equal",
]


def __getattr__(name: str) -> Any:
    """Load an exported name from its module on first use."""
    if name not in __all__:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(importlib.import_module(f"{__name__}.{_WHERE.get(name, 'messages')}"), name)
    globals()[name] = value
    return value
