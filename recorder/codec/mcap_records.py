"""MCAP record bodies parsed by a bounds-checked reader of our own, into the ``mcap`` library's record classes.

The library's ``Record.read(stream)`` trusts every length inside a record: a string, map or data
length of 2**64 - 16 becomes ``stream.read(2**64 - 16)`` (``OverflowError``), one of 2**40 an
attempt to allocate a terabyte, and a map or index whose byte length is not a whole number of
entries reads on past its end. Here every field is read through :class:`Body`, which checks
each length against the bytes of the record really left before it reads, and raises a
one-line :class:`DamageError` naming the record, the field, its byte offset in the record and
what is wrong. Only the layout (the MCAP specification's field order) is repeated here; the
records built are the library's, so the rest of the code and the writer see the same types.
"""

from __future__ import annotations

import struct
from typing import Any

from mcap.opcode import Opcode
from mcap.records import (
    Channel,
    Chunk,
    ChunkIndex,
    Footer,
    Header,
    Message,
    MessageIndex,
    Metadata,
    MetadataIndex,
    Schema,
    Statistics,
)

from slamreplay.recorder.errors import DamageError

MESSAGE_FIXED = 2 + 4 + 8 + 8  # channel_id, sequence, log_time, publish_time
_U16, _U32, _U64 = struct.Struct("<H"), struct.Struct("<I"), struct.Struct("<Q")


def record_name(opcode: int) -> str:
    """``Chunk``, ``MessageIndex``..., or ``unknown (opcode 0x42)``."""
    try:
        return "".join(part.title() for part in Opcode(opcode).name.split("_"))
    except ValueError:
        return f"unknown (opcode 0x{opcode:02x})"


class Body:
    """A cursor over one record body (or a part of it) that never reads past its end.

    Parameters
    ----------
    data : the record body, exactly its bytes.
    what : the record named for errors, e.g. ``Chunk record at byte 1022``.
    start, end : the part of ``data`` this cursor reads (a map or index inside the record).
    """

    def __init__(self, data: bytes, what: str, start: int = 0, end: int | None = None) -> None:
        self.data, self.what = data, what
        self.pos, self.end = start, len(data) if end is None else end

    @property
    def left(self) -> int:
        """Bytes not read yet."""
        return self.end - self.pos

    def fail(self, why: str) -> DamageError:
        """The error for damage found at the cursor."""
        return DamageError(f"{self.what} is damaged: {why}")

    def _need(self, n: int, field: str) -> None:
        if n > self.left:
            raise self.fail(f"its {field} at byte {self.pos} of the record needs {n:,} bytes but only "
                            f"{max(0, self.left):,} are left")

    def u16(self, field: str) -> int:
        """A little-endian uint16."""
        self._need(2, field)
        (v,) = _U16.unpack_from(self.data, self.pos)
        self.pos += 2
        return int(v)

    def u32(self, field: str) -> int:
        """A little-endian uint32."""
        self._need(4, field)
        (v,) = _U32.unpack_from(self.data, self.pos)
        self.pos += 4
        return int(v)

    def u64(self, field: str) -> int:
        """A little-endian uint64."""
        self._need(8, field)
        (v,) = _U64.unpack_from(self.data, self.pos)
        self.pos += 8
        return int(v)

    def length(self, width: int, field: str) -> int:
        """A length prefix, checked against the bytes left after it before anyone uses it."""
        at = self.pos
        n = self.u32(f"{field} length") if width == 4 else self.u64(f"{field} length")
        if n > self.left:
            raise self.fail(f"its {field} length at byte {at} of the record claims {n:,} bytes but only "
                            f"{self.left:,} follow it")
        return n

    def take(self, n: int, field: str) -> bytes:
        """The next ``n`` bytes (``n`` already checked, or checked here)."""
        self._need(n, field)
        out = self.data[self.pos:self.pos + n]
        self.pos += n
        return bytes(out)

    def string(self, field: str) -> str:
        """A uint32-length-prefixed UTF-8 string."""
        at = self.pos
        raw = self.take(self.length(4, field), field)
        try:
            return raw.decode("utf-8")
        except UnicodeDecodeError as err:
            raise self.fail(f"its {field} at byte {at} of the record is not UTF-8 ({err.reason} at byte "
                            f"{err.start} of it)") from err

    def section(self, field: str, entry: int | None = None) -> Body:
        """A uint32-byte-length-prefixed part (a map, an index), as a cursor bounded to it; with
        ``entry``, its byte length must be a whole number of ``entry``-byte entries."""
        at = self.pos
        n = self.length(4, field)
        if entry is not None and n % entry:
            raise self.fail(f"its {field} at byte {at} of the record holds {n:,} bytes, not a whole number of "
                            f"{entry}-byte entries")
        part = Body(self.data, self.what, self.pos, self.pos + n)
        self.pos += n
        return part

    def string_map(self, field: str) -> dict[str, str]:
        """A map<string, string>: each key and value must lie inside the map's own byte length."""
        part = self.section(field)
        out: dict[str, str] = {}
        while part.left > 0:
            key = part.string(f"{field} key")
            out[key] = part.string(f"{field} value")
        return out


