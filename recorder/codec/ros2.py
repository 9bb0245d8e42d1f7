"""ROS 2 messages (``ros2msg`` schemas, CDR encoding) -> slamreplay messages, read-only.

Supported: ``nav_msgs/msg/Odometry``, ``geometry_msgs/msg/PoseStamped`` and
``PoseWithCovarianceStamped`` (as odometry or ground-truth poses), ``sensor_msgs/msg/Image``
(mono8, rgb8, bgr8) and ``sensor_msgs/msg/CompressedImage`` (png, jpeg). Decoding of CDR bytes
into objects is done by ``mcap_ros2`` (or ``rosbags`` in :mod:`slamreplay.recorder.importers.ros2bag`);
this module maps those objects onto the message model. Schema names may use the ROS 1 style
``nav_msgs/Odometry`` too.
"""

from __future__ import annotations

from typing import Any, cast

from slamreplay.recorder.codec.protobuf import decode_image_bytes, raw_pixels, yaw_from_quaternion
from slamreplay.recorder.errors import CodecError
from slamreplay.recorder.messages import CameraImage, Message, PlanarPose

ROS2_SCHEMAS = (
    "nav_msgs/msg/Odometry",
    "geometry_msgs/msg/PoseStamped",
    "sensor_msgs/msg/Image",
    "sensor_msgs/msg/CompressedImage",
)


# Types holding a pose: Odometry and PoseWithCovarianceStamped at ``.pose.pose``, PoseStamped at ``.pose``.
POSE_TYPES = ("nav_msgs/msg/Odometry", "geometry_msgs/msg/PoseStamped", "geometry_msgs/msg/PoseWithCovarianceStamped")


def canonical_ros_type(schema_name: str) -> str:
    """``nav_msgs/Odometry`` -> ``nav_msgs/msg/Odometry``; other names unchanged."""
    parts = schema_name.split("/")
    return f"{parts[0]}/msg/{parts[1]}" if len(parts) == 2 else schema_name


def _stamp(header: Any, log_time_ns: int) -> int:
    ns = int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)
    return ns if ns > 0 else log_time_ns


def from_ros2(kind: type, schema_name: str, obj: Any, log_time_ns: int) -> Message:
    """Build a message of type ``kind`` from a decoded ROS 2 message object."""
    name = canonical_ros_type(schema_name)
    if issubclass(kind, PlanarPose) and name in POSE_TYPES:
        pose = obj.pose if name == "geometry_msgs/msg/PoseStamped" else obj.pose.pose
        p, o = pose.position, pose.orientation
        # kind is an OdometryPose/GroundTruthPose subclass of PlanarPose in practice
        return cast(Message, kind(_stamp(obj.header, log_time_ns), p.x, p.y,
                                  yaw_from_quaternion(o.w, o.x, o.y, o.z)))
    if kind is CameraImage and name == "sensor_msgs/msg/Image":
        px = raw_pixels(bytes(obj.data), obj.width, obj.height, obj.step, obj.encoding)
        return CameraImage(_stamp(obj.header, log_time_ns), px, obj.header.frame_id or "camera", "raw")
    if kind is CameraImage and name == "sensor_msgs/msg/CompressedImage":
        fmt = obj.format.lower()
        px = decode_image_bytes(bytes(obj.data), fmt)
        return CameraImage(_stamp(obj.header, log_time_ns), px, obj.header.frame_id or "camera",
                           "jpeg" if "jp" in fmt else "png")
    raise CodecError(f"ROS 2 type {schema_name} cannot be read as {kind.__name__}")
