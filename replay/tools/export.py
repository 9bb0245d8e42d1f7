"""A recording's data as plain files, for programs that do not read MCAP (external pipelines, docs/external.md).

Each export reads one logical topic and writes one file (or folder) whole, under a temporary name renamed
when complete. Times are int nanoseconds of log time, as in the recording; never ground truth (an external
program is scored against it and must not see it).

| export | file | columns |
| --- | --- | --- |
| ``odometry_tum`` | ``odometry.tum`` | TUM: ``t_s x y z qx qy qz qw`` of the cumulative odometry pose |
| ``odometry_csv`` | ``odometry.csv`` | ``t_ns,x_m,y_m,yaw_rad`` (header line first) |
| ``range_bearing_csv`` | ``range_bearing.csv`` | ``t_ns,landmark_id,range_m,bearing_rad`` (a row per observation) |
| ``images`` | ``images/`` | ``<t_ns>.png`` per image and ``times.csv``: ``t_ns,file`` |
| ``ros2_bag`` | ``ros2_bag/`` | a ROS 2 bag (sqlite3, message definitions stored): ``/odom`` nav_msgs/Odometry; |
| | | with the recording's images ``/camera/image_raw`` sensor_msgs/Image (mono8, rgb8); with its |
| | | scans ``/landmarks/range_bearing`` ``slamreplay_msgs/msg/RangeBearingScan`` (``RANGE_BEARING_MSG``) |
"""

from __future__ import annotations

import shutil
from collections.abc import Callable, Iterable, Mapping
from pathlib import Path
from typing import Any

import numpy as np

from slamreplay.recorder.files import atomic_write
from slamreplay.recorder.messages import TOPIC_CAMERA_IMAGE, TOPIC_ODOM, TOPIC_RANGE_BEARING
from slamreplay.replay.engine.reader import RecordingReader
from slamreplay.replay.engine.trajectory import to_tum
from slamreplay.replay.errors import ReplayError
from slamreplay.replay.tools.export_names import EXPORT_FILES


def _odometry(reader: RecordingReader) -> tuple[np.ndarray, np.ndarray]:
    t, poses = [], []
    for env in reader.messages([TOPIC_ODOM]):
        t.append(env.log_time_ns)
        poses.append(env.msg.xy_yaw)  # type: ignore[union-attr]
    return np.asarray(t, np.int64), np.asarray(poses, np.float64).reshape(-1, 3)


def export_odometry_tum(reader: RecordingReader, out_dir: Path) -> Path:
    """``odometry.tum``: the cumulative odometry pose, TUM."""
    path = out_dir / "odometry.tum"
    atomic_write(path, to_tum(*_odometry(reader)))
    return path


def export_odometry_csv(reader: RecordingReader, out_dir: Path) -> Path:
    """``odometry.csv``: ``t_ns,x_m,y_m,yaw_rad``, full float precision."""
    t, poses = _odometry(reader)
    rows = "".join(f"{ti},{x!r},{y!r},{yaw!r}\n" for ti, (x, y, yaw) in zip(t.tolist(), poses.tolist(), strict=True))
    path = out_dir / "odometry.csv"
    atomic_write(path, ("t_ns,x_m,y_m,yaw_rad\n" + rows).encode())
    return path


def export_range_bearing_csv(reader: RecordingReader, out_dir: Path) -> Path:
    """``range_bearing.csv``: a row per observation, ``t_ns,landmark_id,range_m,bearing_rad`` (id -1: unknown)."""
    lines = ["t_ns,landmark_id,range_m,bearing_rad\n"]
    for env in reader.messages([TOPIC_RANGE_BEARING]):
        m = env.msg
        for i, r, b in zip(m.landmark_ids.tolist(), m.ranges_m.tolist(), m.bearings_rad.tolist(),  # type: ignore
                           strict=True):
            lines.append(f"{env.log_time_ns},{i},{r!r},{b!r}\n")
    path = out_dir / "range_bearing.csv"
    atomic_write(path, "".join(lines).encode())
    return path


def export_images(reader: RecordingReader, out_dir: Path) -> Path:
    """``images/``: each camera image as ``<t_ns>.png`` (lossless), listed in ``times.csv``."""
    import cv2

    folder = out_dir / "images"
    tmp = out_dir / ".images.partial"
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    rows = ["t_ns,file\n"]
    for env in reader.messages([TOPIC_CAMERA_IMAGE]):
        px = env.msg.pixels  # type: ignore[union-attr]
        name = f"{env.log_time_ns}.png"
        ok, data = cv2.imencode(".png", px if px.ndim == 2 else px[:, :, ::-1])
        if not ok:
            raise ReplayError(f"cannot encode the image at {env.log_time_ns} ns as PNG")
        (tmp / name).write_bytes(data.tobytes())
        rows.append(f"{env.log_time_ns},{name}\n")
    (tmp / "times.csv").write_text("".join(rows))
    shutil.rmtree(folder, ignore_errors=True)
    tmp.rename(folder)
    return folder


RANGE_BEARING_TYPE = "slamreplay_msgs/msg/RangeBearingScan"
RANGE_BEARING_MSG = "std_msgs/Header header\nint64[] landmark_ids\nfloat64[] ranges_m\nfloat64[] bearings_rad\n"
BAG_TOPICS = {TOPIC_ODOM: "/odom", TOPIC_CAMERA_IMAGE: "/camera/image_raw",
              TOPIC_RANGE_BEARING: "/landmarks/range_bearing"}


