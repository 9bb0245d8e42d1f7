"""Importer for ROS 2 bags of either storage (sqlite3 ``.db3``, MCAP), read with ``rosbags``.

A bag is a folder (``metadata.yaml`` plus storage files), or one ``.db3`` or ``.mcap`` file.
Message definitions stored in the bag are used; where the bag holds none (sqlite3 bags before
Iron), the ROS 2 Humble or Jazzy type store (``typestore``) supplies them. Each topic maps to a
logical topic of the recording (docs/design.md, "Recording format"):

- ``nav_msgs/Odometry`` -> ``/odom``: the pose, planar;
- ``geometry_msgs/PoseStamped``, ``PoseWithCovarianceStamped`` -> ``/ground_truth/pose``;
- ``tf2_msgs/TFMessage`` on ``/tf`` and ``/tf_static`` -> ``/odom`` (when no odometry topic is
  mapped: ``base_frame`` in ``odom_frame``) and ``/ground_truth/pose`` (with
  ``ground_truth_frame``: ``base_frame`` in it), composed through the tree (:mod:`.tf_tree`);
- ``sensor_msgs/Imu`` -> ``/imu/yaw_rate``: angular velocity about +z (sensor aligned with the base);
- ``sensor_msgs/LaserScan`` -> ``/landmarks/range_bearing``: poles and trunks (:mod:`.poles`),
  ids unknown, moved into the base frame through a static tf when there is one;
- ``sensor_msgs/Image``, ``CompressedImage`` -> ``/camera/image``;
- ``sensor_msgs/CameraInfo`` -> ``/camera/calibration``: K, D, size.

One bag topic per logical topic: where several qualify, the first in name order is taken and the
others are listed as ignored (``topic_map`` picks another). Any other type is listed and skipped.
Stamps are the header stamps (the bag's receive time where a header stamp is 0); messages are
written in stamp order, so the whole bag is held in memory while importing.
"""

from __future__ import annotations

import dataclasses
import json
import math
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Final

import numpy as np

from slamreplay.recorder.codec.ros2 import POSE_TYPES, from_ros2
from slamreplay.recorder.errors import RecorderError
from slamreplay.recorder.importers.poles import PoleConfig, extract_poles
from slamreplay.recorder.importers.ros2bag_check import CheckedBag, check_storage, checked_bag, rosbags_error
from slamreplay.recorder.importers.tf_tree import TfTree
from slamreplay.recorder.messages import (
    TOPIC_CAMERA_CALIBRATION,
    TOPIC_CAMERA_IMAGE,
    TOPIC_GROUND_TRUTH_POSE,
    TOPIC_IMU_YAW_RATE,
    TOPIC_ODOM,
    TOPIC_RANGE_BEARING,
    CameraCalibration,
    CameraImage,
    GroundTruthPose,
    ImuYawRate,
    Message,
    OdometryPose,
    RangeBearingScan,
)
from slamreplay.recorder.sensor_model import SensorModel
from slamreplay.recorder.writer import Recorder

IMPORTER: Final = "ros2"
TF_TYPE: Final = "tf2_msgs/msg/TFMessage"
TF_TOPICS: Final = ("/tf", "/tf_static")
TYPESTORES: Final = ("humble", "jazzy")
# What each ROS 2 type can become; the first entry is its automatic mapping.
TARGETS: Final[dict[str, tuple[str, ...]]] = {
    "nav_msgs/msg/Odometry": (TOPIC_ODOM, TOPIC_GROUND_TRUTH_POSE),
    "geometry_msgs/msg/PoseStamped": (TOPIC_GROUND_TRUTH_POSE, TOPIC_ODOM),
    "geometry_msgs/msg/PoseWithCovarianceStamped": (TOPIC_GROUND_TRUTH_POSE, TOPIC_ODOM),
    "sensor_msgs/msg/Imu": (TOPIC_IMU_YAW_RATE,),
    "sensor_msgs/msg/LaserScan": (TOPIC_RANGE_BEARING,),
    "sensor_msgs/msg/Image": (TOPIC_CAMERA_IMAGE,),
    "sensor_msgs/msg/CompressedImage": (TOPIC_CAMERA_IMAGE,),
    "sensor_msgs/msg/CameraInfo": (TOPIC_CAMERA_CALIBRATION,),
}
NEEDS: Final = ("a pipeline needs odometry (nav_msgs/Odometry, or /tf from --odom-frame to --base-frame) plus "
                "range-bearing landmarks (sensor_msgs/LaserScan) or camera images (sensor_msgs/Image or "
                "CompressedImage)")

