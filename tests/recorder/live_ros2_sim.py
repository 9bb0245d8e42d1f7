"""The sim-landmarks simulation as a ROS 2 robot publishes it, for the live-recording tests' ROS 2 variant.

``sim_as_ros2_bag(recording, bag)`` writes a ROS 2 bag (MCAP storage, message definitions stored: the file
``live_peer.py`` serves as ``foxglove_bridge`` would) from a ``sim-landmarks`` recording:

- ``/odom`` nav_msgs/Odometry: the recording's odometry poses (``odom -> base_link``);
- ``/tf`` tf2_msgs/TFMessage: ``map -> odom`` (the truth composed with the odometry's inverse) and
  ``odom -> base_link``, at each odometry stamp: ground truth is ``base_link`` in ``map``;
- ``/tf_static``: ``base_link -> laser``, ``LASER_X_M`` forward;
- ``/scan`` sensor_msgs/LaserScan at each range-bearing scan's stamp: the landmarks as poles of
  ``POLE_RADIUS_M``, ray-cast from the true laser pose over the sensor's field of view and range, with
  seeded range noise (the landmark ids are not sent: the pole extractor finds them again, ids unknown).
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore

from slamreplay.recorder.messages import (
    TOPIC_GROUND_TRUTH_LANDMARKS,
    TOPIC_GROUND_TRUTH_POSE,
    TOPIC_ODOM,
    TOPIC_RANGE_BEARING,
)
from slamreplay.replay.engine.reader import RecordingReader

LASER_X_M = 0.2
POLE_RADIUS_M = 0.1
BEAMS = 721  # over 180 degrees: 0.25 degree apart, a pole 5 m away spans 9 of them
RANGE_SIGMA_M = 0.005

F64 = NDArray[np.float64]


def _compose(a: F64, b: F64) -> F64:
    c, s = math.cos(a[2]), math.sin(a[2])
    return np.array([a[0] + c * b[0] - s * b[1], a[1] + s * b[0] + c * b[1], a[2] + b[2]])


def _inverse(a: F64) -> F64:
    c, s = math.cos(a[2]), math.sin(a[2])
    return np.array([-c * a[0] - s * a[1], s * a[0] - c * a[1], -a[2]])


def _ranges(laser: F64, poles_xy: F64, angles: F64, range_max: float) -> F64:
    """Each beam's range to the nearest pole (inf: none within ``range_max``)."""
    d = np.stack([np.cos(angles + laser[2]), np.sin(angles + laser[2])])  # (2, beams)
    o = poles_xy - laser[:2]  # (n, 2)
    b = o @ d  # (n, beams): the beam's closest approach along it
    disc = b * b - (np.sum(o * o, axis=1)[:, None] - POLE_RADIUS_M**2)
    t = np.where(disc >= 0, b - np.sqrt(np.maximum(disc, 0.0)), np.inf)
    r = np.min(np.where(t > 0, t, np.inf), axis=0) if len(poles_xy) else np.full(len(angles), np.inf)
    return np.where(r <= range_max, r, np.inf)


def messages_by_topic(recording: Path) -> dict[str, list[Any]]:
    """A recording's messages by topic, in replay order."""
    out: dict[str, list[Any]] = {}
    for e in RecordingReader(recording).messages():
        out.setdefault(e.topic, []).append(e.msg)
    return out


