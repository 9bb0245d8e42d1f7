"""Recording: the message model, the MCAP codec, the `Recorder`, simulators and importers."""

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

__all__ = [
    "TOPIC_CAMERA_CALIBRATION", "TOPIC_CAMERA_IMAGE", "TOPIC_GROUND_TRUTH_LANDMARKS", "TOPIC_GROUND_TRUTH_POSE",
    "TOPIC_ODOM", "TOPIC_RANGE_BEARING", "TOPIC_TYPES", "CameraCalibration", "CameraImage", "CodecError",
    "GroundTruthPose", "LandmarkMap", "Message", "OdometryPose", "RangeBearingScan", "Recorder", "RecorderError",
    "assert_msg_equal",
]