def export_ros2_bag(reader: RecordingReader, out_dir: Path) -> Path:
    """``ros2_bag/``: the odometry (and images, range-bearing scans) as a ROS 2 bag, CDR-encoded by ``rosbags``
    (ROS 2 Humble's message types), every message at its log time, header stamps the same."""
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    ts = get_typestore(Stores.ROS2_HUMBLE)
    ts.register(get_types_from_msg(RANGE_BEARING_MSG, RANGE_BEARING_TYPE))
    T = ts.types
    types = {TOPIC_ODOM: "nav_msgs/msg/Odometry", TOPIC_CAMERA_IMAGE: "sensor_msgs/msg/Image",
             TOPIC_RANGE_BEARING: RANGE_BEARING_TYPE}
    present = [t for t in types if t in reader.info.logical_topics()]
    zeros36 = np.zeros(36)

    def header(ns: int, frame: str) -> object:
        return T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](sec=ns // 10**9, nanosec=ns % 10**9),
                                        frame_id=frame)

    def odometry(ns: int, x: float, y: float, yaw: float) -> object:
        pose = T["geometry_msgs/msg/Pose"](position=T["geometry_msgs/msg/Point"](x=x, y=y, z=0.0),
                                           orientation=T["geometry_msgs/msg/Quaternion"](
                                               x=0.0, y=0.0, z=float(np.sin(yaw / 2)), w=float(np.cos(yaw / 2))))
        vec = T["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0)
        twist = T["geometry_msgs/msg/Twist"](linear=vec, angular=vec)
        return T["nav_msgs/msg/Odometry"](
            header=header(ns, "odom"), child_frame_id="base_link",
            pose=T["geometry_msgs/msg/PoseWithCovariance"](pose=pose, covariance=zeros36),
            twist=T["geometry_msgs/msg/TwistWithCovariance"](twist=twist, covariance=zeros36))

    def message(topic: str, ns: int, msg: Any) -> object:
        if topic == TOPIC_ODOM:
            return odometry(ns, *map(float, msg.xy_yaw))
        if topic == TOPIC_CAMERA_IMAGE:
            px = np.ascontiguousarray(msg.pixels)
            return T["sensor_msgs/msg/Image"](header=header(ns, "camera"), height=px.shape[0], width=px.shape[1],
                                              encoding="mono8" if px.ndim == 2 else "rgb8", is_bigendian=0,
                                              step=px.shape[1] * (1 if px.ndim == 2 else 3), data=px.ravel())
        return T[RANGE_BEARING_TYPE](header=header(ns, "base_link"),
                                     landmark_ids=np.asarray(msg.landmark_ids, np.int64),
                                     ranges_m=np.asarray(msg.ranges_m, np.float64),
                                     bearings_rad=np.asarray(msg.bearings_rad, np.float64))

    folder, tmp = out_dir / "ros2_bag", out_dir / ".ros2_bag.partial"  # the bag is tmp/ros2_bag until complete
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    with Writer(tmp / folder.name, version=9, storage_plugin=StoragePlugin.SQLITE3) as bag:
        conns = {t: bag.add_connection(BAG_TOPICS[t], types[t], typestore=ts) for t in present}
        for env in reader.messages(present):
            conn = conns[env.topic]
            bag.write(conn, env.log_time_ns, ts.serialize_cdr(message(env.topic, env.log_time_ns, env.msg),
                                                              conn.msgtype))
    shutil.rmtree(folder, ignore_errors=True)
    (tmp / folder.name).rename(folder)
    tmp.rmdir()
    return folder


EXPORTS: dict[str, tuple[str, Callable[[RecordingReader, Path], Path]]] = {  # what each reads, its writer
    "odometry_tum": (TOPIC_ODOM, export_odometry_tum),
    "odometry_csv": (TOPIC_ODOM, export_odometry_csv),
    "range_bearing_csv": (TOPIC_RANGE_BEARING, export_range_bearing_csv),
    "images": (TOPIC_CAMERA_IMAGE, export_images),
    "ros2_bag": (TOPIC_ODOM, export_ros2_bag),
}
assert list(EXPORTS) == list(EXPORT_FILES), "each export is described once, in export_names.EXPORT_FILES"


def parse_exports(text: str | Iterable[str]) -> list[str]:
    """Export names from ``"a,b"`` or a list; ReplayError naming an unknown one."""
    names = [n.strip() for n in (text.split(",") if isinstance(text, str) else text) if n.strip()]
    for name in names:
        if name not in EXPORTS:
            raise ReplayError(f"unknown export {name!r}; exports: {', '.join(EXPORTS)} (docs/external.md)")
    return names


def export_topics(names: Iterable[str]) -> tuple[str, ...]:
    """The logical topics the exports ``names`` read (what a program asking for them needs in a recording)."""
    return tuple(dict.fromkeys(EXPORTS[n][0] for n in parse_exports(list(names))))


def export_recording(recording: Path, out_dir: Path, names: Iterable[str],
                     topic_map: Mapping[str, str] | None = None) -> list[Path]:
    """Write the exports ``names`` of ``recording`` into ``out_dir`` (created); the paths written."""
    names = parse_exports(list(names))
    reader = RecordingReader(recording, dict(topic_map or {}))
    present = reader.info.logical_topics()
    for name in names:
        topic = EXPORTS[name][0]
        if topic not in present:
            raise ReplayError(f"{recording.name} has no {topic}, which export {name} reads")
    out_dir.mkdir(parents=True, exist_ok=True)
    return [EXPORTS[name][1](reader, out_dir) for name in names]
