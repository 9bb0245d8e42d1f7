"""Salvage a truncated, ``.partial`` or damaged MCAP into a valid, indexed one, and say what was lost.

The input is read linearly, record by record, every length checked against the file
(:mod:`slamreplay.recorder.codec.mcap_io`). What is kept: every schema, channel, metadata and message
record that reads cleanly, re-written into a new file with zstd chunks and CRCs. What is
dropped, as byte ranges with the reason:

- a chunk that fails its CRC or does not decompress: the whole chunk (its content cannot be
  trusted); its lost messages are counted from the MessageIndex records that follow it;
- a record whose framing is broken (a length past the end, an unknown opcode where a record
  must start): the bytes up to the next chunk that reads cleanly, found through the summary's
  chunk index when it is readable, else by scanning for a Chunk record that passes its CRC;
- a chunk cut short by the end of the file: the part that is there is decompressed as a
  stream (zstd gives back whole blocks of up to 128 KiB) and its complete records are kept;
- a message that its channel's schema cannot decode (slamreplay's topics and schemas), and
  every message of a channel whose schema is damaged.

Messages lost are counted against the file's own Statistics record when the summary is
readable (exact), else from the MessageIndex records of dropped chunks (a lower bound when a
range without index was dropped). A file with no readable message is refused: nothing is written.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

from mcap.opcode import Opcode
from mcap.records import Channel, Chunk, Message, Metadata, Schema
from mcap.writer import CompressionType, Writer

from slamreplay.recorder.codec import READABLE_SCHEMAS, TopicDecoder
from slamreplay.recorder.codec.bounds import shown
from slamreplay.recorder.codec.mcap_io import (
    MAGIC,
    MAX_CHUNK_BYTES,
    McapFile,
    check_chunk_size,
    chunk_records,
    cut_chunk_records,
    decompress,
)
from slamreplay.recorder.codec.mcap_records import parse_record, record_name
from slamreplay.recorder.codec.ros2 import canonical_ros_type
from slamreplay.recorder.errors import CodecError, DamageError, RecorderError
from slamreplay.recorder.messages import TOPIC_TYPES
from slamreplay.recorder.sensor_model import METADATA_KEY, SensorModel
from slamreplay.recorder.version import version
from slamreplay.recorder.writer import CHUNK_SIZE, METADATA_NAME, partial_path

RESYNC_BYTES_PER_BYTE = 64  # see _Salvage.budget


@dataclass(frozen=True, slots=True)
class RecoveryReport:
    """What was kept and what was lost.

    ``messages`` kept on ``channels`` channels; ``lost`` messages known lost, exact when
    ``lost_exact`` (counted against the file's Statistics record), else a lower bound;
    ``dropped`` the byte ranges [start, end) left out, each with its reason; ``stopped_at``
    the first damage met (None: none).
    """

    messages: int
    channels: int
    stopped_at: str | None
    lost: int = 0
    lost_exact: bool = True
    expected: int | None = None
    dropped: tuple[tuple[int, int, str], ...] = ()
    notes: tuple[str, ...] = field(default_factory=tuple)


class _Copier:
    """Re-writes schemas, channels and messages into a new file, registering each once, decoding
    each message of a slamreplay-readable schema first so that nothing undecodable is kept."""

    def __init__(self, out: IO[bytes]) -> None:
        self.writer = Writer(out, chunk_size=CHUNK_SIZE, compression=CompressionType.ZSTD, enable_crcs=True)
        self.writer.start(profile="", library=f"slamreplay/{version()} recover")
        self.schemas: dict[int, Schema] = {}
        self.channels: dict[int, Channel] = {}
        self.schema_ids: dict[int, int] = {}
        self.channel_ids: dict[int, int] = {}
        self.decoders: dict[int, TopicDecoder | str | None] = {}  # None: not validated; str: why unreadable
        self.messages = 0
        self.rejected = 0
        self._reasons: dict[str, list[Any]] = {}  # what went wrong -> [first full reason, count]
        self.metadata_notes: list[str] = []

    def _decoder(self, channel: Channel) -> TopicDecoder | str | None:
        schema = self.schemas.get(channel.schema_id) if channel.schema_id else None
        if channel.schema_id and schema is None:
            return (f"topic {shown(channel.topic)}: its Schema record ({channel.schema_id}) was lost with the damaged "
                    f"bytes")
        name = canonical_ros_type(schema.name) if schema is not None else ""
        # slamreplay's own topics, and schemas it reads on any topic: kept only when they decode
        kind = TOPIC_TYPES.get(channel.topic) or next((k for k, names in READABLE_SCHEMAS.items() if name in names),
                                                      None)
        if kind is None:
            return None
        try:
            return TopicDecoder(channel.topic, kind, schema, channel.message_encoding)
        except CodecError as err:
            return str(err)

    def add(self, record: Any) -> None:
        if isinstance(record, Schema):
            self.schemas.setdefault(record.id, record)
        elif isinstance(record, Channel):
            self.channels.setdefault(record.id, record)
        elif isinstance(record, Metadata):
            self.writer.add_metadata(record.name, self._checked_metadata(record))
        elif isinstance(record, Message):
            self._message(record)

    def _checked_metadata(self, record: Metadata) -> dict[str, str]:
        """The record's map without a sensor model that does not read (damaged JSON): inspect and run read it."""
        kept = dict(record.metadata)
        for key in [k for k in kept if record.name == METADATA_NAME and k.startswith(METADATA_KEY)]:
            try:
                SensorModel.from_record(kept, key[len(METADATA_KEY):])
            except RecorderError as err:
                del kept[key]
                self.metadata_notes.append(f"the {shown(key)} entry of the {METADATA_NAME} metadata: {err}")
        return kept

    def _message(self, record: Message) -> None:
        channel = self.channels.get(record.channel_id)
        if channel is None:
            self._reject(f"messages of channel {record.channel_id}, whose Channel record was lost")
            return
        if record.channel_id not in self.decoders:
            self.decoders[record.channel_id] = self._decoder(channel)
        dec = self.decoders[record.channel_id]
        if isinstance(dec, str):
            self._reject(dec)
            return
        if dec is not None:
            try:
                dec(record.data, record.log_time)
            except CodecError as err:
                cause = type(err.__cause__).__name__ if err.__cause__ is not None else "CodecError"
                self._reject(f"{err} (the first of them)", key=f"{shown(channel.topic)}: {cause}")
                return
        channel_id = self.channel_ids.get(record.channel_id)
        if channel_id is None:
            schema_id = 0
            if channel.schema_id:
                if channel.schema_id not in self.schema_ids:
                    s = self.schemas[channel.schema_id]
                    self.schema_ids[channel.schema_id] = self.writer.register_schema(s.name, s.encoding, s.data)
                schema_id = self.schema_ids[channel.schema_id]
            channel_id = self.writer.register_channel(channel.topic, channel.message_encoding, schema_id,
                                                      channel.metadata)
            self.channel_ids[record.channel_id] = channel_id
        self.writer.add_message(channel_id, record.log_time, record.data, record.publish_time, record.sequence)
        self.messages += 1

    def _reject(self, why: str, key: str | None = None) -> None:
        self.rejected += 1
        entry = self._reasons.setdefault(key or why, [why, 0])
        entry[1] += 1

    @property
    def notes(self) -> list[str]:
        """One line per reason messages were dropped (how many, and the first one's reason), then one per
        metadata entry dropped."""
        return [f"{n} message{'s' if n != 1 else ''}: {why}" for why, n in self._reasons.values()] + self.metadata_notes


class _Salvage:
    """One linear pass over the damaged file."""

    def __init__(self, f: McapFile, copier: _Copier) -> None:
        self.f, self.copier = f, copier
        self.dropped: list[tuple[int, int, str]] = []
        self.lost_indexed = 0  # messages of dropped chunks, from their MessageIndex records
        self.unindexed_drop = False  # a dropped range whose messages nobody counted
        self.expected: int | None = None
        self.chunk_offsets: list[int] = []
        self.end = f.size
        self.summary_damage: str | None = None
        # Work spent on what turns out to be damage (bytes read plus bytes decompressed, over the file): the search
        # for the next clean chunk (a hostile file can put a plausible Chunk at every 0x06 byte) and the chunks
        # dropped after decompressing them (a file of valid-CRC bombs, each refused only once decompressed). It
        # keeps recover linear in the file's size; chunks that read cleanly are not charged.
        self.budget = RESYNC_BYTES_PER_BYTE * f.size + MAX_CHUNK_BYTES
        try:
            summary = f.summary()
        except DamageError as err:
            summary = None
            if f.size >= len(MAGIC) * 2 and f.read_at(f.size - len(MAGIC), len(MAGIC)) == MAGIC:
                self.summary_damage = str(err)  # closed, but its index is damaged (a cut file has none)
        if summary is not None:
            self.end = summary.start
            if summary.statistics is not None:
                self.expected = summary.statistics.message_count
            self.chunk_offsets = sorted(ci.chunk_start_offset for ci in summary.chunk_indexes)
            for record in (*summary.schemas.values(), *summary.channels.values()):
                copier.add(record)  # the summary repeats every schema and channel: a lost chunk loses none

    def drop(self, start: int, end: int, why: str, *, indexed: bool) -> None:
        self.dropped.append((start, end, why))
        if not indexed:
            self.unindexed_drop = True

    def run(self) -> None:
        pos, dropped_chunk = len(MAGIC), False
        while pos < self.end:
            try:
                opcode, length = self.f.frame_at(pos, self.end)
            except DamageError as err:
                pos = self._broken_frame(pos, err)
                dropped_chunk = False
                continue
            after = pos + 9 + length
            if opcode == Opcode.MESSAGE_INDEX:
                if dropped_chunk:
                    try:
                        record = parse_record(opcode, self.f.read_at(pos + 9, length), f"at byte {pos}")
                        self.lost_indexed += len(record.records)
                    except DamageError:
                        self.unindexed_drop = True
                pos = after
                continue
            dropped_chunk = False
            if opcode in (Opcode.DATA_END, Opcode.FOOTER):
                if self.summary_damage is not None and opcode == Opcode.DATA_END and after < self.f.size:
                    self.drop(after, self.f.size, f"the summary section is damaged ({self.summary_damage}); the "
                                                  f"new file gets a new one", indexed=True)
                return
            try:
                record = parse_record(opcode, self.f.read_at(pos + 9, length), f"at byte {pos}")
            except DamageError as err:
                self.drop(pos, after, str(err), indexed=opcode not in (Opcode.MESSAGE, Opcode.CHUNK))
                dropped_chunk = opcode == Opcode.CHUNK
                pos = after
                continue
            if isinstance(record, Chunk):
                dropped_chunk = not self._chunk(record, pos, after)
            elif isinstance(record, (Schema, Channel, Metadata, Message)):
                self.copier.add(record)
            pos = after

    def _chunk(self, chunk: Chunk, pos: int, after: int) -> bool:
        """Copy a chunk's records; False when it was dropped whole."""
        if self.budget < 0:
            self.drop(pos, after, f"Chunk record at byte {pos} not decompressed: recover has spent its budget for "
                                  f"damage ({RESYNC_BYTES_PER_BYTE} bytes per byte of the file) on the chunks before "
                                  f"it", indexed=True)
            return False
        try:
            data = decompress(chunk, pos)
        except DamageError as err:
            self.budget -= _work(chunk)
            self.drop(pos, after, str(err), indexed=True)
            return False
        try:
            for record in chunk_records(data, pos):
                self.copier.add(record)
        except DamageError as err:  # a CRC-less chunk damaged inside: the records before the damage are kept
            self.drop(pos, after, f"{err} (the records before it were kept)", indexed=False)
        return True

    def _broken_frame(self, pos: int, err: DamageError) -> int:
        """Handle a record that cannot be framed at ``pos``; the offset to go on from."""
        tail_is_chunk = self.end == self.f.size and self.f.read_at(pos, 1) == bytes([Opcode.CHUNK])
        if tail_is_chunk and self._resync(pos + 1) is None:  # a chunk cut by the end of the file
            salvaged = cut_chunk_records(self.f.read_at(pos, self.f.size - pos))
            before = self.copier.messages
            for record in salvaged:
                self.copier.add(record)
            kept = self.copier.messages - before
            self.drop(pos, self.f.size, f"{err}: the file is cut inside this chunk ({kept} messages salvaged "
                                        f"from the cut chunk)", indexed=False)
            return self.f.size
        nxt = self._resync(pos + 1)
        # a cut index or summary record carries no message: nothing is lost with it
        carries = self.f.read_at(pos, 1)[0] in (Opcode.CHUNK, Opcode.MESSAGE) or nxt is not None
        self.drop(pos, self.end if nxt is None else nxt, str(err), indexed=not carries)
        return self.end if nxt is None else nxt

    def _resync(self, start: int) -> int | None:
        """The next offset >= ``start`` where a Chunk record reads cleanly (passes its CRC)."""
        candidates = [o for o in self.chunk_offsets if o >= start]
        if not candidates:
            data = self.f.read_at(start, self.end - start) if self.end > start else b""
            candidates = []
            at = data.find(bytes([Opcode.CHUNK]))
            while at >= 0 and len(candidates) < 10_000:
                candidates.append(start + at)
                at = data.find(bytes([Opcode.CHUNK]), at + 1)
        for offset in candidates:
            try:
                opcode, length = self.f.frame_at(offset, self.end)
                self.budget -= length  # bytes read, then (below) bytes decompressed, for candidates that fail
                if opcode != Opcode.CHUNK or self.budget < 0:
                    continue
                _, record, _ = self.f.record_at(offset, self.end)
                self.budget -= record.uncompressed_size
                if isinstance(record, Chunk) and record.uncompressed_crc != 0 and self.budget >= 0:
                    decompress(record, offset)
                    return offset
            except DamageError:
                continue
        return None


def _work(chunk: Chunk) -> int:
    """Bytes ``decompress`` may have produced before refusing ``chunk``: none when its declared sizes were refused."""
    try:
        check_chunk_size(chunk.compression, len(chunk.data), chunk.uncompressed_size, "")
    except DamageError:
        return 0
    return int(chunk.uncompressed_size)


def recover(src: str | Path, dst: str | Path) -> RecoveryReport:
    """Copy every readable message of ``src`` into a new valid MCAP ``dst``; report what was lost.

    Raises RecorderError when ``src`` is missing or not an MCAP, or ``dst`` exists; DamageError
    (a RecorderError) when ``src`` holds no readable message. Nothing is written then.
    """
    src, dst = Path(src), Path(dst)
    if not src.is_file():
        raise RecorderError(f"{src}: no such file")
    if dst.exists() or partial_path(dst).exists():
        raise RecorderError(f"{dst} already exists; choose another --out")
    if src.stat().st_size == 0:
        raise DamageError(f"{src} is empty (0 bytes): nothing was written to it, so there is nothing to recover")
    with open(src, "rb") as f:
        if f.read(len(MAGIC)) != MAGIC:
            raise RecorderError(f"{src} is not an MCAP file: nothing to recover")
    tmp = partial_path(dst)
    try:
        with McapFile(src) as f, open(tmp, "xb") as out:
            copier = _Copier(out)
            salvage = _Salvage(f, copier)
            salvage.run()
            if copier.messages == 0:
                found = "; ".join(why for _, _, why in salvage.dropped[:3]) or "no Message record in it"
                extra = f"; {copier.notes[0]}" if copier.notes else ""
                raise DamageError(f"{src} holds no readable message ({found}{extra}): nothing to recover, "
                                    f"no file written")
            copier.writer.finish()  # type: ignore[no-untyped-call]  # mcap's Writer.finish is unannotated
            out.flush()
            os.fsync(out.fileno())
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    os.replace(tmp, dst)
    kept = copier.messages
    if salvage.expected is not None:
        lost, exact = max(0, salvage.expected - kept), True
    else:
        lost, exact = salvage.lost_indexed + copier.rejected, not salvage.unindexed_drop
    dropped = tuple(salvage.dropped)
    stopped = None
    if dropped:
        stopped = dropped[0][2]
        if len(dropped) > 1:
            stopped += f" (and {len(dropped) - 1} more damaged ranges)"
    elif copier.notes:
        stopped = copier.notes[0]
    return RecoveryReport(kept, len(copier.channel_ids), stopped, lost, exact, salvage.expected, dropped,
                          tuple(copier.notes))


def describe(report: RecoveryReport, out: str | Path) -> str:
    """The report as the few lines ``slamreplay recover`` prints."""
    if report.lost_exact:
        lost = f"{report.lost} messages lost"
    elif report.lost:
        lost = f"at least {report.lost} messages lost (more in bytes no index counts)"
    else:
        lost = "an unknown number of messages lost in the dropped bytes (no index counts them)"
    of = f" of the {report.expected} the file's statistics count" if report.expected is not None else ""
    lines = [f"recovered {report.messages} messages{of} on {report.channels} channels into {out}; {lost}"]
    for start, end, why in report.dropped:
        lines.append(f"  dropped bytes {start}..{end} ({end - start:,} bytes): {why}")
    for note in report.notes:
        lines.append(f"  dropped {note}")
    if not report.dropped and not report.notes:
        lines.append("  no damage found")
    return "\n".join(lines)


__all__ = ["RecoveryReport", "describe", "record_name", "recover"]
