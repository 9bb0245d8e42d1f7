"""Which channels of a live stream are recorded, as what, and how a payload becomes messages.

A channel is chosen by ``--topics`` (names, globs such as ``/robot/*``, or ``re:REGEX`` matched against the
whole topic; none given: every channel), then mapped onto a logical topic of the recording (docs/design.md,
"Recording format"), as the ROS 2 bag importer maps a bag's topics:

- ``protobuf`` or ``json`` channels in a schema slamreplay reads (``foxglove.PoseInFrame``,
  ``foxglove.CompressedImage``, ``foxglove.RawImage``, ``foxglove.CameraCalibration``, slamreplay's own):
  the message as it comes (decoded, checked, written in the same schema);
- ``cdr`` channels with a ``ros2msg`` schema: the types ``record ros2`` reads, converted by its functions
  (:mod:`.ros2bag`): odometry, poses, IMU, laser scans (poles as landmarks, moved into ``base_frame`` by
  ``/tf_static``), images, camera info; ``/tf`` (with ``/tf_static``) gives odometry when no channel does
  (``base_frame`` in ``odom_frame``) and ground truth given a ``ground_truth_frame``, composed through the tree;
- anything else is listed and skipped, with the reason.

A channel whose topic is a logical topic it may carry maps there; the others take the first logical topic
their type can become that no channel has taken, in name order (``--topic-map CHANNEL=TOPIC`` picks another).
"""

from __future__ import annotations

import fnmatch
import re
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from typing import Any

from slamreplay.recorder.errors import RecorderError
from slamreplay.recorder.importers.foxglove_ws import ChannelInfo
from slamreplay.recorder.importers.pole_config import PoleConfig
from slamreplay.recorder.messages import (
    TOPIC_GROUND_TRUTH_POSE,
    TOPIC_NAV_LOCALIZATION,
    TOPIC_ODOM,
    TOPIC_RANGE_BEARING,
    TOPIC_TYPES,
    Message,
)

TF_TREE = "transform tree"
# (logical topic, message, (schema data, bytes) when the message is written as it came)
Converted = tuple[str, Message, tuple[bytes, bytes] | None]
TF, TF_STATIC = "/tf", "/tf_static"
TF_TYPE = "tf2_msgs/msg/TFMessage"
# Logical topics a live stream does not feed: a pipeline's output
NOT_RECORDED = (TOPIC_NAV_LOCALIZATION,)
READS = ("slamreplay records protobuf or JSON channels in Foxglove's and slamreplay's schemas (foxglove.PoseInFrame, "
         "foxglove.CompressedImage, foxglove.RawImage, foxglove.CameraCalibration, slamreplay.*) and ROS 2 CDR "
         "channels of the types `record ros2` reads")


@dataclass(frozen=True, slots=True)
class ChannelPlan:
    """One advertised channel: the logical topic it becomes (``transform tree``: read for the laser's mounting;
    None: skipped) and why."""

    channel: ChannelInfo
    maps_to: str | None
    note: str
    composes: tuple[str, ...] = ()  # /tf: the logical topics composed through the tree (odometry, ground truth)

    def line(self) -> str:
        c = self.channel
        what = f"{c.encoding} {c.schema_name or '(no schema)'}"
        return f"{c.topic:<28} {what:<44} " + (f"-> {self.maps_to} ({self.note})" if self.maps_to else
                                               f"skipped: {self.note}")


def compile_patterns(patterns: Iterable[str]) -> Callable[[str], bool]:
    """A predicate on topics: true when a pattern matches (a name, a glob, or ``re:REGEX`` on the whole topic);
    every topic when there is no pattern. RecorderError for a regular expression that does not compile."""
    regexes: list[re.Pattern[str]] = []
    globs: list[str] = []
    for p in patterns:
        if p.startswith("re:"):
            try:
                regexes.append(re.compile(p[3:]))
            except re.error as err:
                raise RecorderError(f"--topics {p!r}: not a regular expression ({err})") from None
        else:
            globs.append(p)

    def selected(topic: str) -> bool:
        return (not regexes and not globs) or any(r.fullmatch(topic) for r in regexes) or any(
            fnmatch.fnmatchcase(topic, g) for g in globs)

    return selected


