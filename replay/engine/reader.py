"""The ordered reader: one total order over a recording's messages, MCAP and ROS 2 bags alike.

Messages come out in the order (log_time, position in the file): the MCAP reader merges
chunks by log_time and breaks ties by chunk offset, then by position inside the chunk.
File topics are mapped onto slamreplay's logical topics (``/odom``, ``/camera/image``...):
identically named topics map to themselves, a ``--topic-map`` names the others, and in a
ROS 2 bag a message type that appears on exactly one topic is mapped automatically.
"""

from __future__ import annotations

import heapq
import re
from collections.abc import Iterable, Iterator, Mapping
from dataclasses import dataclass, field
from operator import itemgetter
from pathlib import Path
from typing import Any

from mcap.opcode import Opcode
from mcap.records import Channel, Chunk, ChunkIndex, Metadata, Schema
from mcap.records import Message as McapMessage

from slamreplay.recorder.codec import TopicDecoder
from slamreplay.recorder.codec.bounds import shown
from slamreplay.recorder.codec.mcap_io import McapFile, Summary, chunk_messages, chunk_records, decompress, record_name
from slamreplay.recorder.codec.ros2 import canonical_ros_type
from slamreplay.recorder.errors import CodecError, DamageError
from slamreplay.recorder.messages import TOPIC_TYPES, Message
from slamreplay.replay.engine.recording_file import (  # noqa: F401  (also imported from here: inspect, navigate, api)
    MCAP_MAGIC,
    check_framing,
    resolve_mcap_path,
)
from slamreplay.replay.errors import ReplayError

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


ROBOT_NAMESPACE = re.compile(r"/robot\d+(?=/)")  # a robot of a multi-robot recording: /robot2/odom


def topic_type(logical: str) -> type | None:
    """The message type of a logical topic: a slamreplay topic (``/odom``), or one under a robot's namespace
    (``/robot2/odom``, read by multi-robot pipelines); None for anything else."""
    ns = ROBOT_NAMESPACE.match(logical)
    return TOPIC_TYPES.get(logical[ns.end():] if ns else logical)


LISTED = 20  # topics an error names at most: a file may declare 65,535 channels, and an error is one line


def listed(topics: Iterable[str], most: int = LISTED) -> str:
    """Sorted topic names for an error line, each shortened, the first ``most`` and how many more."""
    names = sorted(set(topics))
    more = f" and {len(names) - most:,} more (`slamreplay inspect` lists them)" if len(names) > most else ""
    return ", ".join(shown(t) for t in names[:most]) + more if names else "(none)"