def sim_as_ros2_bag(recording: Path, bag: Path, *, seed: int = 0, fov_rad: float = math.pi,
                    range_max_m: float = 5.0) -> dict[str, int]:
    """Write ``recording`` (sim-landmarks) as the ROS 2 bag folder ``bag`` (``bag/bag.mcap``); messages per topic."""
    rng = np.random.default_rng(seed)
    by_topic = messages_by_topic(recording)
    odom = {m.stamp_ns: np.array([m.x_m, m.y_m, m.yaw_rad]) for m in by_topic[TOPIC_ODOM]}  # type: ignore[attr-defined]
    truth = {m.stamp_ns: np.array([m.x_m, m.y_m, m.yaw_rad])  # type: ignore[attr-defined]
             for m in by_topic[TOPIC_GROUND_TRUTH_POSE]}
    poles = np.asarray(by_topic[TOPIC_GROUND_TRUTH_LANDMARKS][0].positions_m, dtype=np.float64)  # type: ignore[attr-defined]
    truth_stamps = np.array(sorted(truth), dtype=np.int64)
    angles = np.linspace(-fov_rad / 2, fov_rad / 2, BEAMS)
    mount = np.array([LASER_X_M, 0.0, 0.0])

    ts = get_typestore(Stores.ROS2_HUMBLE)
    T = ts.types

    def header(ns: int, frame: str) -> object:
        return T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](sec=ns // 10**9, nanosec=ns % 10**9),
                                        frame_id=frame)

    def quat(yaw: float) -> object:
        return T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=math.sin(yaw / 2), w=math.cos(yaw / 2))

    def tf(ns: int, parent: str, child: str, p: F64) -> object:
        return T["geometry_msgs/msg/TransformStamped"](
            header=header(ns, parent), child_frame_id=child, transform=T["geometry_msgs/msg/Transform"](
                translation=T["geometry_msgs/msg/Vector3"](x=float(p[0]), y=float(p[1]), z=0.0), rotation=quat(p[2])))

    out: list[tuple[int, int, str, object]] = []  # (stamp, order, topic, message)
    first = min(odom)
    out.append((first, 0, "/tf_static", T["tf2_msgs/msg/TFMessage"](transforms=[tf(first, "base_link", "laser",
                                                                                   mount)])))
    zeros36, zero3 = np.zeros(36), T["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0)
    for ns, o in sorted(odom.items()):
        out.append((ns, 1, "/odom", T["nav_msgs/msg/Odometry"](
            header=header(ns, "odom"), child_frame_id="base_link", pose=T["geometry_msgs/msg/PoseWithCovariance"](
                pose=T["geometry_msgs/msg/Pose"](position=T["geometry_msgs/msg/Point"](x=o[0], y=o[1], z=0.0),
                                                 orientation=quat(o[2])), covariance=zeros36),
            twist=T["geometry_msgs/msg/TwistWithCovariance"](
                twist=T["geometry_msgs/msg/Twist"](linear=zero3, angular=zero3), covariance=zeros36))))
        if ns in truth:
            out.append((ns, 2, "/tf", T["tf2_msgs/msg/TFMessage"](transforms=[
                tf(ns, "map", "odom", _compose(truth[ns], _inverse(o))), tf(ns, "odom", "base_link", o)])))
    for scan in by_topic[TOPIC_RANGE_BEARING]:
        ns = scan.stamp_ns  # type: ignore[attr-defined]
        nearest = int(truth_stamps[np.argmin(np.abs(truth_stamps - ns))])
        r = _ranges(_compose(truth[nearest], mount), poles, angles, range_max_m)
        r = np.where(np.isfinite(r), r + rng.normal(0, RANGE_SIGMA_M, len(r)), np.inf).astype(np.float32)
        out.append((ns, 3, "/scan", T["sensor_msgs/msg/LaserScan"](
            header=header(ns, "laser"), angle_min=float(angles[0]), angle_max=float(angles[-1]),
            angle_increment=float(angles[1] - angles[0]), time_increment=0.0, scan_time=0.2, range_min=0.05,
            range_max=range_max_m, ranges=r, intensities=np.zeros(0, dtype=np.float32))))
    out.sort(key=lambda m: (m[0], m[1]))
    counts: dict[str, int] = {}
    with Writer(bag, version=9, storage_plugin=StoragePlugin.MCAP) as w:
        conns = {topic: w.add_connection(topic, typ, typestore=ts) for topic, typ in (
            ("/odom", "nav_msgs/msg/Odometry"), ("/tf", "tf2_msgs/msg/TFMessage"),
            ("/tf_static", "tf2_msgs/msg/TFMessage"), ("/scan", "sensor_msgs/msg/LaserScan"))}
        for ns, _, topic, msg in out:
            w.write(conns[topic], ns, ts.serialize_cdr(msg, conns[topic].msgtype))
            counts[topic] = counts.get(topic, 0) + 1
    return counts