def ros_type(channel: ChannelInfo) -> str:
    from slamreplay.recorder.codec.ros2 import canonical_ros_type

    return canonical_ros_type(channel.schema_name)


def targets(channel: ChannelInfo) -> tuple[str, ...]:
    """The logical topics a channel can become (the first: its automatic mapping); () when none."""
    from slamreplay.recorder.codec.live import PROTOBUF_SCHEMAS
    from slamreplay.recorder.codec.protobuf import READABLE_SCHEMAS
    from slamreplay.recorder.importers.ros2bag import TARGETS

    if channel.encoding == "cdr" and channel.schema_encoding == "ros2msg":
        return TARGETS.get(ros_type(channel), ())
    if channel.encoding in ("protobuf", "json") and channel.schema_name in PROTOBUF_SCHEMAS:
        return tuple(t for t, kind in TOPIC_TYPES.items()
                     if t not in NOT_RECORDED and channel.schema_name in READABLE_SCHEMAS[kind])
    return ()


def _why_not(channel: ChannelInfo) -> str:
    if channel.problem:
        return channel.problem
    if channel.encoding == "cdr" and channel.schema_encoding != "ros2msg":
        return f"a {channel.schema_encoding or 'schema-less'} schema: slamreplay reads ROS 2 CDR with ros2msg schemas"
    if channel.encoding == "cdr":
        return f"ROS 2 type {ros_type(channel)} is not read by slamreplay"
    if channel.encoding in ("protobuf", "json"):
        return f"schema {channel.schema_name or '(none)'} is not one slamreplay reads"
    return f"{channel.encoding} encoding is not read: {READS}"


def plan_channels(channels: Iterable[ChannelInfo], selected: Callable[[str], bool], topic_map: Mapping[str, str],
                  taken: dict[str, str], ground_truth_frame: str | None = None) -> list[ChannelPlan]:
    """Map ``channels`` onto logical topics; ``taken`` (logical topic -> channel topic, updated) holds what earlier
    channels of the stream took; ``/tf`` gives ground truth when ``ground_truth_frame`` is given. RecorderError
    when ``topic_map`` asks for what a channel cannot become."""
    plans: dict[int, ChannelPlan] = {}
    todo = sorted(channels, key=lambda c: (c.topic, c.id))
    for c in todo:
        if not selected(c.topic):
            plans[c.id] = ChannelPlan(c, None, "not chosen by --topics")
        elif c.topic in topic_map:
            target = topic_map[c.topic]
            allowed = targets(c)
            if target not in allowed:
                can = ", ".join(allowed) if allowed else f"nothing ({_why_not(c)})"
                raise RecorderError(f"--topic-map {c.topic}={target}: a {c.encoding} {c.schema_name} channel can "
                                    f"become {can}")
            if taken.get(target, c.topic) != c.topic:
                raise RecorderError(f"--topic-map {c.topic}={target}: {target} comes from {taken[target]} already")
            taken[target] = c.topic
            plans[c.id] = ChannelPlan(c, target, "--topic-map")
    # a channel named as a logical topic it may carry keeps its name, before the others choose
    for c in todo:
        if c.id not in plans and c.topic in targets(c) and taken.get(c.topic, c.topic) == c.topic:
            taken[c.topic] = c.topic
            plans[c.id] = ChannelPlan(c, c.topic, "as named")
    scans = TOPIC_RANGE_BEARING in taken or any(TOPIC_RANGE_BEARING in targets(c) for c in todo if selected(c.topic))
    tfs = [c for c in todo if c.id not in plans and c.encoding == "cdr" and ros_type(c) == TF_TYPE]
    for c in todo:
        if c.id in plans or c in tfs:
            continue
        options = targets(c)
        if not options or c.problem:
            plans[c.id] = ChannelPlan(c, None, _why_not(c))
            continue
        target = options[0]
        if taken.get(target, c.topic) != c.topic:
            plans[c.id] = ChannelPlan(c, None, f"{target} comes from {taken[target]} (pick another with "
                                               f"--topic-map {c.topic}={target})")
            continue
        taken[target] = c.topic
        how = {TOPIC_RANGE_BEARING: "poles and trunks as landmarks, ids unknown"}.get(target, "automatic") \
            if c.encoding == "cdr" else "as it comes"
        plans[c.id] = ChannelPlan(c, target, how)
    # the tf channels last, as the bag importer decides them: /tf gives odometry when no channel does, and ground
    # truth with a ground-truth frame; /tf_static the laser's mounting and the static links of those
    for c in sorted(tfs, key=lambda c: c.topic != TF):
        plans[c.id] = _plan_tf(c, taken, scans, ground_truth_frame)
    return [plans[c.id] for c in todo]