Progress = Callable[[int, int], None]


@dataclass(frozen=True, slots=True)
class TopicPlan:
    """One bag topic: its type, message count, and the logical topic it becomes (None: why not)."""

    topic: str
    msgtype: str
    messages: int
    maps_to: str | None
    note: str


@dataclass(frozen=True, slots=True)
class BagPlan:
    """How a bag maps onto a recording."""

    path: Path
    storage: str
    topics: tuple[TopicPlan, ...]
    tf_odometry: bool  # /odom comes from the tf tree
    tf_ground_truth: bool  # /ground_truth/pose comes from the tf tree
    # (parent, child) of every transform seen (plan_bag reads /tf_static and the start of /tf), and what each
    # frame option finds there: {"--base-frame": "base_link: found", ...}; empty when the bag has no tf
    tf_edges: tuple[tuple[str, str], ...] = ()
    frame_checks: dict[str, str] = field(default_factory=dict)

    def as_dict(self) -> dict[str, Any]:
        return {"path": str(self.path), "storage": self.storage, "tf_odometry": self.tf_odometry,
                "tf_ground_truth": self.tf_ground_truth,
                "tf_edges": [list(e) for e in self.tf_edges], "frame_checks": dict(self.frame_checks),
                "topics": [{"topic": t.topic, "type": t.msgtype, "messages": t.messages, "maps_to": t.maps_to,
                            "note": t.note} for t in self.topics]}


@dataclass(frozen=True, slots=True)
class ImportSummary:
    """What :func:`import_ros2_bag` wrote: messages per logical topic."""

    path: Path
    plan: BagPlan
    counts: dict[str, int] = field(default_factory=dict)
    poles: int = 0

    @property
    def messages(self) -> int:
        return sum(self.counts.values())


def sensor_model(poles: PoleConfig | None = None) -> dict[str, float]:
    """The noise of what a bag's import states, as pipeline config keys: the pole extractor's range and
    bearing floors (each scan also carries the sigma its circle fits give, never below these)."""
    cfg = poles or PoleConfig()
    return {"range_sigma_m": cfg.range_sigma_m, "bearing_sigma_rad": cfg.bearing_sigma_rad}


def is_ros2_bag(path: Path) -> bool:
    """A bag folder (``metadata.yaml``) or a ``.db3`` file: something only :mod:`rosbags` reads."""
    return (path.is_dir() and (path / "metadata.yaml").is_file()) or (path.is_file() and path.suffix == ".db3")


