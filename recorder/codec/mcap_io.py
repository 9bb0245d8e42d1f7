"""Bounds-checked MCAP reading: damaged files give a :class:`DamageError` naming the record and its byte offset.

The ``mcap`` library trusts the lengths it reads: a record length, a string length or a
chunk's ``uncompressed_size`` flipped by one bit becomes an allocation of gigabytes
(``MemoryError``), a seek before the start of the file (``OSError``) or a ``KeyError`` on a
channel id. Here every length is checked against the bytes that are really there before
anything is read or allocated: record framing here, every field inside a record by the
bounds-checked parser of :mod:`slamreplay.recorder.codec.mcap_records`. A chunk's declared
uncompressed size is checked against MAX_CHUNK_BYTES and what its compression can give
(MAX_RATIO) before it is decompressed; it is decompressed as a stream, never into a buffer
sized by the file, stopped at the declared size, and checked against its CRC; and it may hold at
most MAX_RECORDS_PER_BYTE records per byte of it, which bounds a whole file's records by its size.
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
from mcap.opcode import Opcode
from mcap.records import Channel, Chunk, ChunkIndex, Footer, Header, Message, MetadataIndex, Schema, Statistics

from slamreplay.recorder.codec.mcap_records import MESSAGE_FIXED, Body, parse_record, record_name
from slamreplay.recorder.errors import DamageError

MAGIC = b"\x89MCAP0\r\n"
FOOTER_RECORD = 1 + 8 + 20  # opcode, length, summary_start, summary_offset_start, summary_crc
_MESSAGE_HEAD = struct.Struct("<HIQQ")
_LENGTH = struct.Struct("<Q")
_PIECE = 1 << 20  # decompression output is taken in pieces of this size, never sized by the file
# The most a chunk may hold uncompressed: its records are held in memory at once (twice, for a moment, while
# they are handed over), so this is the reader's memory bound per chunk. Writers use far smaller chunks
# (slamreplay 1 MiB, rosbag2 768 KiB by default); a chunk outgrows that only to hold one large message, and
# the largest slamreplay decodes is a raw rgb8 frame of MAX_IMAGE_PIXELS (96 MiB).
MAX_CHUNK_BYTES = 128 << 20
# The most records one chunk may hold: each message becomes a Python tuple and bytes (~200 B) before it is
# sorted, and the loop over them is Python. A 1 MiB chunk of the smallest messages holds ~30,000; a 128 MiB
# chunk of 31-byte empty messages (a bomb of repeated records compresses to nothing) would hold 4.3 million.
MAX_CHUNK_RECORDS = 1_000_000
# The most output one byte of compressed data can give: zstd's densest block is a 4-byte RLE block for up to
# 128 KiB (ratio 32,768), lz4's a match length extended by 255 per byte (ratio ~255). A chunk claiming more
# than its compressed size times this is refused before it is decompressed.
MAX_RATIO = {"zstd": 1 << 15, "lz4": 255, "": 1}
_RATIO_SLACK = 1 << 10  # frame headers: a tiny compressed chunk may decompress to a little more than ratio x size
# The most records a chunk may hold per byte of its record (compressed data plus CHUNK_HEAD), which bounds the
# records of a whole file at twice its size, however many chunks it has. The cost of reading is per record (a
# tuple, a decode, a pipeline step: about 13 us each in `run`), and a chunk of identical records compresses to
# almost nothing (a 9 KB chunk of 1,000,000 messages took `run` 13 s and 780 MB), while records that differ
# only in their times do not: the densest recordings measured hold 0.26 records per byte (zstd, empty messages
# at 1 ms; slamreplay's stationary odometry 0.09) and 0.98 for a contrived burst of empty messages that share
# one timestamp. Bytes need no such bound per file: they cost little per byte (zstd and the CRC run at GB/s),
# and a recording of black frames really holds 15,000 times its size (4K frames, slamreplay's own chunks).
MAX_RECORDS_PER_BYTE = 2
CHUNK_HEAD = 1 + 8 + 8 + 8 + 8 + 4 + 4 + 4 + 8  # opcode, length, times, size, CRC, "zstd", data length
_MIN_RECORD = 9  # opcode and length: a record of fewer bytes does not exist


def check_chunk_size(compression: str, compressed: int, uncompressed: int, where: str) -> None:
    """DamageError when a chunk's ``uncompressed`` size is above MAX_CHUNK_BYTES or more than its
    compression could give from ``compressed`` bytes; checked before anything is decompressed."""
    if uncompressed > MAX_CHUNK_BYTES:
        raise DamageError(f"{where} claims {uncompressed:,} bytes uncompressed, above slamreplay's limit of "
                          f"{MAX_CHUNK_BYTES:,} bytes per chunk: the chunk is damaged or not from a recorder")
    ratio = MAX_RATIO.get(compression)
    if ratio is not None and uncompressed > compressed * ratio + (_RATIO_SLACK if ratio > 1 else 0):
        raise DamageError(f"{where} claims {uncompressed:,} bytes uncompressed from {compressed:,} compressed "
                          f"bytes, more than {compression or 'no compression'} can give (at most {ratio:,} to 1): "
                          f"its sizes are damaged")


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
    check_chunk_size(chunk.compression, len(chunk.data), chunk.uncompressed_size, where)
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
    limit = max_records(len(chunk.data))
    if len(data) > _MIN_RECORD * limit and _count_records(data, limit) > limit:  # else too few bytes to hold more
        raise DamageError(f"{where} holds more than {limit:,} records in {len(chunk.data):,} compressed bytes, "
                          f"above slamreplay's limit of {MAX_RECORDS_PER_BYTE} per byte of chunk (real "
                          f"recordings hold under 1): a decompression bomb, not a recording")
    return data


def max_records(compressed: int) -> int:
    """The most records a chunk of ``compressed`` data bytes may hold (MAX_RECORDS_PER_BYTE, MAX_CHUNK_RECORDS)."""
    return min(MAX_CHUNK_RECORDS, MAX_RECORDS_PER_BYTE * (compressed + CHUNK_HEAD))


def _count_records(data: bytes, limit: int) -> int:
    """Records in a chunk's uncompressed ``data``, counted up to ``limit + 1`` (framing only: damage inside is
    for the parsers to name)."""
    pos, n, size, unpack_len = 0, 0, len(data), _LENGTH.unpack_from
    while pos + _MIN_RECORD <= size and n <= limit:
        pos += _MIN_RECORD + unpack_len(data, pos + 1)[0]
        n += 1
    return n


def zstd_bounded(data: bytes, limit: int, where: str) -> bytes:
    """zstd frames decompressed as a stream, never past ``limit`` bytes; DamageError naming ``where`` otherwise."""
    return _zstd(data, limit, where)


def _zstd(data: bytes, limit: int, where: str) -> bytes:
    out = bytearray()
    try:
        declared = zstandard.frame_content_size(data)  # -1: the frame does not say
        if declared > limit:
            raise DamageError(f"{where} holds a zstd frame of {declared:,} bytes, more than the {limit:,} it "
                              f"records")
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


def _too_many(offset: int) -> DamageError:
    return DamageError(f"Chunk record at byte {offset} holds more than {MAX_CHUNK_RECORDS:,} records, above "
                       f"slamreplay's limit per chunk: the chunk is damaged or not from a recorder")


def chunk_records(data: bytes, offset: int) -> Iterator[Schema | Channel | Message]:
    """The Schema, Channel and Message records in a chunk's uncompressed ``data``, in order."""
    pos, n = 0, 0
    while pos < len(data):
        n += 1
        if n > MAX_CHUNK_RECORDS:
            raise _too_many(offset)
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
    pos, size, k, n = 0, len(data), 0, 0
    while pos < size:
        n += 1
        if n > MAX_CHUNK_RECORDS:
            raise _too_many(offset)
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