def _plan_tf(c: ChannelInfo, taken: dict[str, str], scans: bool, ground_truth_frame: str | None) -> ChannelPlan:
    if c.topic not in (TF, TF_STATIC):
        return ChannelPlan(c, None, "transforms are read from /tf and /tf_static only")
    composes: list[str] = []
    if c.topic == TF:
        for target, wanted in ((TOPIC_ODOM, True), (TOPIC_GROUND_TRUTH_POSE, ground_truth_frame is not None)):
            if wanted and taken.get(target, TF) == TF:
                taken[target] = TF
                composes.append(target)
    uses = [what for what, on in (("odometry", TOPIC_ODOM in composes), ("ground truth", TOPIC_GROUND_TRUTH_POSE
                                                                          in composes)) if on]
    if c.topic == TF_STATIC:
        uses = [what for what, on in (("odometry", taken.get(TOPIC_ODOM) == TF),
                                      ("ground truth", taken.get(TOPIC_GROUND_TRUTH_POSE) == TF),
                                      ("the laser's mounting", scans)) if on]
    if not uses:
        why = f"not needed: odometry comes from {taken.get(TOPIC_ODOM)}" if TOPIC_ODOM in taken else \
            "not needed: no odometry, ground truth or laser scan is composed through it"
        return ChannelPlan(c, None, why + ("" if ground_truth_frame else " and no --ground-truth-frame was given"))
    return ChannelPlan(c, TF_TREE, " and ".join(uses) + " composed through the tree", tuple(composes))


