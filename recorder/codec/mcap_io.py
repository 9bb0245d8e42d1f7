"""Bounds-checked MCAP reading: damaged files give a :class:`DamageError` naming the record and its byte offset.

The ``mcap`` library trusts the lengths it reads: a record length, a string length or a
chunk's ``uncompressed_size`` flipped by one bit becomes an allocation of gigabytes
(``MemoryError``), a seek before the start of the file (``OSError``) or a ``KeyError`` on a
channel id. Here every length is checked against the bytes that are really there before
anything is read or allocated; record bodies are parsed with the library's record classes
from an exact, bounded buffer; chunks are decompressed as a stream, never into a buffer
sized by the file, and checked against their CRC.
"""

from __future__ import annotations

import io
import os
import struct
import zlib
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

import lz4.frame  # type: ignore[import-untyped]  # no stubs, no py.typed
import zstandard
from mcap.data_stream import ReadDataStream
from mcap.exceptions import EndOfFile, McapError
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

MAGIC = b"\x89MCAP0\r\n"
FOOTER_RECORD = 1 + 8 + 20  # opcode, length, summary_start, summary_offset_start, summary_crc
MESSAGE_FIXED = 2 + 4 + 8 + 8  # channel_id, sequence, log_time, publish_time
_MESSAGE_HEAD = struct.Struct("<HIQQ")
_LENGTH = struct.Struct("<Q")
_PIECE = 1 << 20  # decompression output is taken in pieces of this size, never sized by the file
_CLASSES: dict[int, Any] = {
    Opcode.HEADER: Header, Opcode.FOOTER: Footer, Opcode.SCHEMA: Schema, Opcode.CHANNEL: Channel,
    Opcode.MESSAGE: Message, Opcode.CHUNK: Chunk, Opcode.MESSAGE_INDEX: MessageIndex,
    Opcode.CHUNK_INDEX: ChunkIndex, Opcode.STATISTICS: Statistics, Opcode.METADATA: Metadata,
    Opcode.METADATA_INDEX: MetadataIndex,
}


def record_name(opcode: int) -> str:
    """``Chunk``, ``MessageIndex``..., or ``unknown (opcode 0x42)``."""
    try:
        return "".join(part.title() for part in Opcode(opcode).name.split("_"))
    except ValueError:
        return f"unknown (opcode 0x{opcode:02x})"


class _Exact(ReadDataStream):
    """A ReadDataStream that refuses to hand back fewer bytes than asked for."""

    def read(self, length: int) -> bytes:
        if length < 0:
            raise EndOfFile()
        data = super().read(length)
        if len(data) != length:
            raise EndOfFile()
        return data


def parse_record(opcode: int, body: bytes, where: str) -> Any:
    """The record of ``opcode`` in ``body`` (exactly its bytes); None for an opcode read as opaque.

    Raises DamageError naming the record and ``where`` when a field runs past the body or
    holds bytes that are not what the field is (a string that is not UTF-8...).
    """
    cls = _CLASSES.get(opcode)
    if cls is None:
        return None
    stream = _Exact(io.BytesIO(body))
    try:
        if cls is Message:
            if len(body) < MESSAGE_FIXED:
                raise EndOfFile()
            return Message.read(stream, len(body))
        return cls.read(stream)
    except (EndOfFile, struct.error) as err:
        msg = f"{record_name(opcode)} record {where} is damaged: a field runs past its {len(body)} bytes"
        raise DamageError(msg) from err
    except (UnicodeDecodeError, ValueError, McapError) as err:
        msg = f"{record_name(opcode)} record {where} is damaged: {err}"
        raise DamageError(msg) from err


@dataclass
class Summary:
    """What the summary section holds (the records the reader uses)."""

    schemas: dict[int, Schema] = field(default_factory=dict)
    channels: dict[int, Channel] = field(default_factory=dict)
    chunk_indexes: list[ChunkIndex] = field(default_factory=list)
    metadata_indexes: list[MetadataIndex] = field(default_factory=list)
    statistics: Statistics | None = None
    start: int = 0  # byte offset of the summary section


