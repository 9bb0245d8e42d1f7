"""A whole MCAP file checked by slamreplay's bounded reader before another library reads it.

``rosbags`` reads a ROS 2 bag's MCAP storage trusting what the file says: it seeks by record
lengths (``skip_exact``: ``OverflowError`` past 2**63), reads chunks at the offsets and sizes of
the summary's ChunkIndex records (``read(2**40)``: ``MemoryError``), and decompresses whatever
bytes are there. :func:`check_mcap` walks every record once with the reader of
:mod:`slamreplay.recorder.codec.mcap_io`, which checks each length against the file and each
chunk's sizes before it decompresses (bounded, never sized by the file) and checks its CRC, and
compares every index with the record it points at; a file it passes is one whose every offset
and length rosbags follows lands on the bytes checked.
"""

from __future__ import annotations

import zlib
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from mcap.opcode import Opcode
from mcap.records import Chunk, ChunkIndex, Message, MessageIndex, Metadata

from slamreplay.recorder.codec.mcap_io import FOOTER_RECORD, MAGIC, McapFile, chunk_records, decompress
from slamreplay.recorder.errors import DamageError

_PIECE = 1 << 20  # CRCs of sections are computed over pieces of this size, never over the section at once


@dataclass(frozen=True, slots=True)
class McapCheck:
    """What :func:`check_mcap` read: top-level records, chunks, messages and the file's size."""

    records: int
    chunks: int
    messages: int
    size_bytes: int


def check_mcap(path: str | Path, each_message: Callable[[bytes, str], None] | None = None) -> McapCheck:
    """Check the structure of the MCAP file at ``path``; DamageError names the first damage and its byte offset.

    Checked: the magic at both ends, the Header first and the Footer last; every top-level record's
    opcode and length within the file and its fields within its length; each chunk's sizes, its
    decompression and CRC (:func:`~slamreplay.recorder.codec.mcap_io.decompress`) and every record
    inside it; the data section's and the summary's CRCs where the file holds them; that the
    Footer's summary offsets start records; and that each ChunkIndex, message index offset and
    MetadataIndex points at a record of its kind whose offsets, lengths, sizes, compression and
    times it repeats. One chunk is held at a time, and the summary's indexes. ``each_message(data, where)``,
    when given, is called with every message's payload (a check of its own, raising DamageError).
    """
    with McapFile(path) as f:
        f.header()
        if f.size < 2 * len(MAGIC) or f.read_at(f.size - len(MAGIC), len(MAGIC)) != MAGIC:
            raise DamageError("the file does not end with the MCAP magic: it is cut short or damaged")
        footer = f.footer()
        summary = f.summary()  # every summary record framed and parsed, each ChunkIndex inside the data section
        footer_at = f.size - len(MAGIC) - FOOTER_RECORD
        chunk_indexes = {i.chunk_start_offset: i for i in summary.chunk_indexes} if summary else {}
        message_indexes = {offset: (cid, index) for index in chunk_indexes.values()
                           for cid, offset in index.message_index_offsets.items()}
        metadata_indexes = {i.offset: i for i in summary.metadata_indexes} if summary else {}
        starts = {footer.summary_start, footer.summary_offset_start} - {0}
        pos, records, chunks, messages = len(MAGIC), 0, 0, 0
        while True:
            if pos >= footer_at + FOOTER_RECORD:
                raise DamageError(f"the records end at byte {pos} without the Footer record")
            opcode, record, after = f.record_at(pos, footer_at + FOOTER_RECORD)
            records += 1
            starts.discard(pos)
            if isinstance(record, Chunk):
                for inner in chunk_records(decompress(record, pos), pos):
                    if isinstance(inner, Message):
                        messages += 1
                        if each_message is not None:
                            each_message(inner.data, f"at log time {inner.log_time} in the chunk at byte {pos}")
                chunks += 1
                if pos in chunk_indexes:
                    _same_chunk(chunk_indexes.pop(pos), record, after - pos, pos)
            elif isinstance(record, Message):
                messages += 1
                if each_message is not None:
                    each_message(record.data, f"at byte {pos}")
            elif isinstance(record, MessageIndex) and pos in message_indexes:
                cid, index = message_indexes.pop(pos)
                end = index.chunk_start_offset + index.chunk_length
                if not end <= pos < after <= end + index.message_index_length:
                    raise DamageError(f"a ChunkIndex puts channel {cid}'s MessageIndex at byte {pos}, outside the "
                                      f"message indexes of its chunk (bytes {end}..+{index.message_index_length})")
                if record.channel_id != cid:
                    raise DamageError(f"a ChunkIndex puts channel {cid}'s MessageIndex at byte {pos}, where channel "
                                      f"{record.channel_id}'s is")
            elif isinstance(record, Metadata) and pos in metadata_indexes:
                meta = metadata_indexes.pop(pos)
                if (meta.length, meta.name) != (after - pos, record.name):
                    raise DamageError(f"a MetadataIndex says the Metadata record at byte {pos} is {meta.length} "
                                      f"bytes named {meta.name[:40]!r}; it is {after - pos} bytes named "
                                      f"{record.name[:40]!r}")
            elif opcode == Opcode.DATA_END:
                _check_crc(f, 0, pos, f.read_at(pos + 9, 4) if after - pos >= 13 else b"", "the data section")
            elif opcode == Opcode.FOOTER:
                break
            pos = after
        if pos != footer_at:
            raise DamageError(f"a Footer record at byte {pos}, before the end of the records at byte {footer_at}")
        if footer.summary_start:
            _check_crc(f, footer.summary_start, footer_at + 1 + 8 + 16, footer.summary_crc.to_bytes(4, "little"),
                       "the summary section")
    _left(starts, "the Footer puts the summary section (or its offsets) at byte", "where no record starts")
    _left(chunk_indexes, "a ChunkIndex points at byte", "where no Chunk record starts")
    _left(message_indexes, "a ChunkIndex puts a MessageIndex at byte", "where no MessageIndex record starts")
    _left(metadata_indexes, "a MetadataIndex points at byte", "where no Metadata record starts")
    return McapCheck(records, chunks, messages, f.size)


