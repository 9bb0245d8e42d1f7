"""A small ROS 2 bag (MCAP storage, ros2msg/CDR) written in the test, as rosbag2 would."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
from mcap_ros2.writer import Writer

SEP = "=" * 80
HEADER = f"""{SEP}
MSG: std_msgs/Header
builtin_interfaces/Time stamp
string frame_id
{SEP}
MSG: builtin_interfaces/Time
int32 sec
uint32 nanosec"""
POSE = f"""{SEP}
MSG: geometry_msgs/Pose
Point position
Quaternion orientation
{SEP}
MSG: geometry_msgs/Point
float64 x
float64 y
float64 z
{SEP}
MSG: geometry_msgs/Quaternion
float64 x
float64 y
float64 z
float64 w"""
ODOMETRY = f"""std_msgs/Header header
string child_frame_id
geometry_msgs/PoseWithCovariance pose
geometry_msgs/TwistWithCovariance twist
{HEADER}
{SEP}
MSG: geometry_msgs/PoseWithCovariance
Pose pose
float64[36] covariance
{POSE}
{SEP}
MSG: geometry_msgs/TwistWithCovariance
Twist twist
float64[36] covariance
{SEP}
MSG: geometry_msgs/Twist
Vector3 linear
Vector3 angular
{SEP}
MSG: geometry_msgs/Vector3
float64 x
float64 y
float64 z"""
POSE_STAMPED = f"""std_msgs/Header header
geometry_msgs/Pose pose
{HEADER}
{POSE}"""
IMAGE = f"""std_msgs/Header header
uint32 height
uint32 width
string encoding
uint8 is_bigendian
uint32 step
uint8[] data
{HEADER}"""


def _stamp(t_ns: int) -> dict[str, int]:
    return {"sec": t_ns // 1_000_000_000, "nanosec": t_ns % 1_000_000_000}


def _pose(x: float, y: float, yaw: float) -> dict[str, object]:
    return {"position": {"x": x, "y": y, "z": 0.0},
            "orientation": {"x": 0.0, "y": 0.0, "z": math.sin(yaw / 2), "w": math.cos(yaw / 2)}}


def write_ros2_bag(path: Path, n: int = 20, odom_topic: str = "/wheel/odom", gt_topic: str = "/mocap/pose") -> Path:
    """Odometry (nav_msgs/Odometry), ground truth (PoseStamped) and bgr8 images, all at 10 Hz."""
    path.mkdir(parents=True)
    bag = path / f"{path.name}_0.mcap"
    with open(bag, "wb") as f:
        w = Writer(f)
        odom_schema = w.register_msgdef("nav_msgs/msg/Odometry", ODOMETRY)
        gt_schema = w.register_msgdef("geometry_msgs/msg/PoseStamped", POSE_STAMPED)
        img_schema = w.register_msgdef("sensor_msgs/msg/Image", IMAGE)
        zero_cov = [0.0] * 36
        for k in range(n):
            t = 2_000_000_000 + k * 100_000_000
            x, y, yaw = 0.1 * k, 0.0, 0.05 * k
            header = {"stamp": _stamp(t), "frame_id": "odom"}
            w.write_message(odom_topic, odom_schema, {
                "header": header, "child_frame_id": "base_link",
                "pose": {"pose": _pose(1.1 * x, y, yaw), "covariance": zero_cov},
                "twist": {"twist": {"linear": {"x": 0, "y": 0, "z": 0}, "angular": {"x": 0, "y": 0, "z": 0}},
                          "covariance": zero_cov}}, log_time=t, publish_time=t)
            w.write_message(gt_topic, gt_schema, {"header": {"stamp": _stamp(t), "frame_id": "world"},
                                                   "pose": _pose(x, y, yaw)}, log_time=t, publish_time=t)
            bgr = np.zeros((4, 5, 3), np.uint8)
            bgr[..., 0] = k  # blue channel carries the frame number
            w.write_message("/camera/color", img_schema, {
                "header": header, "height": 4, "width": 5, "encoding": "bgr8", "is_bigendian": 0, "step": 15,
                "data": bgr.tobytes()}, log_time=t, publish_time=t)
        w.finish()
    (path / "metadata.yaml").write_text("rosbag2_bagfile_information:\n  storage_identifier: mcap\n")
    return path