class McapFile:
    """An open MCAP file whose records are read with every length checked against the file."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self._f: IO[bytes] = open(self.path, "rb")  # noqa: SIM115 -- closed in close()
        self.size = os.fstat(self._f.fileno()).st_size

    def close(self) -> None:
        self._f.close()

    def __enter__(self) -> McapFile:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def read_at(self, offset: int, length: int) -> bytes:
        """``length`` bytes at ``offset``; DamageError when the file has fewer."""
        if offset < 0 or length < 0 or offset + length > self.size:
            raise DamageError(f"{length} bytes at byte {offset} are past the end of the {self.size}-byte file")
        self._f.seek(offset)
        data = self._f.read(length)
        if len(data) != length:
            raise DamageError(f"the file ended while reading {length} bytes at byte {offset}")
        return data

    def frame_at(self, offset: int, end: int | None = None) -> tuple[int, int]:
        """(opcode, body length) of the record at ``offset``, its body within [offset + 9, end)."""
        end = self.size if end is None else min(end, self.size)
        if offset + 9 > end:
            raise DamageError(f"a record at byte {offset} is cut short: {max(0, end - offset)} of its 9-byte "
                              f"opcode and length are there")
        head = self.read_at(offset, 9)
        opcode, length = head[0], struct.unpack_from("<Q", head, 1)[0]
        if length > end - offset - 9:
            raise DamageError(f"{record_name(opcode)} record at byte {offset} claims {length:,} bytes but only "
                              f"{end - offset - 9:,} follow it")
        return opcode, length

    def record_at(self, offset: int, end: int | None = None) -> tuple[int, Any, int]:
        """(opcode, parsed record or None, offset after it) of the record at ``offset``."""
        opcode, length = self.frame_at(offset, end)
        body = self.read_at(offset + 9, length)
        return opcode, parse_record(opcode, body, f"at byte {offset}"), offset + 9 + length

    def header(self) -> Header:
        """The Header record; DamageError when the file does not start with one."""
        if self.size < len(MAGIC) or self.read_at(0, len(MAGIC)) != MAGIC:
            raise DamageError("the file does not start with the MCAP magic")
        opcode, record, _ = self.record_at(len(MAGIC))
        if opcode != Opcode.HEADER:
            raise DamageError(f"the first record (byte 8) is a {record_name(opcode)} record, not the Header")
        assert isinstance(record, Header)
        return record

    def footer(self) -> Footer:
        """The Footer record before the closing magic."""
        at = self.size - len(MAGIC) - FOOTER_RECORD
        if at < len(MAGIC):
            raise DamageError(f"the file is too short ({self.size} bytes) to hold a Footer record")
        opcode, record, _ = self.record_at(at, self.size - len(MAGIC))
        if opcode != Opcode.FOOTER:
            raise DamageError(f"no Footer record before the closing magic (byte {at} holds a "
                              f"{record_name(opcode)} record)")
        assert isinstance(record, Footer)
        return record

    def summary(self) -> Summary | None:
        """The summary section (None when the file has none), every index checked against the file."""
        footer = self.footer()
        if footer.summary_start == 0:
            return None
        end = self.size - len(MAGIC) - FOOTER_RECORD
        if not len(MAGIC) < footer.summary_start <= end:
            raise DamageError(f"the Footer puts the summary section at byte {footer.summary_start}, outside the "
                              f"file's data ({len(MAGIC)}..{end})")
        s = Summary(start=footer.summary_start)
        pos = footer.summary_start
        while pos < end:
            _, record, pos = self.record_at(pos, end)
            if isinstance(record, Schema):
                s.schemas[record.id] = record
            elif isinstance(record, Channel):
                s.channels[record.id] = record
            elif isinstance(record, ChunkIndex):
                if not (len(MAGIC) <= record.chunk_start_offset
                        and record.chunk_start_offset + record.chunk_length <= footer.summary_start):
                    raise DamageError(f"a ChunkIndex record in the summary (before byte {pos}) puts a chunk at bytes "
                                      f"{record.chunk_start_offset}..+{record.chunk_length}, outside the data section")
                s.chunk_indexes.append(record)
            elif isinstance(record, MetadataIndex):
                s.metadata_indexes.append(record)
            elif isinstance(record, Statistics):
                s.statistics = record
        return s

    def records(self, start: int = len(MAGIC), end: int | None = None) -> Iterator[tuple[int, int, Any]]:
        """(offset, opcode, record) of the top-level records from ``start`` up to the Footer or ``end``."""
        pos, end = start, self.size if end is None else end
        while pos < end:
            opcode, record, after = self.record_at(pos, end)
            yield pos, opcode, record
            if opcode == Opcode.FOOTER:
                return
            pos = after

    def chunk(self, index: ChunkIndex) -> tuple[Chunk, int]:
        """The Chunk record an index points at, and its offset."""
        opcode, record, _ = self.record_at(index.chunk_start_offset, index.chunk_start_offset + index.chunk_length)
        if opcode != Opcode.CHUNK:
            raise DamageError(f"the index points at a Chunk record at byte {index.chunk_start_offset}, but a "
                              f"{record_name(opcode)} record is there")
        return record, index.chunk_start_offset


def decompress(chunk: Chunk, offset: int, *, validate_crc: bool = True) -> bytes:
    """The records of a chunk, uncompressed; DamageError when they do not decompress to
    ``uncompressed_size`` bytes or fail the chunk's CRC. Output grows as it is produced."""
    where = f"Chunk record at byte {offset}"
    if chunk.compression == "":
        data = bytes(chunk.data)
    elif chunk.compression == "zstd":
        data = _zstd(chunk.data, chunk.uncompressed_size, where)
    elif chunk.compression == "lz4":
        data = _lz4(chunk.data, chunk.uncompressed_size, where)
    else:
        raise DamageError(f"{where} uses compression {chunk.compression[:40]!r}, which is not zstd, lz4 or none")
    if len(data) != chunk.uncompressed_size:
        raise DamageError(f"{where} decompresses to {len(data):,} bytes, not the {chunk.uncompressed_size:,} "
                          f"it records")
    if validate_crc and chunk.uncompressed_crc != 0:
        crc = zlib.crc32(data)
        if crc != chunk.uncompressed_crc:
            raise DamageError(f"{where} fails its CRC check (expected {chunk.uncompressed_crc:#010x}, "
                              f"got {crc:#010x})")
    return data