@dataclass
class OpenBag:
    """A bag open in rosbags (``reader``, an AnyReader), every byte it reads checked first (:mod:`.ros2bag_check`);
    :meth:`messages` turns whatever rosbags raises into a BagError. Close it (or use ``with``)."""

    path: Path
    reader: Any
    storage: str
    checked: CheckedBag

    def messages(self, conns: list[Any]) -> Iterator[tuple[Any, int, Any]]:
        """(connection, bag time, raw CDR) of ``conns``; storage damaged past what the check and the index cover
        (a sqlite page) raises BagError when it is reached."""
        items = self.reader.messages(connections=conns)
        done = 0
        while True:
            try:
                item = next(items)
            except StopIteration:
                return
            except Exception as err:  # rosbags', apsw's, sqlite's, zstd's errors: the storage is damaged
                raise rosbags_error(err, f"{self.path}: the bag's storage is damaged after message {done}",
                                    "re-record or copy the bag again") from err
            done += 1
            yield item

    def close(self) -> None:
        try:
            self.reader.close()
        except Exception:  # noqa: BLE001 -- closing what failed to read: the error that matters is raised already
            pass
        finally:
            self.checked.cleanup()

    def __enter__(self) -> OpenBag:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def open_bag(path: str | Path, typestore: str = "humble") -> OpenBag:
    """Open the bag at ``path`` (a folder, a .db3 or .mcap file) in rosbags once its bytes are checked; types the
    bag does not define come from ``typestore`` (humble or jazzy). BagError (a RecorderError) otherwise."""
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    if typestore not in TYPESTORES:
        raise RecorderError(f"typestore must be one of {', '.join(TYPESTORES)}, got {typestore!r}")
    path = Path(path)
    store = get_typestore(Stores.ROS2_HUMBLE if typestore == "humble" else Stores.ROS2_JAZZY)
    checked = checked_bag(path)
    src = checked.path
    try:
        try:
            reader = AnyReader([src], default_typestore=store)
            reader.open()
        except Exception:
            # a folder whose metadata.yaml rosbags cannot read (hand-written, another writer's) but whose one
            # storage file it can: read that file alone, checked as well
            if checked.fallback is None:
                raise
            src = checked.fallback
            check_storage(src, "sqlite3" if src.suffix == ".db3" else "mcap")
            reader = AnyReader([src], default_typestore=store)
            reader.open()
        # types the bag does not define come from the chosen store (mixed bags: some topics carry definitions)
        missing = {c.msgtype for c in reader.connections} - set(reader.typestore.fielddefs)
        if missing:
            extra = {k: v for k, v in store.fielddefs.items() if k not in reader.typestore.fielddefs}
            reader.typestore.register(extra)
    except Exception as err:  # rosbags, sqlite and YAML errors alike: the file is not a readable bag
        checked.cleanup()
        raise rosbags_error(err, f"{path} cannot be read as a ROS 2 bag") from err
    storage = checked.storage if src == checked.path else "sqlite3" if src.suffix == ".db3" else "mcap"
    return OpenBag(path, reader, storage, checked)


def plan_bag(path: str | Path, topic_map: Mapping[str, str] | None = None, *, base_frame: str = "base_link",
             odom_frame: str = "odom", ground_truth_frame: str | None = None, typestore: str = "humble") -> BagPlan:
    """Map each topic of the bag onto a logical topic, or say why it is ignored (the bag stays unread)."""
    with open_bag(path, typestore) as bag:
        plan = _plan(bag, Path(path), dict(topic_map or {}), ground_truth_frame)
        edges = _tf_edges(bag)
    if not edges:
        return plan
    frames = {f for e in edges for f in e}
    wanted = {"--base-frame": base_frame} if plan.tf_odometry or plan.tf_ground_truth else {}
    if plan.tf_odometry:
        wanted["--odom-frame"] = odom_frame
    if ground_truth_frame is not None:
        wanted["--ground-truth-frame"] = ground_truth_frame
    checks = {option: f"{frame}: " + ("found" if frame in frames else f"not in the tf tree read (frames: "
                                      f"{', '.join(sorted(frames))}): pass {option} with one of them")
              for option, frame in wanted.items()}
    return dataclasses.replace(plan, tf_edges=tuple(sorted(edges)), frame_checks=checks)


TF_SAMPLE = 2000  # /tf messages plan_bag reads for the frame names (all of /tf_static)


def _tf_edges(bag: OpenBag) -> set[tuple[str, str]]:
    """(parent, child) of the transforms in /tf_static and the first TF_SAMPLE messages of /tf."""
    edges: set[tuple[str, str]] = set()
    for topic in TF_TOPICS:
        conns = [c for c in bag.reader.connections if c.topic == topic and c.msgtype == TF_TYPE]
        if not conns:  # rosbags reads every connection when given none
            continue
        for n, (conn, _, raw) in enumerate(bag.messages(conns)):
            if topic == "/tf" and n >= TF_SAMPLE:
                break
            try:
                msg = bag.reader.deserialize(raw, conn.msgtype)
            except Exception:  # noqa: BLE001  # a damaged message: the import names it; the plan reads on
                continue
            edges |= {(t.header.frame_id.lstrip("/"), t.child_frame_id.lstrip("/")) for t in msg.transforms}
    return edges