def _channel(b: Body) -> Channel:
    cid, schema_id = b.u16("id"), b.u16("schema id")
    topic, encoding = b.string("topic"), b.string("message encoding")
    return Channel(id=cid, topic=topic, message_encoding=encoding, metadata=b.string_map("metadata"),
                   schema_id=schema_id)


def _schema(b: Body) -> Schema:
    sid, name, encoding = b.u16("id"), b.string("name"), b.string("encoding")
    return Schema(id=sid, name=name, encoding=encoding, data=b.take(b.length(4, "data"), "data"))


def _chunk(b: Body) -> Chunk:
    start, end, size, crc = b.u64("message start time"), b.u64("message end time"), b.u64(
        "uncompressed size"), b.u32("uncompressed CRC")
    compression = b.string("compression")
    data = b.take(b.length(8, "records"), "records")
    return Chunk(compression=compression, data=data, message_end_time=end, message_start_time=start,
                 uncompressed_crc=crc, uncompressed_size=size)


def _message_index(b: Body) -> MessageIndex:
    cid = b.u16("channel id")
    part = b.section("records", entry=16)
    entries = [(part.u64("log time"), part.u64("offset")) for _ in range(part.left // 16)]
    return MessageIndex(cid, entries)


def _chunk_index(b: Body) -> ChunkIndex:
    start, end, offset, length = (b.u64("message start time"), b.u64("message end time"),
                                  b.u64("chunk start offset"), b.u64("chunk length"))
    part = b.section("message index offsets", entry=10)
    offsets = {part.u16("channel id"): part.u64("offset") for _ in range(part.left // 10)}
    index_length, compression = b.u64("message index length"), b.string("compression")
    return ChunkIndex(chunk_start_offset=offset, chunk_length=length, message_index_offsets=offsets,
                      message_index_length=index_length, compression=compression,
                      compressed_size=b.u64("compressed size"), uncompressed_size=b.u64("uncompressed size"),
                      message_start_time=start, message_end_time=end)


def _statistics(b: Body) -> Statistics:
    message_count, schema_count, channel_count = b.u64("message count"), b.u16("schema count"), b.u32(
        "channel count")
    attachment_count, metadata_count, chunk_count = b.u32("attachment count"), b.u32("metadata count"), b.u32(
        "chunk count")
    start, end = b.u64("message start time"), b.u64("message end time")
    part = b.section("channel message counts", entry=10)
    counts = {part.u16("channel id"): part.u64("count") for _ in range(part.left // 10)}
    return Statistics(attachment_count=attachment_count, channel_count=channel_count, channel_message_counts=counts,
                      chunk_count=chunk_count, message_count=message_count, message_end_time=end,
                      message_start_time=start, metadata_count=metadata_count, schema_count=schema_count)


_PARSERS: dict[int, Any] = {
    Opcode.HEADER: lambda b: Header(b.string("profile"), b.string("library")),
    Opcode.FOOTER: lambda b: Footer(summary_start=b.u64("summary start"),
                                    summary_offset_start=b.u64("summary offset start"), summary_crc=b.u32("CRC")),
    Opcode.SCHEMA: _schema,
    Opcode.CHANNEL: _channel,
    Opcode.CHUNK: _chunk,
    Opcode.MESSAGE_INDEX: _message_index,
    Opcode.CHUNK_INDEX: _chunk_index,
    Opcode.STATISTICS: _statistics,
    Opcode.METADATA: lambda b: Metadata(name=b.string("name"), metadata=b.string_map("metadata")),
    Opcode.METADATA_INDEX: lambda b: MetadataIndex(offset=b.u64("offset"), length=b.u64("length"),
                                                   name=b.string("name")),
}


def parse_record(opcode: int, body: bytes, where: str) -> Any:
    """The record of ``opcode`` in ``body`` (exactly its bytes); None for an opcode read as opaque.

    Bytes after the last known field are ignored, as the MCAP specification asks (later
    versions may append fields). Raises DamageError naming the record, ``where`` (e.g.
    ``at byte 1022``), the field and its offset when a field runs past the body or a string is
    not UTF-8.
    """
    what = f"{record_name(opcode)} record {where}"
    if opcode == Opcode.MESSAGE:
        if len(body) < MESSAGE_FIXED:
            raise DamageError(f"{what} is damaged: it holds {len(body)} bytes, fewer than the {MESSAGE_FIXED} of "
                              f"a Message's fixed fields")
        b = Body(body, what)
        cid, seq, log_time, publish_time = b.u16("channel id"), b.u32("sequence"), b.u64("log time"), b.u64(
            "publish time")
        return Message(channel_id=cid, sequence=seq, log_time=log_time, publish_time=publish_time,
                       data=bytes(body[MESSAGE_FIXED:]))
    parser = _PARSERS.get(opcode)
    return None if parser is None else parser(Body(body, what))