def resolve_topic_map(channels: Iterable[tuple[str, str]], explicit: Mapping[str, str] | None) -> dict[str, str]:
    """Map file topics onto logical topics.

    ``channels`` gives (file topic, schema name) pairs; ``explicit`` maps file topics to
    logical topics and wins over the identity and the ROS 2 automatic mapping.
    """
    chans = dict(channels)
    result: dict[str, str] = {}
    for file_topic, logical in (explicit or {}).items():
        if topic_type(logical) is None:
            known = ", ".join(TOPIC_TYPES)
            raise ReplayError(f"topic map target {logical} is not a slamreplay topic; use one of {known}")
        if file_topic not in chans:
            raise ReplayError(f"topic map names {file_topic}, which is not in the recording; "
                              f"its topics are: {listed(chans)}")
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
        self._chunk_indexes: list[ChunkIndex] | None = None
        try:
            with McapFile(self.path) as f:
                header = f.header()
                summary = f.summary()
                if summary is not None:
                    metadata = self._metadata(f, summary)
                    self._chunk_indexes = summary.chunk_indexes or None
        except DamageError as err:
            raise self._damaged(err, "its index") from err
        if summary is None or not summary.chunk_indexes:
            schemas, channels, counts, t0, t1, n, metadata = self._scan()
            nchunks = 0
        if summary is not None:
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

    def _damaged(self, err: DamageError, what: str) -> ReplayError:
        return ReplayError(f"{self.path} is damaged ({what}): {err}. Salvage the readable messages with "
                           f"`slamreplay recover {self.path} --out FIXED.mcap`")

    @staticmethod
    def _metadata(f: McapFile, summary: Summary) -> dict[str, dict[str, str]]:
        """The Metadata records the summary indexes."""
        out: dict[str, dict[str, str]] = {}
        for index in summary.metadata_indexes:
            opcode, record, _ = f.record_at(index.offset, index.offset + index.length)
            if not isinstance(record, Metadata):
                raise DamageError(f"a MetadataIndex points at byte {index.offset}, where a {record_name(opcode)} "
                                  f"record is, not a Metadata record")
            out[record.name] = dict(record.metadata)
        return out

    def _linear(self, f: McapFile) -> Iterator[tuple[int, int, Any]]:
        """(chunk offset, index in chunk, record) of every schema, channel, message and metadata record, in
        file order; the chunk offset of a record outside chunks is its own."""
        for offset, opcode, record in f.records():
            if isinstance(record, Chunk):
                data = decompress(record, offset)
                for i, inner in enumerate(chunk_records(data, offset)):
                    yield offset, i, inner
            elif opcode in (Opcode.SCHEMA, Opcode.CHANNEL, Opcode.MESSAGE, Opcode.METADATA):
                yield offset, 0, record
            elif opcode in (Opcode.DATA_END, Opcode.FOOTER):
                return

    def _scan(self) -> tuple[dict[int, Schema], dict[int, Channel], dict[int, int], int, int, int,
                             dict[str, dict[str, str]]]:
        """A file without chunk indexes: one linear pass to find schemas, channels, counts and metadata."""
        schemas: dict[int, Schema] = {}
        channels: dict[int, Channel] = {}
        counts: dict[int, int] = {}
        metadata: dict[str, dict[str, str]] = {}
        t0, t1, n = 0, 0, 0
        try:
            with McapFile(self.path) as f:
                for _, _, record in self._linear(f):
                    if isinstance(record, Schema):
                        schemas[record.id] = record
                    elif isinstance(record, Channel):
                        channels[record.id] = record
                    elif isinstance(record, Metadata):
                        metadata[record.name] = dict(record.metadata)
                    elif isinstance(record, McapMessage):
                        if record.channel_id not in channels:
                            raise DamageError(f"a Message record refers to channel {record.channel_id}, which no "
                                              f"Channel record before it defines")
                        counts[record.channel_id] = counts.get(record.channel_id, 0) + 1
                        t0 = record.log_time if n == 0 else min(t0, record.log_time)
                        t1 = max(t1, record.log_time)
                        n += 1
        except DamageError as err:
            raise self._damaged(err, "found reading it from the start, as it has no chunk index") from err
        return schemas, channels, counts, t0, t1, n, metadata

    def decoder(self, logical_topic: str) -> TopicDecoder:
        """The decoder of a logical topic; ReplayError when it is absent or unreadable."""
        topics = self.info.logical_topics()
        info = topics.get(logical_topic)
        if info is None:
            have = listed(t.file_topic for t in self.info.topics)
            raise ReplayError(f"{self.path.name} has no {logical_topic} topic; its topics are: {have}. "
                              f"If the data is there under another name, map it with "
                              f"--topic-map FILE_TOPIC={logical_topic}")
        channel = next(c for c in self._channels.values() if c.topic == info.file_topic)
        kind = topic_type(logical_topic)
        assert kind is not None  # the topic map only maps onto typed topics
        if channel.schema_id and channel.schema_id not in self._schemas:
            err = DamageError(f"the Channel record of {shown(channel.topic)} refers to schema {channel.schema_id}, "
                              f"which no Schema record defines")
            raise self._damaged(err, f"topic {logical_topic}")
        try:
            return TopicDecoder(logical_topic, kind, self._schemas.get(channel.schema_id),
                                channel.message_encoding)
        except CodecError as err:
            # a schema that does not parse is damage (recover drops its channel); a schema of the wrong type is not
            hint = (f". `slamreplay recover {self.path} --out FIXED.mcap` keeps the other topics"
                    if err.__cause__ is not None else "")
            raise ReplayError(f"{self.path.name}: {err}{hint}") from err

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
                raise ReplayError(f"{self.path.name}: {err}. `slamreplay recover {self.path} --out FIXED.mcap` "
                                  f"drops the messages that do not decode") from err
            yield Envelope(dec.topic, log_time, publish_time, index, msg)

    def raw(self, file_topics: Iterable[str], *, start_ns: int | None = None,
            end_ns: int | None = None) -> Iterator[tuple[Channel, int, int, bytes]]:
        """Undecoded (channel, log_time, publish_time, data) of file topics in replay order.

        Replay order is (log_time, offset of the message's chunk, position in the chunk): chunks
        are read lazily, merged by their first log time. Raises ReplayError naming the damaged
        record and its byte offset (CRC mismatch, a length past the end, a bad field...).
        """
        names = set(file_topics)
        wanted = {cid for cid, c in self._channels.items() if c.topic in names}
        try:
            with McapFile(self.path) as f:
                if self._chunk_indexes is None:
                    yield from self._raw_linear(f, wanted, start_ns, end_ns)
                else:
                    yield from self._raw_indexed(f, wanted, start_ns, end_ns)
        except DamageError as err:
            raise self._damaged(err, "while reading its messages") from err

    def _keep(self, m: McapMessage, wanted: set[int], start_ns: int | None, end_ns: int | None, where: str) -> bool:
        if m.channel_id not in self._channels:
            raise DamageError(f"a Message record {where} refers to channel {m.channel_id}, which the file does "
                              f"not define")
        return (m.channel_id in wanted and (start_ns is None or m.log_time >= start_ns)
                and (end_ns is None or m.log_time < end_ns))

    def _raw_indexed(self, f: McapFile, wanted: set[int], start_ns: int | None,
                     end_ns: int | None) -> Iterator[tuple[Channel, int, int, bytes]]:
        """A k-way merge of the chunks, each read when the merge reaches its first log time.

        The merge key of a message is (log_time, chunk offset, index in chunk); a chunk enters the
        heap with key (message_start_time, offset, -1). When every message of a chunk just read
        sorts before the heap's smallest key (chunks that do not overlap in time, the usual case),
        the chunk is yielded in one stable sort by log_time, which is the same order, without a
        heap push per message.
        """
        assert self._chunk_indexes is not None
        heap: list[tuple[int, int, int, Any]] = []
        for ci in self._chunk_indexes:
            if start_ns is not None and ci.message_end_time < start_ns:
                continue
            if end_ns is not None and ci.message_start_time >= end_ns:
                continue
            heapq.heappush(heap, (ci.message_start_time, ci.chunk_start_offset, -1, ci))
        channels = self._channels
        while heap:
            _, offset, i, item = heapq.heappop(heap)
            if i >= 0:
                log_time, _, channel_id, publish_time, data = item
                yield channels[channel_id], log_time, publish_time, data
                continue
            chunk, _ = f.chunk(item)
            found = chunk_messages(decompress(chunk, offset), offset)
            unknown = next((m[2] for m in found if m[2] not in channels), None)
            if unknown is not None:
                raise DamageError(f"a Message record in the chunk at byte {offset} refers to channel {unknown}, "
                                  f"which the file does not define")
            kept = [m for m in found if m[2] in wanted and (start_ns is None or m[0] >= start_ns)
                    and (end_ns is None or m[0] < end_ns)]
            if not kept:
                continue
            last = max(m[0] for m in kept)
            if not heap or heap[0][:2] > (last, offset):
                kept.sort(key=itemgetter(0))  # stable: ties keep their order in the chunk
                for log_time, _, channel_id, publish_time, data in kept:
                    yield channels[channel_id], log_time, publish_time, data
                continue
            for m in kept:
                heapq.heappush(heap, (m[0], offset, m[1], m))

    def _raw_linear(self, f: McapFile, wanted: set[int], start_ns: int | None,
                    end_ns: int | None) -> Iterator[tuple[Channel, int, int, bytes]]:
        found = [(r.log_time, offset, i, r) for offset, i, r in self._linear(f)
                 if isinstance(r, McapMessage) and self._keep(r, wanted, start_ns, end_ns, f"at byte {offset}")]
        found.sort(key=lambda t: t[:3])
        for _, _, _, m in found:
            yield self._channels[m.channel_id], m.log_time, m.publish_time, m.data
