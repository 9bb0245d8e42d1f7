"""The ordered reader: one total order over a recording's messages, MCAP and ROS 2 bags alike.

Messages come out in the order (log_time, position in the file): the MCAP reader merges
chunks by log_time and breaks ties by chunk offset, then by position inside the chunk.
File topics are mapped onto slamreplay's logical topics (``/odom``, ``/camera/image``...):
identically named topics map to themselves, a ``--topic-map`` names the others, and in a
ROS 2 bag a message type that appears on exactly one topic is mapped automatically.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path

from mcap.exceptions import McapError
from mcap.reader import NonSeekingReader, make_reader
from mcap.records import Channel, Schema
from mcap.stream_reader import CRCValidationError

from recorder.codec import TopicDecoder
from recorder.codec.ros2 import canonical_ros_type
from recorder.errors import CodecError
from recorder.messages import TOPIC_TYPES, Message
from replay.errors import ReplayError

MCAP_MAGIC = b"\x89MCAP0\r\n"

# In a ROS 2 bag, a message type found on exactly one unmapped topic is mapped here.
ROS2_AUTO_MAP = {
    "nav_msgs/msg/Odometry": "/odom",
    "geometry_msgs/msg/PoseStamped": "/ground_truth/pose",
    "sensor_msgs/msg/Image": "/camera/image",
    "sensor_msgs/msg/CompressedImage": "/camera/image",
}


@dataclass(frozen=True, slots=True)
class Envelope:
    """One decoded message in replay order; ``index`` is its position in that order."""

    topic: str
    log_time_ns: int
    publish_time_ns: int
    index: int
    msg: Message


@dataclass(frozen=True, slots=True)
class TopicInfo:
    """A channel of the file, and the logical topic it is read as (None: not read)."""

    file_topic: str
    logical_topic: str | None
    schema_name: str
    message_encoding: str
    message_count: int


@dataclass(frozen=True, slots=True)
class RecordingInfo:
    """What a recording holds, from its summary section."""

    path: Path
    size_bytes: int
    profile: str
    library: str
    topics: tuple[TopicInfo, ...]
    message_count: int
    start_ns: int
    end_ns: int
    chunk_count: int
    metadata: dict[str, dict[str, str]] = field(default_factory=dict)

    def logical_topics(self) -> dict[str, TopicInfo]:
        """Mapped topics, keyed by logical topic."""
        return {t.logical_topic: t for t in self.topics if t.logical_topic is not None}


def resolve_mcap_path(path: Path) -> Path:
    """The MCAP file of ``path``: the file itself, or the one .mcap in a ROS 2 bag directory."""
    if not path.exists():
        raise ReplayError(f"{path}: no such file or directory")
    if path.is_dir():
        mcaps = sorted(path.glob("*.mcap"))
        if len(mcaps) == 1:
            return mcaps[0]
        if not mcaps and list(path.glob("*.db3")):
            raise ReplayError(f"{path} is a ROS 2 bag in sqlite3 storage; slamreplay reads MCAP storage: "
                              f"convert it with `ros2 bag convert` (storage_id: mcap)")
        what = "no .mcap file" if not mcaps else f"{len(mcaps)} .mcap files (split bag)"
        raise ReplayError(f"{path} is a directory with {what}; give one .mcap file "
                          f"(merge split bags with `ros2 bag convert` first)")
    return path


def check_framing(path: Path) -> None:
    """Raise ReplayError when ``path`` is empty, not an MCAP file, or truncated."""
    size = path.stat().st_size
    if size == 0:
        raise ReplayError(f"{path} is empty (0 bytes): nothing was recorded")
    with open(path, "rb") as f:
        head = f.read(8)
        if head != MCAP_MAGIC:
            raise ReplayError(f"{path} is not an MCAP file (it starts with {head[:8]!r}); slamreplay reads "
                              f"MCAP recordings and ROS 2 bags in MCAP storage")
        f.seek(max(0, size - 8))
        if size < 16 or f.read(8) != MCAP_MAGIC:
            raise ReplayError(f"{path} is truncated: it has no MCAP footer, so it was not closed cleanly. "
                              f"Salvage its messages with `slamreplay recover {path} --out FIXED.mcap`")


def resolve_topic_map(channels: Iterable[tuple[str, str]], explicit: Mapping[str, str] | None) -> dict[str, str]:
    """Map file topics onto logical topics.

    ``channels`` gives (file topic, schema name) pairs; ``explicit`` maps file topics to
    logical topics and wins over the identity and the ROS 2 automatic mapping.
    """
    chans = dict(channels)
    result: dict[str, str] = {}
    for file_topic, logical in (explicit or {}).items():
        if logical not in TOPIC_TYPES:
            known = ", ".join(TOPIC_TYPES)
            raise ReplayError(f"topic map target {logical} is not a slamreplay topic; use one of {known}")
        if file_topic not in chans:
            raise ReplayError(f"topic map names {file_topic}, which is not in the recording; "
                              f"its topics are: {', '.join(sorted(chans)) or '(none)'}")
        result[file_topic] = logical
    taken = set(result.values())
    for file_topic in chans:
        if file_topic in TOPIC_TYPES and file_topic not in result and file_topic not in taken:
            result[file_topic] = file_topic
            taken.add(file_topic)
    for ros_type, logical in ROS2_AUTO_MAP.items():
        if logical in taken:
            continue
        candidates = [t for t, s in chans.items() if t not in result and canonical_ros_type(s) == ros_type]
        if len(candidates) == 1:
            result[candidates[0]] = logical
            taken.add(logical)
    return result


class RecordingReader:
    """Read a recording in replay order.

    Parameters
    ----------
    path : an MCAP file, or a ROS 2 bag directory holding one.
    topic_map : file topic -> logical topic, for recordings that use other topic names.

    Raises
    ------
    ReplayError
        When the file is missing, empty, not an MCAP, truncated or its summary is corrupt.
    """

    def __init__(self, path: str | Path, topic_map: Mapping[str, str] | None = None) -> None:
        self.path = resolve_mcap_path(Path(path))
        check_framing(self.path)
        try:
            with open(self.path, "rb") as f:
                reader = make_reader(f)
                summary = reader.get_summary()
                header = reader.get_header()
                metadata = {m.name: dict(m.metadata) for m in reader.iter_metadata()}
        except (McapError, CRCValidationError, ValueError, EOFError) as err:
            raise ReplayError(f"{self.path} has a corrupt index ({err}); salvage it with "
                              f"`slamreplay recover {self.path} --out FIXED.mcap`") from err
        if summary is None:
            schemas, channels, counts, t0, t1, n, nchunks = self._scan()
        else:
            schemas, channels = dict(summary.schemas), dict(summary.channels)
            st = summary.statistics
            counts = dict(st.channel_message_counts) if st else {}
            t0 = st.message_start_time if st else 0
            t1 = st.message_end_time if st else 0
            n = st.message_count if st else sum(counts.values())
            nchunks = len(summary.chunk_indexes)
        self._schemas: dict[int, Schema] = schemas
        self._channels: dict[int, Channel] = channels
        names = {cid: schemas[c.schema_id].name if c.schema_id in schemas else "" for cid, c in channels.items()}
        self.topic_map = resolve_topic_map(((c.topic, names[cid]) for cid, c in channels.items()), topic_map)
        topics = tuple(TopicInfo(c.topic, self.topic_map.get(c.topic), names[cid], c.message_encoding,
                                 counts.get(cid, 0)) for cid, c in sorted(channels.items()))
        self.info = RecordingInfo(self.path, self.path.stat().st_size, header.profile, header.library, topics,
                                  n, t0, t1, nchunks, metadata)

    def _scan(self) -> tuple[dict[int, Schema], dict[int, Channel], dict[int, int], int, int, int, int]:
        """Summary-less file: one linear pass to find schemas, channels and counts."""
        schemas: dict[int, Schema] = {}
        channels: dict[int, Channel] = {}
        counts: dict[int, int] = {}
        t0, t1, n = 0, 0, 0
        with open(self.path, "rb") as f:
            for schema, channel, message in NonSeekingReader(f).iter_messages(log_time_order=False):
                if schema is not None:
                    schemas[schema.id] = schema
                channels[channel.id] = channel
                counts[channel.id] = counts.get(channel.id, 0) + 1
                t0 = message.log_time if n == 0 else min(t0, message.log_time)
                t1 = max(t1, message.log_time)
                n += 1
        return schemas, channels, counts, t0, t1, n, 0

    def decoder(self, logical_topic: str) -> TopicDecoder:
        """The decoder of a logical topic; ReplayError when it is absent or unreadable."""
        topics = self.info.logical_topics()
        info = topics.get(logical_topic)
        if info is None:
            have = ", ".join(sorted(t.file_topic for t in self.info.topics)) or "(none)"
            raise ReplayError(f"{self.path.name} has no {logical_topic} topic; its topics are: {have}. "
                              f"If the data is there under another name, map it with "
                              f"--topic-map FILE_TOPIC={logical_topic}")
        channel = next(c for c in self._channels.values() if c.topic == info.file_topic)
        try:
            return TopicDecoder(logical_topic, TOPIC_TYPES[logical_topic], self._schemas.get(channel.schema_id),
                                channel.message_encoding)
        except CodecError as err:
            raise ReplayError(f"{self.path.name}: {err}") from err

    def messages(self, topics: Iterable[str] | None = None, *, exclude: Iterable[str] = (),
                 start_ns: int | None = None, end_ns: int | None = None) -> Iterator[Envelope]:
        """Decoded messages of the chosen logical topics in replay order, within [start_ns, end_ns).

        ``topics=None`` reads every mapped topic. Raises ReplayError for a missing or
        unreadable topic (before the first message), a CRC mismatch or a bad message.
        """
        wanted = [t for t in (self.info.logical_topics() if topics is None else topics) if t not in set(exclude)]
        decoders = {self.info.logical_topics()[t].file_topic if t in self.info.logical_topics() else t:
                    self.decoder(t) for t in wanted}
        raw = self.raw(decoders.keys(), start_ns=start_ns, end_ns=end_ns)
        for index, (channel, log_time, publish_time, data) in enumerate(raw):
            dec = decoders[channel.topic]
            try:
                msg = dec(data, log_time)
            except CodecError as err:
                raise ReplayError(f"{self.path.name}: {err}") from err
            yield Envelope(dec.topic, log_time, publish_time, index, msg)

    def raw(self, file_topics: Iterable[str], *, start_ns: int | None = None,
            end_ns: int | None = None) -> Iterator[tuple[Channel, int, int, bytes]]:
        """Undecoded (channel, log_time, publish_time, data) of file topics in replay order."""
        names = list(file_topics)
        with open(self.path, "rb") as f:
            reader = make_reader(f, validate_crcs=True)
            try:
                for _, channel, m in reader.iter_messages(topics=names, log_time_order=True,
                                                          starting_at=start_ns, ending_before=end_ns):
                    yield channel, m.log_time, m.publish_time, m.data
            except CRCValidationError as err:
                raise ReplayError(f"{self.path} is corrupt: {err}. Salvage the messages before the damage with "
                                  f"`slamreplay recover {self.path} --out FIXED.mcap`") from err
            except Exception as err:
                raise ReplayError(f"{self.path} is damaged ({type(err).__name__}: {err}). Try "
                                  f"`slamreplay recover {self.path} --out FIXED.mcap`") from err
