"""Recordings that are all valid framing and valid CRCs, made of many chunks that each stay within the per-chunk
limits but together ask for hours of work: the per-file bound's test input (tests/fuzz/test_bomb_file.py).

``bomb_file(path, chunks, records)`` copies the header, metadata, schema and channel of a one-message slamreplay
recording of ``/odom``, then writes ``chunks`` copies of one zstd chunk holding ``records`` copies of its
message record (same channel, same times; CRC of the uncompressed records set right), each followed by its
MessageIndex, then a summary indexing every chunk and a Statistics record counting every message, as a
writer would.

    .venv/bin/python -m tests.fuzz.bombs /tmp/bomb.mcap --chunks 1000 --records 1000000
"""

from __future__ import annotations

import argparse
import io
import zlib
from pathlib import Path

import zstandard
from mcap.data_stream import RecordBuilder
from mcap.opcode import Opcode
from mcap.records import (
    Channel,
    Chunk,
    ChunkIndex,
    DataEnd,
    Footer,
    Header,
    Message,
    MessageIndex,
    Metadata,
    Schema,
    Statistics,
)

from slamreplay.recorder.codec.mcap_io import MAGIC, McapFile, chunk_records, decompress
from slamreplay.recorder.messages import OdometryPose
from slamreplay.recorder.writer import Recorder


def _template(dirpath: Path) -> tuple[Header, list[Metadata], Schema, Channel, Message]:
    """The records of a one-message slamreplay recording of /odom."""
    path = dirpath / "template.mcap"
    path.unlink(missing_ok=True)
    with Recorder(path, source={"simulator": "bomb template"}) as rec:
        rec.write("/odom", OdometryPose(1_000_000_000, 1.0, 2.0, 0.5))
    metadata: list[Metadata] = []
    with McapFile(path) as f:
        header = f.header()
        for offset, _, record in f.records():
            if isinstance(record, Metadata):
                metadata.append(record)
            elif isinstance(record, Chunk):
                inner = list(chunk_records(decompress(record, offset), offset))
                schema = next(r for r in inner if isinstance(r, Schema))
                channel = next(r for r in inner if isinstance(r, Channel))
                message = next(r for r in inner if isinstance(r, Message))
    path.unlink()
    return header, metadata, schema, channel, message


def _bytes(*records: object) -> bytes:
    b = RecordBuilder()
    for r in records:
        r.write(b)  # type: ignore[attr-defined]
    return bytes(b.end())


def bomb_file(path: Path, chunks: int, records: int) -> int:
    """Write the bomb recording (see the module docstring) to ``path``; its size in bytes."""
    header, metadata, schema, channel, message = _template(path.parent)
    one = _bytes(message)
    uncompressed = one * records
    cobj = zstandard.ZstdCompressor(level=19, write_content_size=False).compressobj()
    data = b"".join(cobj.compress(one * 10_000) for _ in range(records // 10_000))
    data += cobj.compress(one * (records % 10_000)) + cobj.flush()
    t = message.log_time
    chunk = _bytes(Chunk(message_start_time=t, message_end_time=t, uncompressed_size=len(uncompressed),
                         uncompressed_crc=zlib.crc32(uncompressed), compression="zstd", data=data))
    del uncompressed
    index = _bytes(MessageIndex(channel_id=channel.id, records=[(t, k * len(one)) for k in range(min(records, 1))]))
    out = io.BytesIO()
    out.write(MAGIC)
    out.write(_bytes(header, *metadata, schema, channel))
    chunk_indexes = []
    for _ in range(chunks):
        start = out.tell()
        out.write(chunk)
        out.write(index)
        chunk_indexes.append(ChunkIndex(message_start_time=t, message_end_time=t, chunk_start_offset=start,
                                        chunk_length=len(chunk), message_index_offsets={channel.id: start + len(chunk)},
                                        message_index_length=len(index), compression="zstd",
                                        compressed_size=len(data), uncompressed_size=records * len(one)))
    out.write(_bytes(DataEnd(data_section_crc=0)))
    summary_start = out.tell()
    out.write(_bytes(schema, channel, *chunk_indexes,
                     Statistics(message_count=chunks * records, schema_count=1, channel_count=1, attachment_count=0,
                                metadata_count=len(metadata), chunk_count=chunks, message_start_time=t,
                                message_end_time=t, channel_message_counts={channel.id: chunks * records})))
    out.write(_bytes(Footer(summary_start=summary_start, summary_offset_start=0, summary_crc=0)))
    out.write(MAGIC)
    path.write_bytes(out.getvalue())
    assert Opcode.CHUNK  # the records above are the library's own: the file is what a writer would make
    return out.tell()


def main() -> None:
    """Write one bomb recording (see the module docstring)."""
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("out", type=Path)
    p.add_argument("--chunks", type=int, default=1000)
    p.add_argument("--records", type=int, default=1_000_000)
    args = p.parse_args()
    size = bomb_file(args.out, args.chunks, args.records)
    print(f"wrote {args.out}: {size:,} bytes, {args.chunks:,} chunks of {args.records:,} messages")


if __name__ == "__main__":
    main()
