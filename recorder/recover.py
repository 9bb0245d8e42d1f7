"""Salvage a truncated, ``.partial`` or corrupt MCAP into a valid, indexed one.

The input is read linearly (no index needed) and every message up to the first damaged
record is re-written, with its schema, channel, log and publish times, into a new file
with zstd chunks and CRCs. Metadata records met before the damage are kept too.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

from mcap.records import Channel, Message, Metadata, Schema
from mcap.stream_reader import StreamReader
from mcap.writer import CompressionType, Writer

from recorder.errors import RecorderError
from recorder.version import version
from recorder.writer import CHUNK_SIZE, partial_path


@dataclass(frozen=True, slots=True)
class RecoveryReport:
    """What was kept: messages, channels, and where and why reading stopped (None: no damage found)."""

    messages: int
    channels: int
    stopped_at: str | None


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
        if f.read(8) != b"\x89MCAP0\r\n":
            raise RecorderError(f"{src} is not an MCAP file: nothing to recover")
    tmp = partial_path(dst)
    schemas: dict[int, int] = {}
    channels: dict[int, int] = {}
    seen_channels: dict[int, Channel] = {}
    seen_schemas: dict[int, Schema] = {}
    count, stopped = 0, None
    with open(src, "rb") as f, open(tmp, "xb") as out:
        writer = Writer(out, chunk_size=CHUNK_SIZE, compression=CompressionType.ZSTD, enable_crcs=True)
        writer.start(profile="", library=f"slamreplay/{version()} recover")
        try:
            for record in StreamReader(f, skip_magic=False, emit_chunks=False, validate_crcs=True).records:
                if isinstance(record, Schema):
                    seen_schemas[record.id] = record
                elif isinstance(record, Channel):
                    seen_channels[record.id] = record
                elif isinstance(record, Metadata):
                    writer.add_metadata(record.name, record.metadata)
                elif isinstance(record, Message):
                    channel_id = channels.get(record.channel_id)
                    if channel_id is None:
                        channel = seen_channels[record.channel_id]
                        schema_id = 0
                        if channel.schema_id:
                            if channel.schema_id not in schemas:
                                s = seen_schemas[channel.schema_id]
                                schemas[channel.schema_id] = writer.register_schema(s.name, s.encoding, s.data)
                            schema_id = schemas[channel.schema_id]
                        channel_id = writer.register_channel(channel.topic, channel.message_encoding, schema_id,
                                                             channel.metadata)
                        channels[record.channel_id] = channel_id
                    writer.add_message(channel_id, record.log_time, record.data, record.publish_time,
                                       record.sequence)
                    count += 1
        except Exception as err:  # noqa: BLE001 -- damage shows up as any decoder's error; stop there
            stopped = f"{type(err).__name__}: {err}" if str(err) else type(err).__name__
        writer.finish()
        out.flush()
        os.fsync(out.fileno())
    os.replace(tmp, dst)
    return RecoveryReport(count, len(channels), stopped)
