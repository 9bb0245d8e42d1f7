"""A small ROS 2 bag of either storage, written with ``rosbags``' writer from a seeded simulation.

``slamreplay record sim-ros2-bag --out BAG`` writes it, so that the README's ROS 2 section can be tried
without a bag of one's own, and the tests read the same bags. A robot drives a circle among poles.
The bag holds ``/odom`` (nav_msgs/Odometry, drifting), ``/tf`` (``map -> odom`` correcting the drift,
``odom -> base_link``), ``/tf_static`` (``base_link -> laser``, 0.3 m forward), ``/imu`` (yaw rate),
``/scan`` (LaserScan seeing the poles), ``/camera/image_raw`` (mono8), ``/camera/compressed`` (PNG),
``/camera/camera_info`` and a custom type on ``/diagnostics_blob``. The truth is returned for checking.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from numpy.typing import NDArray
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

LASER_X_M = 0.3  # the laser sits 0.3 m ahead of base_link
CUSTOM = "my_msgs/msg/Blob"


@dataclass
class BagTruth:
    """What was written: stamps (ns) and poses of the truth and the odometry, the poles."""

    stamps_ns: NDArray[np.int64]
    truth: NDArray[np.float64]  # (n, 3) base_link in map
    odom: NDArray[np.float64]  # (n, 3) base_link in odom
    yaw_rate: NDArray[np.float64]  # (n,) the IMU's
    poles: NDArray[np.float64]  # (m, 3) x, y, radius in map
    scan_stamps_ns: NDArray[np.int64]
    image: NDArray[np.uint8]
    K: NDArray[np.float64]


def _compose(a: NDArray[np.float64], b: NDArray[np.float64]) -> NDArray[np.float64]:
    c, s = math.cos(a[2]), math.sin(a[2])
    return np.array([a[0] + c * b[0] - s * b[1], a[1] + s * b[0] + c * b[1], a[2] + b[2]])


def _inverse(a: NDArray[np.float64]) -> NDArray[np.float64]:
    c, s = math.cos(a[2]), math.sin(a[2])
    return np.array([-c * a[0] - s * a[1], s * a[0] - c * a[1], -a[2]])


def _ray_cast(pose: NDArray[np.float64], poles: NDArray[np.float64], angles: NDArray[np.float64],
              rmax: float) -> NDArray[np.float64]:
    """Ranges from a sensor at ``pose`` to the nearest pole along each beam (inf: nothing)."""
    r = np.full(len(angles), np.inf)
    d = np.stack([np.cos(angles + pose[2]), np.sin(angles + pose[2])])
    for px, py, rad in poles:
        ox, oy = px - pose[0], py - pose[1]
        b = d[0] * ox + d[1] * oy
        disc = b * b - (ox * ox + oy * oy - rad * rad)
        t = b - np.sqrt(np.maximum(disc, 0.0))
        r = np.where((disc >= 0) & (t > 0) & (t < r), t, r)
    return np.where(r <= rmax, r, np.inf)


def write_bag(path: Path, storage: str, *, seed: int = 0, seconds: float = 60.0, with_definitions: bool = True,
              skip: tuple[str, ...] = (), scan_every: int = 2) -> BagTruth:
    """Write a bag at ``path`` (a folder) in ``storage`` (``sqlite3`` or ``mcap``)."""
    rng = np.random.default_rng(seed)
    ts = get_typestore(Stores.ROS2_HUMBLE)
    ts.register(get_types_from_msg("uint8[] data\nstring note", CUSTOM))
    T = ts.types
    Header, Time = T["std_msgs/msg/Header"], T["builtin_interfaces/msg/Time"]
    Vec3, Quat = T["geometry_msgs/msg/Vector3"], T["geometry_msgs/msg/Quaternion"]
    Pose, Point = T["geometry_msgs/msg/Pose"], T["geometry_msgs/msg/Point"]

    def header(ns: int, frame: str) -> object:
        return Header(stamp=Time(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000), frame_id=frame)

    def quat(yaw: float) -> object:
        return Quat(x=0.0, y=0.0, z=math.sin(yaw / 2), w=math.cos(yaw / 2))

    def tf(ns: int, parent: str, child: str, p: NDArray[np.float64]) -> object:
        return T["geometry_msgs/msg/TransformStamped"](
            header=header(ns, parent), child_frame_id=child,
            transform=T["geometry_msgs/msg/Transform"](translation=Vec3(x=p[0], y=p[1], z=0.0), rotation=quat(p[2])))

    poles = np.column_stack([rng.uniform(-18, 18, 40), rng.uniform(-18, 18, 40), rng.uniform(0.1, 0.25, 40)])
    poles = poles[np.hypot(poles[:, 0], poles[:, 1] - 10) > 3.5]  # keep the driven circle clear
    dt, t0 = 0.1, 1_700_000_000 * 10**9
    n = int(seconds / dt)
    v, w = 1.2, 1.2 / 10.0  # a circle of radius 10 m about (0, 10)
    truth, odom = [np.zeros(3)], [np.zeros(3)]
    rates = []
    for _ in range(n - 1):
        step = np.array([v * dt, 0.0, w * dt])
        truth.append(_compose(truth[-1], step))
        noisy = step * np.array([1.03, 0.0, 1.0]) + np.array([0.0, 0.0, 0.0015]) + rng.normal(0, [0.01, 0.003, 0.003])
        odom.append(_compose(odom[-1], noisy))
        rates.append(w + rng.normal(0, 0.002))
    rates.append(w)
    stamps = t0 + (np.arange(n) * dt * 1e9).astype(np.int64)
    truth_a, odom_a = np.array(truth), np.array(odom)
    angles = np.linspace(-3 * math.pi / 4, 3 * math.pi / 4, 1081)
    img = (np.arange(48 * 64, dtype=np.uint32).reshape(48, 64) * 7 % 251).astype(np.uint8)
    K = np.array([[50.0, 0, 32], [0, 50.0, 24], [0, 0, 1]])

    version = 9 if with_definitions else 8
    plugin = StoragePlugin.SQLITE3 if storage == "sqlite3" else StoragePlugin.MCAP
    scan_stamps = []
    with Writer(path, version=version, storage_plugin=plugin) as w_:
        conns = {}
        for topic, typ in (("/odom", "nav_msgs/msg/Odometry"), ("/tf", "tf2_msgs/msg/TFMessage"),
                           ("/tf_static", "tf2_msgs/msg/TFMessage"), ("/imu", "sensor_msgs/msg/Imu"),
                           ("/scan", "sensor_msgs/msg/LaserScan"), ("/camera/image_raw", "sensor_msgs/msg/Image"),
                           ("/camera/compressed", "sensor_msgs/msg/CompressedImage"),
                           ("/camera/camera_info", "sensor_msgs/msg/CameraInfo"), ("/diagnostics_blob", CUSTOM)):
            if topic not in skip:
                conns[topic] = w_.add_connection(topic, typ, typestore=ts)

        def put(topic: str, ns: int, msg: object) -> None:
            if topic in conns:
                w_.write(conns[topic], ns, ts.serialize_cdr(msg, conns[topic].msgtype))

        TF = T["tf2_msgs/msg/TFMessage"]
        put("/tf_static", int(stamps[0]), TF(transforms=[tf(int(stamps[0]), "base_link", "laser",
                                                            np.array([LASER_X_M, 0.0, 0.0]))]))
        zeros36 = np.zeros(36)
        for k in range(n):
            ns = int(stamps[k])
            o, x = odom_a[k], truth_a[k]
            put("/odom", ns, T["nav_msgs/msg/Odometry"](
                header=header(ns, "odom"), child_frame_id="base_link",
                pose=T["geometry_msgs/msg/PoseWithCovariance"](
                    pose=Pose(position=Point(x=o[0], y=o[1], z=0.0), orientation=quat(o[2])), covariance=zeros36),
                twist=T["geometry_msgs/msg/TwistWithCovariance"](
                    twist=T["geometry_msgs/msg/Twist"](linear=Vec3(x=v, y=0.0, z=0.0), angular=Vec3(x=0.0, y=0.0,
                                                                                                   z=w)),
                    covariance=zeros36)))
            map_odom = _compose(x, _inverse(o))
            put("/tf", ns, TF(transforms=[tf(ns, "map", "odom", map_odom), tf(ns, "odom", "base_link", o)]))
            cov = np.zeros(9)
            cov[8] = 0.002**2
            put("/imu", ns, T["sensor_msgs/msg/Imu"](
                header=header(ns, "base_link"), orientation=quat(0.0), orientation_covariance=np.full(9, -1.0),
                angular_velocity=Vec3(x=0.0, y=0.0, z=rates[k]), angular_velocity_covariance=cov,
                linear_acceleration=Vec3(x=0.0, y=0.0, z=9.81), linear_acceleration_covariance=np.zeros(9)))
            if k % scan_every == 0:
                laser = _compose(x, np.array([LASER_X_M, 0.0, 0.0]))
                r = _ray_cast(laser, poles, angles, 25.0)
                r = np.where(np.isfinite(r), r + rng.normal(0, 0.01, len(r)), np.inf).astype(np.float32)
                put("/scan", ns, T["sensor_msgs/msg/LaserScan"](
                    header=header(ns, "laser"), angle_min=float(angles[0]), angle_max=float(angles[-1]),
                    angle_increment=float(angles[1] - angles[0]), time_increment=0.0, scan_time=0.1,
                    range_min=0.1, range_max=25.0, ranges=r, intensities=np.zeros(0, dtype=np.float32)))
                scan_stamps.append(ns)
            if k % 50 == 0:
                put("/camera/image_raw", ns, T["sensor_msgs/msg/Image"](
                    header=header(ns, "camera"), height=48, width=64, encoding="mono8", is_bigendian=0, step=64,
                    data=img.ravel()))
                png = cv2.imencode(".png", img)[1].ravel().astype(np.uint8)
                put("/camera/compressed", ns, T["sensor_msgs/msg/CompressedImage"](
                    header=header(ns, "camera"), format="png", data=png))
                put("/camera/camera_info", ns, T["sensor_msgs/msg/CameraInfo"](
                    header=header(ns, "camera"), height=48, width=64, distortion_model="plumb_bob",
                    d=np.zeros(5), k=K.ravel(), r=np.eye(3).ravel(), p=np.hstack([K, np.zeros((3, 1))]).ravel(),
                    binning_x=0, binning_y=0, roi=T["sensor_msgs/msg/RegionOfInterest"](
                        x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)))
                put("/diagnostics_blob", ns, T[CUSTOM](data=np.zeros(3, dtype=np.uint8), note="hello"))
    return BagTruth(stamps, truth_a, odom_a, np.array(rates), poles, np.array(scan_stamps, dtype=np.int64), img, K)