@dataclass
class Conversion:
    """Turns payloads of planned channels into (logical topic, message) pairs; shared state of a stream: the
    transform tree (``/tf``, ``/tf_static``), the poses composed through it so far, and laser scans held until
    the laser's mounting is known."""

    base_frame: str = "base_link"
    poles: PoleConfig = field(default_factory=PoleConfig)
    odom_frame: str = "odom"
    ground_truth_frame: str | None = None
    tree: Any = None
    composed: dict[str, int | None] = field(default_factory=dict)  # logical topic -> stamp of its last pose
    _decoders: dict[int, Callable[[bytes, int], list[Converted]]] = field(default_factory=dict)
    held: list[tuple[int, str, Any]] = field(default_factory=list)  # scans: (stamp, frame, LaserScan)
    hold_scans: bool = False  # until /tf_static has given the laser's mounting
    scans_converted: int = 0
    poles_found: int = 0

    def __post_init__(self) -> None:
        from slamreplay.recorder.importers.tf_tree import TfTree

        self.tree = TfTree()

    def add(self, plan: ChannelPlan) -> None:
        """Make the decoder of a planned channel (CodecError: its schema cannot be read)."""
        c, target = plan.channel, plan.maps_to
        assert target is not None
        for topic in plan.composes:
            self.composed.setdefault(topic, None)
        if c.encoding == "cdr":
            from slamreplay.recorder.codec.live import ros2_decoder
            from slamreplay.recorder.importers.ros2bag import convert_message

            raw = ros2_decoder(c.topic, c.schema_name, c.schema)
            msgtype = ros_type(c)
            logical = None if target == TF_TREE else target
            if c.topic == TF_STATIC:
                self.hold_scans = True

            def cdr(data: bytes, stamp_ns: int) -> list[Converted]:
                obj = raw(data)
                try:
                    item = convert_message(c.topic, msgtype, logical, obj, stamp_ns, self.tree, self.held)
                except (ValueError, AttributeError, TypeError) as err:  # values a message cannot hold
                    raise RecorderError(f"a {msgtype} message on {c.topic} cannot be read: {err}") from err
                if c.topic == TF_STATIC:
                    self.hold_scans = False
                out: list[Converted] = [(item[0], item[1], None)] if item is not None else []
                return out + self.release()

            self._decoders[c.id] = cdr
        else:
            from slamreplay.recorder.codec.live import message_decoder

            dec = message_decoder(c.topic, TOPIC_TYPES[target], c.encoding, c.schema_name, c.schema_encoding,
                                  c.schema)
            if c.encoding == "protobuf":  # decoded to check it and read its stamp, written as it came
                self._decoders[c.id] = lambda data, stamp_ns: [(target, dec(data, stamp_ns), (c.schema, data))]
            else:
                self._decoders[c.id] = lambda data, stamp_ns: [(target, dec(data, stamp_ns), None)]

    def __call__(self, channel_id: int, data: bytes, stamp_ns: int) -> list[Converted]:
        """The messages a payload of channel ``channel_id`` gives (``stamp_ns``: its time if it states none)."""
        return self._decoders[channel_id](data, stamp_ns)

    def release(self, force: bool = False) -> list[Converted]:
        """Scans held so far, as range-bearing scans, once the laser's mounting is known (or ``force``)."""
        if not self.held or (self.hold_scans and not force):
            return []
        from slamreplay.recorder.importers.ros2bag import poles_scan

        out: list[Converted] = []
        for stamp, frame, scan in self.held:
            mount = (0.0, 0.0, 0.0)
            if frame and frame != self.base_frame and {frame, self.base_frame} <= self.tree.frames:
                mount = self.tree.static_planar(self.base_frame, frame) or mount
            rb = poles_scan(stamp, scan, self.poles, mount)
            self.poles_found += len(rb)
            out.append((TOPIC_RANGE_BEARING, rb, None))
        self.scans_converted += len(self.held)
        self.held.clear()
        return out

    def compose(self) -> tuple[list[Converted], list[str]]:
        """Odometry and ground truth composed through the tree since the last call (as ``record ros2`` composes
        them: a pose at each stamp of the moving transforms where all of them are known), and why a composed
        topic has none (a frame not in the tree yet, frames not linked)."""
        from slamreplay.recorder.importers.ros2bag import tf_poses

        out: list[Converted] = []
        problems: list[str] = []
        for topic, after in self.composed.items():
            frame = self.odom_frame if topic == TOPIC_ODOM else self.ground_truth_frame
            assert frame is not None
            option = "--odom-frame" if topic == TOPIC_ODOM else "--ground-truth-frame"
            try:
                self.tree.check_frame(frame, option)
                self.tree.check_frame(self.base_frame, "--base-frame")
                msgs = tf_poses(self.tree, topic, frame, self.base_frame, after)
            except RecorderError as err:
                problems.append(f"{topic} from /tf: {err}")
                continue
            if msgs:
                self.composed[topic] = msgs[-1].stamp_ns
            out += [(topic, m, None) for m in msgs]
        done = [t for t in self.composed.values() if t is not None]
        if done:  # what no later pose needs is dropped (a topic that never composed holds nothing back)
            self.tree.forget_before(min(done))
        return out, problems