def _plan(bag: OpenBag, path: Path, topic_map: dict[str, str], ground_truth_frame: str | None) -> BagPlan:
    counts: dict[str, int] = {}
    types: dict[str, str] = {}
    for c in bag.reader.connections:
        counts[c.topic] = counts.get(c.topic, 0) + c.msgcount
        types[c.topic] = c.msgtype
    for topic, target in topic_map.items():
        if topic not in types:
            raise RecorderError(f"--topic-map names {topic!r}, which the bag does not hold (topics: "
                                f"{', '.join(sorted(types))})")
        allowed = TARGETS.get(types[topic], ())
        if target not in allowed:
            can = ", ".join(allowed) if allowed else "nothing: slamreplay does not read this type"
            raise RecorderError(f"--topic-map {topic}={target}: a {types[topic]} can become {can}")
    taken: dict[str, str] = {v: k for k, v in topic_map.items()}
    if len(taken) != len(topic_map):
        raise RecorderError("--topic-map maps two bag topics onto one logical topic: one source per topic")
    has_tf = any(types[t] == TF_TYPE for t in types if t in TF_TOPICS)
    if ground_truth_frame is not None:
        if not has_tf:
            raise RecorderError(f"--ground-truth-frame {ground_truth_frame} needs /tf, and the bag has no "
                                f"tf2_msgs/TFMessage on /tf or /tf_static")
        taken.setdefault(TOPIC_GROUND_TRUTH_POSE, "/tf")
    plans: dict[str, TopicPlan] = {}
    for topic in sorted(types):
        msgtype, n = types[topic], counts[topic]
        if topic in topic_map:
            plans[topic] = TopicPlan(topic, msgtype, n, topic_map[topic], "--topic-map")
            continue
        if msgtype == TF_TYPE and topic in TF_TOPICS:
            continue  # decided below, once the other topics are known
        targets = TARGETS.get(msgtype)
        if targets is None:
            plans[topic] = TopicPlan(topic, msgtype, n, None, "type not read by slamreplay: skipped")
            continue
        target = targets[0]
        if target in taken:
            plans[topic] = TopicPlan(topic, msgtype, n, None, f"{target} comes from {taken[target]} (pick another "
                                     f"with --topic-map {topic}={target})")
            continue
        taken[target] = topic
        how = {TOPIC_RANGE_BEARING: "poles and trunks as landmarks, ids unknown",
               TOPIC_IMU_YAW_RATE: "angular velocity about +z"}.get(target, "automatic")
        plans[topic] = TopicPlan(topic, msgtype, n, target, how)
    tf_odom = has_tf and TOPIC_ODOM not in taken
    tf_gt = ground_truth_frame is not None
    for topic in TF_TOPICS:
        if topic in types and types[topic] == TF_TYPE and topic not in plans:
            laser = topic == "/tf_static" and TOPIC_RANGE_BEARING in taken
            uses = [what for what, on in (("odometry", tf_odom), ("ground truth", tf_gt), ("the laser's mounting",
                                                                                       laser)) if on]
            if uses:
                plans[topic] = TopicPlan(topic, TF_TYPE, counts[topic], "transform tree",
                                         " and ".join(uses) + " composed through the tree")
            else:
                plans[topic] = TopicPlan(topic, TF_TYPE, counts[topic], None, "not needed: odometry comes from "
                                         f"{taken.get(TOPIC_ODOM)} and no --ground-truth-frame was given")
    ordered = tuple(plans[t] for t in sorted(plans))
    usable = {p.maps_to for p in ordered if p.maps_to} | ({TOPIC_ODOM} if tf_odom else set())
    if not usable - {"transform tree"}:
        found = ", ".join(f"{t} ({types[t]})" for t in sorted(types)) or "no topics at all"
        raise RecorderError(f"{path} holds nothing slamreplay can use (found: {found}): {NEEDS}")
    return BagPlan(path, bag.storage, ordered, tf_odom, tf_gt)