def _same_chunk(index: ChunkIndex, chunk: Chunk, length: int, at: int) -> None:
    """DamageError when the ChunkIndex of the chunk at ``at`` says other than the chunk itself."""
    said = {"length": index.chunk_length, "compression": index.compression, "compressed size": index.compressed_size,
            "uncompressed size": index.uncompressed_size, "message start time": index.message_start_time,
            "message end time": index.message_end_time}
    real = {"length": length, "compression": chunk.compression, "compressed size": len(chunk.data),
            "uncompressed size": chunk.uncompressed_size, "message start time": chunk.message_start_time,
            "message end time": chunk.message_end_time}
    for name, value in said.items():
        if value != real[name]:
            shown = repr(value[:40]) if isinstance(value, str) else f"{value:,}"
            raise DamageError(f"the ChunkIndex of the Chunk record at byte {at} gives its {name} as {shown}, the "
                              f"chunk's is {real[name]!r}: the index is damaged")


def _check_crc(f: McapFile, start: int, end: int, stored: bytes, what: str) -> None:
    """DamageError when the CRC-32 of bytes [start, end) is not ``stored`` (little-endian; 0: none written)."""
    expected = int.from_bytes(stored, "little") if len(stored) == 4 else 0
    if expected == 0:
        return
    crc, pos = 0, start
    while pos < end:
        n = min(_PIECE, end - pos)
        crc = zlib.crc32(f.read_at(pos, n), crc)
        pos += n
    if crc != expected:
        raise DamageError(f"{what} (bytes {start}..{end}) fails its CRC check (expected {expected:#010x}, got "
                          f"{crc:#010x})")


def _left(wanted: dict[int, Any] | set[int], what: str, why: str) -> None:
    if wanted:
        at = min(wanted)
        raise DamageError(f"{what} {at}, {why}" + (f" ({len(wanted) - 1} more)" if len(wanted) > 1 else ""))

