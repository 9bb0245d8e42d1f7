"""Salvage a truncated, ``.partial`` or corrupt MCAP into a valid, indexed one.

The input is read linearly (no index needed) and every message up to the first damaged
record is re-written, with its schema, channel, log and publish times, into a new file
with zstd chunks and CRCs. When the damage is a chunk cut short (a truncated file), the
part of the chunk that is there is decompressed as a stream and its complete messages are
kept too. Metadata records met before the damage are kept.
"""

from __future__ import annotations

import io
import os
import struct
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any

import zstandard
from mcap.data_stream import ReadDataStream
from mcap.opcode import Opcode
from mcap.records import Channel, Message, Metadata, Schema
from mcap.stream_reader import StreamReader
from mcap.writer import CompressionType, Writer

from recorder.errors import RecorderError
from recorder.version import version
from recorder.writer import CHUNK_SIZE, partial_path

MAGIC = b"\x89MCAP0\r\n"
_RECORD_CLASSES: dict[int, type[Any]] = {Opcode.SCHEMA: Schema, Opcode.CHANNEL: Channel, Opcode.MESSAGE: Message}


@dataclass(frozen=True, slots=True)
class RecoveryReport:
    """What was kept: messages, channels, and where and why reading stopped (None: no damage found)."""

    messages: int
    channels: int
    stopped_at: str | None


class _Copier:
    """Re-writes schemas, channels and messages into a new file, registering each once."""

    def __init__(self, out: IO[bytes]) -> None:
        self.writer = Writer(out, chunk_size=CHUNK_SIZE, compression=CompressionType.ZSTD, enable_crcs=True)
        self.writer.start(profile="", library=f"slamreplay/{version()} recover")
        self.schemas: dict[int, Schema] = {}
        self.channels: dict[int, Channel] = {}
        self.schema_ids: dict[int, int] = {}
        self.channel_ids: dict[int, int] = {}
        self.messages = 0

    def add(self, record: Any) -> None:
        if isinstance(record, Schema):
            self.schemas[record.id] = record
        elif isinstance(record, Channel):
            self.channels[record.id] = record
        elif isinstance(record, Metadata):
            self.writer.add_metadata(record.name, record.metadata)
        elif isinstance(record, Message):
            channel_id = self.channel_ids.get(record.channel_id)
            if channel_id is None:
                channel = self.channels[record.channel_id]
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


def _records_of_cut_chunk(tail: bytes) -> list[Any]:
    """Complete schema/channel/message records in a chunk record cut short (``tail`` starts at its opcode)."""
    if len(tail) < 9 or tail[0] != Opcode.CHUNK:
        return []
    (record_length,) = struct.unpack_from("<Q", tail, 1)
    if len(tail) >= 9 + record_length:
        return []  # the chunk is all there, so it is damaged, not cut: its content cannot be trusted
    body = tail[9:]
    if len(body) < 32:
        return []
    (compression_length,) = struct.unpack_from("<I", body, 28)
    compression = body[32:32 + compression_length].decode(errors="replace")
    data = body[32 + compression_length + 8:]
    if compression == "zstd":
        try:
            data = zstandard.ZstdDecompressor().decompressobj().decompress(data)
        except zstandard.ZstdError:
            return []
    elif compression != "":
        return []  # lz4 chunks are kept whole or not at all
    records, pos = [], 0
    while pos + 9 <= len(data):
        opcode = data[pos]
        (length,) = struct.unpack_from("<Q", data, pos + 1)
        if pos + 9 + length > len(data):
            break
        cls = _RECORD_CLASSES.get(opcode)
        if cls is not None:
            records.append(cls.read(ReadDataStream(io.BytesIO(data[pos + 9:pos + 9 + length])), length)
                           if cls is Message else cls.read(ReadDataStream(io.BytesIO(data[pos + 9:pos + 9 + length]))))
        pos += 9 + length
    return records


def recover(src: str | Path, dst: str | Path) -> RecoveryReport:
    """Copy every readable message of ``src`` into a new valid MCAP ``dst``.

    Raises RecorderError when ``src`` is missing or not an MCAP at all, or ``dst`` exists.
    A file with no readable message still gives a valid (empty) ``dst``.
    """
    src, dst = Path(src), Path(dst)
    if not src.is_file():
        raise RecorderError(f"{src}: no such file")
    if dst.exists() or partial_path(dst).exists():
        raise RecorderError(f"{dst} already exists; choose another --out")
    with open(src, "rb") as f:
        if f.read(8) != MAGIC:
            raise RecorderError(f"{src} is not an MCAP file: nothing to recover")
    tmp = partial_path(dst)
    stopped = None
    with open(src, "rb") as f, open(tmp, "xb") as out:
        copier = _Copier(out)
        record_start = 8
        try:
            for record in StreamReader(f, skip_magic=False, emit_chunks=False, validate_crcs=True).records:
                copier.add(record)
                if not isinstance(record, (Schema, Channel, Message)):  # records inside chunks move no cursor
                    record_start = f.tell()
        except Exception as err:  # noqa: BLE001 -- damage shows up as any decoder's error; stop there
            stopped = f"{type(err).__name__}: {err}" if str(err) else type(err).__name__
            f.seek(record_start)
            salvaged = [r for r in _records_of_cut_chunk(f.read()) if isinstance(r, (Schema, Channel, Message))]
            before = copier.messages
            for record in salvaged:
                copier.add(record)
            if copier.messages > before:
                stopped += f" ({copier.messages - before} messages salvaged from the cut chunk)"
        copier.writer.finish()  # type: ignore[no-untyped-call]  # mcap's Writer.finish is unannotated
        out.flush()
        os.fsync(out.fileno())
    os.replace(tmp, dst)
    return RecoveryReport(copier.messages, len(copier.channel_ids), stopped)