def _stamp(header: Any, fallback_ns: int) -> int:
    ns = int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)
    return ns if ns > 0 else int(fallback_ns)


def import_ros2_bag(bag_path: str | Path, out: str | Path, *, topic_map: Mapping[str, str] | None = None,
                    base_frame: str = "base_link", odom_frame: str = "odom", ground_truth_frame: str | None = None,
                    typestore: str = "humble", poles: PoleConfig | None = None,
                    progress: Progress | None = None) -> ImportSummary:
    """Import a ROS 2 bag into the recording ``out`` (see the module's table for the mapping).

    Raises
    ------
    RecorderError : the bag is missing or unreadable, holds nothing usable, the tf tree lacks a
        named frame, ``--topic-map`` names a topic or target that cannot be, or ``out`` exists.
    """
    bag_path = Path(bag_path)
    poles = poles or PoleConfig()
    with open_bag(bag_path, typestore) as bag:
        reader = bag.reader
        plan = _plan(bag, bag_path, dict(topic_map or {}), ground_truth_frame)
        by_topic = {p.topic: p for p in plan.topics if p.maps_to}
        conns = [c for c in reader.connections if c.topic in by_topic]
        tree = TfTree()
        out_msgs: list[tuple[int, int, str, Message]] = []
        scans: list[tuple[int, str, Any]] = []
        total = sum(c.msgcount for c in conns)
        every = max(1, total // 200)
        for done, (conn, bag_ns, raw) in enumerate(bag.messages(conns) if conns else (), start=1):
            where = f"message {done} on {conn.topic} ({conn.msgtype})"
            try:
                obj = reader.deserialize(raw, conn.msgtype)
            except Exception as err:  # rosbags' deserialization errors of damaged CDR, whatever their type
                raise rosbags_error(err, f"{bag_path}: {where} is damaged", "re-record or copy the bag again") from err
            try:
                item = convert_message(conn.topic, conn.msgtype, by_topic[conn.topic].maps_to, obj, bag_ns, tree, scans)
            except (ValueError, AttributeError, TypeError) as err:  # values a message cannot hold
                raise RecorderError(f"{bag_path}: {where} cannot be read: {err}") from err
            if item is not None:
                out_msgs.append((item[1].stamp_ns, len(out_msgs), item[0], item[1]))
            if progress is not None and done % every == 0:
                progress(done, total)

    n_poles = 0
    if scans:
        mount = (0.0, 0.0, 0.0)
        frame = scans[0][1]
        if frame and frame != base_frame and base_frame in tree.frames and frame in tree.frames:
            mount = tree.static_planar(base_frame, frame) or mount
        for stamp, _, scan in scans:
            rb = poles_scan(stamp, scan, poles, mount)
            n_poles += len(rb)
            out_msgs.append((stamp, len(out_msgs), TOPIC_RANGE_BEARING, rb))
    if plan.tf_odometry:
        tree.check_frame(odom_frame, "--odom-frame")
        tree.check_frame(base_frame, "--base-frame")
        for msg in tf_poses(tree, TOPIC_ODOM, odom_frame, base_frame):
            out_msgs.append((msg.stamp_ns, len(out_msgs), TOPIC_ODOM, msg))
    if plan.tf_ground_truth:
        assert ground_truth_frame is not None
        tree.check_frame(ground_truth_frame, "--ground-truth-frame")
        tree.check_frame(base_frame, "--base-frame")
        for msg in tf_poses(tree, TOPIC_GROUND_TRUTH_POSE, ground_truth_frame, base_frame):
            out_msgs.append((msg.stamp_ns, len(out_msgs), TOPIC_GROUND_TRUTH_POSE, msg))
    if not any(t in (TOPIC_ODOM, TOPIC_CAMERA_IMAGE) for _, _, t, _ in out_msgs):
        raise RecorderError(f"{bag_path}: no odometry nor image message could be read: {NEEDS}")
    out_msgs.sort(key=lambda m: (m[0], m[1]))
    counts: dict[str, int] = {}
    rec = Recorder(Path(out), source={"importer": IMPORTER, "bag": bag_path.name, "storage": plan.storage},
                   parameters={"topic_map": {p.topic: p.maps_to for p in plan.topics if p.maps_to},
                               "base_frame": base_frame, "odom_frame": odom_frame,
                               "ground_truth_frame": ground_truth_frame, "typestore": typestore,
                               "pole_extractor": poles.as_dict() if scans else None},
                   robot={"frames": json.dumps(sorted(tree.frames))},
                   sensor_model=SensorModel(**sensor_model(poles), source="the pole extractor's noise floors "
                                            "(each scan states the sigma of its circle fits, never below them)")
                   if scans else None)
    with rec:
        for _, _, topic, msg in out_msgs:
            rec.write(topic, msg)
            counts[topic] = counts.get(topic, 0) + 1
    return ImportSummary(Path(out), plan, counts, n_poles)


def convert_message(topic: str, msgtype: str, target: str | None, obj: Any, bag_ns: int, tree: TfTree,
                    scans: list[tuple[int, str, Any]]) -> tuple[str, Message] | None:
    """One ROS 2 message (of a bag or a live stream) as a message of the recording.

    Parameters
    ----------
    topic, msgtype : where it came from and its ROS 2 type (``nav_msgs/msg/Odometry``)
    target : the logical topic it maps to (None for ``tf2_msgs/msg/TFMessage``)
    obj : the decoded ROS 2 object
    bag_ns : its receive time (ns), the stamp when its header's is 0
    tree : transforms of ``/tf`` and ``/tf_static`` are added to it (``/tf_static`` ones as static)
    scans : ``sensor_msgs/LaserScan`` messages are appended to it as (stamp ns, laser frame, scan), for
        :func:`poles_scan` once the laser's mounting is known

    Returns
    -------
    (logical topic, message), or None when the message was gathered for later (tf, scans).
    """
    if msgtype == TF_TYPE:
        for tf in obj.transforms:
            t, q = tf.transform.translation, tf.transform.rotation
            tree.add(tf.header.frame_id, tf.child_frame_id, _stamp(tf.header, bag_ns), (t.x, t.y, t.z),
                     (q.x, q.y, q.z, q.w), static=topic == "/tf_static")
        return None
    if msgtype in POSE_TYPES:
        kind = OdometryPose if target == TOPIC_ODOM else GroundTruthPose
        return str(target), from_ros2(kind, msgtype, obj, bag_ns)
    if msgtype in ("sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage"):
        return TOPIC_CAMERA_IMAGE, from_ros2(CameraImage, msgtype, obj, bag_ns)
    if msgtype == "sensor_msgs/msg/CameraInfo":
        k = np.asarray(obj.k, dtype=np.float64).reshape(3, 3)
        return TOPIC_CAMERA_CALIBRATION, CameraCalibration(
            _stamp(obj.header, bag_ns), int(obj.width), int(obj.height), k, np.asarray(obj.d, dtype=np.float64),
            obj.distortion_model or "plumb_bob", obj.header.frame_id or "camera")
    if msgtype == "sensor_msgs/msg/Imu":
        cov = float(obj.angular_velocity_covariance[8])
        sigma = math.sqrt(cov) if cov > 0 and obj.angular_velocity_covariance[0] >= 0 else 0.0
        return TOPIC_IMU_YAW_RATE, ImuYawRate(_stamp(obj.header, bag_ns), float(obj.angular_velocity.z), sigma)
    if msgtype == "sensor_msgs/msg/LaserScan":
        # checked here, where the message is named: the pole extractor places readings by these angles
        if not (math.isfinite(obj.angle_min) and math.isfinite(obj.angle_increment)):
            raise RecorderError(f"{topic}: a LaserScan with angle_min {obj.angle_min} and angle_increment "
                                f"{obj.angle_increment}: both must be finite to place its readings")
        scans.append((_stamp(obj.header, bag_ns), obj.header.frame_id.lstrip("/"), obj))
        return None
    raise RecorderError(f"{topic}: type {msgtype} has no mapping")


def poles_scan(stamp: int, scan: Any, cfg: PoleConfig, mount: tuple[float, float, float]) -> RangeBearingScan:
    """A ``sensor_msgs/LaserScan``'s poles and trunks (:mod:`.poles`) as a range-bearing scan in the base frame.

    Parameters
    ----------
    stamp : the scan's time (ns)
    scan : the decoded LaserScan (``ranges`` in m, ``angle_min`` and ``angle_increment`` in rad)
    cfg : the pole extractor's settings
    mount : ``(x_m, y_m, yaw_rad)`` of the laser in the base frame (zeros: the laser is the base)

    Returns
    -------
    The poles' ranges and bearings from the base, ids unknown (-1), one sigma each: the largest of its poles'.
    """
    with np.errstate(invalid="ignore"):  # a signalling NaN (damaged bytes) widened: a NaN, a range not read
        ranges = np.asarray(scan.ranges, dtype=np.float64)
    p = extract_poles(ranges, float(scan.angle_min), float(scan.angle_increment), cfg, float(scan.range_min),
                      float(scan.range_max))
    r, b = p.ranges_m, p.bearings_rad
    if mount != (0.0, 0.0, 0.0):
        mx, my, myaw = mount
        x = mx + r * np.cos(b + myaw)
        y = my + r * np.sin(b + myaw)
        r, b = np.hypot(x, y), np.arctan2(y, x)
    # one sigma per scan: the largest of its poles' (a conservative bound for every pole in it)
    rs = float(p.range_sigmas_m.max()) if len(p) else cfg.range_sigma_m
    bs = float(p.bearing_sigmas_rad.max()) if len(p) else cfg.bearing_sigma_rad
    return RangeBearingScan(stamp, r, b, np.full(len(r), -1, dtype=np.int64), rs, bs)


def tf_poses(tree: TfTree, target: str, frame: str, base_frame: str, after_ns: int | None = None) -> list[Message]:
    """``base_frame``'s planar pose in ``frame``, composed through the tf tree, as odometry or ground truth.

    Parameters
    ----------
    tree : the transforms read so far
    target : ``/odom`` (odometry poses) or ``/ground_truth/pose`` (ground-truth poses)
    frame, base_frame : e.g. ``odom`` and ``base_link`` (odometry), ``map`` and ``base_link`` (ground truth)
    after_ns : only the poses stamped after it (a live stream: what is new since the last call)

    Returns
    -------
    One pose at each stamp of a moving transform between the two frames where all of them are known,
    in stamp order. RecorderError when a frame is missing or the frames are not linked by moving transforms.
    """
    kind = OdometryPose if target == TOPIC_ODOM else GroundTruthPose
    stamps, poses = tree.planar_poses(frame, base_frame, after_ns)
    return [kind(int(t), *pose.tolist()) for t, pose in zip(stamps, poses, strict=True)]


def iter_plan_lines(plan: BagPlan) -> Iterator[str]:
    """The plan as text lines for ``slamreplay inspect``."""
    yield f"ROS 2 bag {plan.path} ({plan.storage} storage)"
    yield f"{'topic':<28} {'type':<44} {'messages':>9}  maps to"
    for t in plan.topics:
        target = t.maps_to or "ignored"
        yield f"{t.topic:<28} {t.msgtype:<44} {t.messages:>9}  {target} ({t.note})"
    if plan.tf_edges:
        yield "tf: " + ", ".join(f"{parent} -> {child}" for parent, child in plan.tf_edges)
    for option, check in plan.frame_checks.items():
        yield f"{option} {check}"