def cut_chunk_records(tail: bytes) -> list[Any]:
    """Complete schema/channel/message records of a chunk record cut short by the end of the file
    (``tail`` starts at its opcode); the zstd stream is decompressed as far as it goes, never past the
    size the chunk claims nor MAX_CHUNK_BYTES, and no more records are kept than :func:`max_records` allows."""
    if not tail or tail[0] != Opcode.CHUNK:
        return []
    head = Body(tail, "the cut Chunk record", 9)
    try:
        head.u64("message start time")
        head.u64("message end time")
        uncompressed_size = head.u64("uncompressed size")
        head.u32("uncompressed CRC")
        compression = head.string("compression")
        head.u64("records length")  # runs past the end of the file: that is why the chunk is cut
    except DamageError:
        return []
    if uncompressed_size > MAX_CHUNK_BYTES:
        return []  # a size no chunk of a recorder has: the header itself is damaged
    data = tail[head.pos:]
    if compression == "zstd":
        out = bytearray()
        try:
            reader = zstandard.ZstdDecompressor().stream_reader(io.BytesIO(data))
            while len(out) <= uncompressed_size:
                piece = reader.read(1 << 20)
                if not piece:
                    break
                out += piece
        except zstandard.ZstdError:
            pass  # the stream ends in the middle of a block: keep the blocks before it
        data = bytes(out[:uncompressed_size])
    elif compression != "":
        return []  # lz4 chunks are kept whole or not at all
    records: list[Any] = []
    pos, limit = 0, max_records(len(tail) - head.pos)
    while pos + 9 <= len(data) and len(records) < limit:
        opcode = data[pos]
        (length,) = struct.unpack_from("<Q", data, pos + 1)
        if length > len(data) - pos - 9:
            break
        if opcode in (Opcode.SCHEMA, Opcode.CHANNEL, Opcode.MESSAGE):
            try:
                records.append(parse_record(opcode, data[pos + 9:pos + 9 + length], "in the cut chunk"))
            except DamageError:
                break
        pos += 9 + length
    return records