def _zstd(data: bytes, limit: int, where: str) -> bytes:
    out = bytearray()
    try:
        reader = zstandard.ZstdDecompressor().stream_reader(io.BytesIO(data), read_across_frames=True)
        while len(out) <= limit:
            piece = reader.read(_PIECE)
            if not piece:
                break
            out += piece
    except zstandard.ZstdError as err:
        raise DamageError(f"{where} does not decompress (zstd: {err})") from err
    if len(out) > limit:
        raise DamageError(f"{where} decompresses to more than the {limit:,} bytes it records")
    return bytes(out)


def _lz4(data: bytes, limit: int, where: str) -> bytes:
    out = bytearray()
    try:
        d = lz4.frame.LZ4FrameDecompressor()
        piece = d.decompress(data, max_length=_PIECE)
        out += piece
        while not d.eof and len(out) <= limit and d.needs_input is False:
            piece = d.decompress(b"", max_length=_PIECE)
            if not piece:
                break
            out += piece
    except RuntimeError as err:  # the lz4 binding reports bad frames as RuntimeError
        raise DamageError(f"{where} does not decompress (lz4: {err})") from err
    if len(out) > limit:
        raise DamageError(f"{where} decompresses to more than the {limit:,} bytes it records")
    return bytes(out)


def chunk_records(data: bytes, offset: int) -> Iterator[Schema | Channel | Message]:
    """The Schema, Channel and Message records in a chunk's uncompressed ``data``, in order."""
    pos = 0
    while pos < len(data):
        if pos + 9 > len(data):
            raise DamageError(f"Chunk record at byte {offset}: a record at byte {pos} of its content is cut short")
        opcode, length = data[pos], struct.unpack_from("<Q", data, pos + 1)[0]
        if length > len(data) - pos - 9:
            raise DamageError(f"Chunk record at byte {offset}: the {record_name(opcode)} record at byte {pos} of its "
                              f"content claims {length:,} bytes but only {len(data) - pos - 9:,} follow it")
        if opcode == Opcode.MESSAGE and length >= MESSAGE_FIXED:  # the hot path: fixed fields, then the payload
            channel_id, sequence, log_time, publish_time = _MESSAGE_HEAD.unpack_from(data, pos + 9)
            yield Message(channel_id=channel_id, sequence=sequence, log_time=log_time, publish_time=publish_time,
                          data=data[pos + 9 + MESSAGE_FIXED:pos + 9 + length])
        elif opcode in (Opcode.SCHEMA, Opcode.CHANNEL, Opcode.MESSAGE):
            yield parse_record(opcode, data[pos + 9:pos + 9 + length], f"at byte {pos} of the chunk at byte {offset}")
        pos += 9 + length


def chunk_messages(data: bytes, offset: int) -> list[tuple[int, int, int, int, bytes]]:
    """(log_time, index in chunk, channel_id, publish_time, payload) of every Message record in a chunk's
    uncompressed ``data``, in chunk order; the same checks as :func:`chunk_records` (its Schema and Channel
    records are parsed, so that damage in them is found, and dropped). Tuples, not records: replay's hot path."""
    out: list[tuple[int, int, int, int, bytes]] = []
    append, unpack_head, unpack_len = out.append, _MESSAGE_HEAD.unpack_from, _LENGTH.unpack_from
    pos, size, k = 0, len(data), 0
    while pos < size:
        if pos + 9 > size:
            raise DamageError(f"Chunk record at byte {offset}: a record at byte {pos} of its content is cut short")
        opcode, (length,) = data[pos], unpack_len(data, pos + 1)
        if length > size - pos - 9:
            raise DamageError(f"Chunk record at byte {offset}: the {record_name(opcode)} record at byte {pos} of its "
                              f"content claims {length:,} bytes but only {size - pos - 9:,} follow it")
        if opcode == Opcode.MESSAGE and length >= MESSAGE_FIXED:
            channel_id, _, log_time, publish_time = unpack_head(data, pos + 9)
            append((log_time, k, channel_id, publish_time, data[pos + 9 + MESSAGE_FIXED:pos + 9 + length]))
        elif opcode in (Opcode.SCHEMA, Opcode.CHANNEL, Opcode.MESSAGE):
            parse_record(opcode, data[pos + 9:pos + 9 + length], f"at byte {pos} of the chunk at byte {offset}")
        if opcode in (Opcode.SCHEMA, Opcode.CHANNEL, Opcode.MESSAGE):
            k += 1
        pos += 9 + length
    return out
