"""recover: salvages truncated and damaged recordings into valid ones and says how much it kept."""

from __future__ import annotations

import io
import struct
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from mcap.writer import CompressionType, Writer

from slamreplay.recorder import GroundTruthPose, Recorder, RecorderError, codec
from slamreplay.recorder.codec.mcap_io import MAGIC
from slamreplay.recorder.errors import DamageError
from slamreplay.recorder.recover import describe, recover
from slamreplay.replay.engine.reader import RecordingReader
from slamreplay.replay.tools.inspect import inspect_recording


def big_recording(path: Path, n: int = 30000) -> Path:
    """Enough messages for several 1 MiB chunks."""
    rng = np.random.default_rng(0)
    with Recorder(path, source={}) as rec:
        for k in range(n):
            rec.write("/ground_truth/pose", GroundTruthPose(1000 + k, *rng.normal(size=3)))
    return path


@pytest.mark.parametrize("fraction", [0.1, 0.6])
def test_truncated_file_is_salvaged(tmp_path: Path, fraction: float) -> None:
    """A cut file gives a valid MCAP with its complete chunks plus what the cut chunk still holds, in order."""
    src = big_recording(tmp_path / "a.mcap")
    data = src.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: int(len(data) * fraction)])
    report = recover(cut, tmp_path / "fixed.mcap")
    # zstd gives back whole 128 KiB blocks of a cut chunk: at most a block's worth of messages is lost
    assert 30000 * (fraction - 0.1) < report.messages < 30000
    assert report.stopped_at is not None and "salvaged from the cut chunk" in report.stopped_at
    assert (report.lost, report.lost_exact, report.expected) == (0, False, None)  # no index is left to count them
    assert "an unknown number of messages lost in the dropped bytes" in describe(report, "fixed.mcap")
    reader = RecordingReader(tmp_path / "fixed.mcap")
    got = [e.log_time_ns for e in reader.messages()]
    assert got == list(range(1000, 1000 + report.messages))
    assert reader.info.metadata["slamreplay.recording"]["source"] == "{}"


def test_whole_file_is_copied(tmp_path: Path) -> None:
    """An undamaged file is copied entirely and reported as such."""
    src = big_recording(tmp_path / "a.mcap", 500)
    report = recover(src, tmp_path / "b.mcap")
    assert (report.messages, report.channels, report.stopped_at) == (500, 1, None)


def _chunk_indexes(path: Path) -> list[Any]:
    from mcap.reader import make_reader

    with open(path, "rb") as f:
        return sorted(make_reader(f).get_summary().chunk_indexes, key=lambda c: c.chunk_start_offset)


def test_crc_damage_drops_only_the_bad_chunk(tmp_path: Path) -> None:
    """A flipped byte inside the second chunk drops that chunk alone, counted exactly against the statistics."""
    src = big_recording(tmp_path / "a.mcap")
    chunks = _chunk_indexes(src)
    assert len(chunks) >= 3
    data = bytearray(src.read_bytes())
    second = chunks[1]
    data[second.chunk_start_offset + second.chunk_length - 100] ^= 0xFF
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(bytes(data))
    report = recover(bad, tmp_path / "fixed.mcap")
    # the pose messages have log times 1000, 1001, ...: chunk 2 holds exactly its [start, end] times
    in_second = second.message_end_time - second.message_start_time + 1
    assert (report.messages, report.lost, report.lost_exact, report.expected) == (30000 - in_second, in_second,
                                                                                 True, 30000)
    assert [(a, b) for a, b, _ in report.dropped] == [(second.chunk_start_offset,
                                                       second.chunk_start_offset + second.chunk_length)]
    assert report.stopped_at is not None and "Chunk record at byte" in report.stopped_at
    got = [e.log_time_ns for e in RecordingReader(tmp_path / "fixed.mcap").messages()]
    assert got == [t for t in range(1000, 31000) if not second.message_start_time <= t <= second.message_end_time]


def test_lost_messages_counted_from_message_indexes_without_summary(tmp_path: Path) -> None:
    """With the summary cut off, a dropped chunk's messages are counted from the MessageIndex records after it."""
    src = big_recording(tmp_path / "a.mcap")
    chunks = _chunk_indexes(src)
    second = chunks[1]
    data = bytearray(src.read_bytes())
    data[second.chunk_start_offset + 200] ^= 0x01
    last = chunks[-1]
    cut = last.chunk_start_offset + last.chunk_length + last.message_index_length  # before DataEnd and the summary
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(bytes(data[:cut]))
    report = recover(bad, tmp_path / "fixed.mcap")
    in_second = second.message_end_time - second.message_start_time + 1
    assert (report.messages, report.lost, report.lost_exact, report.expected) == (30000 - in_second, in_second,
                                                                                 True, None)


def _uncompressed_recording(path: Path, n: int = 400) -> Path:
    """Poses written with uncompressed 2 KiB chunks, so that every message's last byte is known."""
    out = io.BytesIO()
    w = Writer(out, chunk_size=2048, compression=CompressionType.NONE, enable_crcs=True)
    w.start()
    msg0 = GroundTruthPose(1000, 0.0, 0.0, 0.0)
    sid = w.register_schema(codec.schema_name(msg0), "protobuf", codec.schema_data(msg0))
    cid = w.register_channel("/ground_truth/pose", "protobuf", sid)
    for k in range(n):
        w.add_message(cid, 1000 + k, codec.encode(GroundTruthPose(1000 + k, 0.01 * k, 0.0, 0.0)), 1000 + k, k)
    w.finish()
    path.write_bytes(out.getvalue())
    return path


def _message_ends(path: Path) -> list[int]:
    """The file offset just after each message record, in file order (uncompressed chunks only)."""
    ends = []
    data = path.read_bytes()
    for ci in _chunk_indexes(path):
        body = ci.chunk_start_offset + 9
        (clen,) = struct.unpack_from("<I", data, body + 28)
        start = body + 32 + clen + 8
        (size,) = struct.unpack_from("<Q", data, body + 32 + clen)
        pos = start
        while pos < start + size:
            opcode, (length,) = data[pos], struct.unpack_from("<Q", data, pos + 1)
            pos += 9 + length
            if opcode == 0x05:
                ends.append(pos)
    return ends


def test_truncation_keeps_every_message_before_the_cut(tmp_path: Path) -> None:
    """Uncompressed chunks: the recovered count is exactly the number of message records wholly before the cut.

    Every record of an uncompressed chunk can be read up to the cut, so nothing before it is
    lost, whether the cut falls in a chunk's header, inside a message, between messages or in
    the message indexes after a chunk.
    """
    src = _uncompressed_recording(tmp_path / "plain.mcap")
    ends = _message_ends(src)
    assert len(ends) == 400 and len(_chunk_indexes(src)) > 5
    data = src.read_bytes()
    rng = np.random.default_rng(3)
    cuts = sorted({*(int(c) for c in rng.integers(ends[0], len(data) - 8, 12)), ends[57], ends[57] - 1, ends[-1]})
    for cut in cuts:
        bad = tmp_path / f"cut-{cut}.mcap"
        bad.write_bytes(data[:cut])
        report = recover(bad, tmp_path / f"fixed-{cut}.mcap")
        expected = sum(1 for e in ends if e <= cut)
        assert report.messages == expected, cut
        got = [e.log_time_ns for e in RecordingReader(tmp_path / f"fixed-{cut}.mcap").messages()]
        assert got == list(range(1000, 1000 + expected))


@pytest.mark.parametrize("fraction", [0.05, 0.3, 0.52, 0.77, 0.999])
def test_truncated_zstd_recording_keeps_whole_chunks_and_a_prefix(tmp_path: Path, fraction: float) -> None:
    """zstd chunks: every chunk wholly before the cut is kept, plus the whole 128 KiB zstd blocks of the cut chunk.

    A zstd block is decoded only when all of it is there, so the messages of the cut chunk
    that lie in its last, partial block are lost: the recovered messages are the original's
    first N, with N between the messages of the complete chunks and those of every chunk that
    starts before the cut.
    """
    src = big_recording(tmp_path / "a.mcap")
    chunks = _chunk_indexes(src)
    data = src.read_bytes()
    cut = int(len(data) * fraction)
    whole = sum(c.message_end_time - c.message_start_time + 1 for c in chunks
                if c.chunk_start_offset + c.chunk_length <= cut)
    started = sum(c.message_end_time - c.message_start_time + 1 for c in chunks if c.chunk_start_offset < cut)
    bad = tmp_path / "cut.mcap"
    bad.write_bytes(data[:cut])
    report = recover(bad, tmp_path / "fixed.mcap")
    assert whole <= report.messages <= started
    got = [e.log_time_ns for e in RecordingReader(tmp_path / "fixed.mcap").messages()]
    assert got == list(range(1000, 1000 + report.messages))


def test_random_body_between_magics_is_refused(tmp_path: Path) -> None:
    """No valid MCAP content: recover says so, raises, and writes nothing (no file, no .partial)."""
    junk = tmp_path / "junk.mcap"
    junk.write_bytes(MAGIC + np.random.default_rng(0).integers(0, 256, 3000, dtype=np.uint8).tobytes() + MAGIC)
    with pytest.raises(DamageError, match="holds no readable message.*nothing to recover, no file written"):
        recover(junk, tmp_path / "o.mcap")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["junk.mcap"]


def test_header_only_recording_is_refused(tmp_path: Path) -> None:
    """A recording cut right after its header and metadata has no message to recover."""
    src = big_recording(tmp_path / "a.mcap", 10)
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(src.read_bytes()[:_chunk_indexes(src)[0].chunk_start_offset])
    with pytest.raises(DamageError, match="holds no readable message"):
        recover(cut, tmp_path / "o.mcap")


def test_undecodable_messages_and_damaged_schema_are_dropped(tmp_path: Path) -> None:
    """A message whose bytes do not decode is dropped and counted; so is every message of a damaged schema."""
    path = tmp_path / "mixed.mcap"
    with open(path, "wb") as f:
        w = Writer(f, compression=CompressionType.ZSTD)
        w.start()
        msg0 = GroundTruthPose(1000, 0.0, 0.0, 0.0)
        good = w.register_schema(codec.schema_name(msg0), "protobuf", codec.schema_data(msg0))
        broken = w.register_schema(codec.schema_name(msg0), "protobuf", b"\xff\xff not a FileDescriptorSet")
        gt = w.register_channel("/ground_truth/pose", "protobuf", good)
        odom = w.register_channel("/odom", "protobuf", broken)
        for k in range(10):
            body = b"\x0a\xff\xff" if k == 4 else codec.encode(GroundTruthPose(1000 + k, 0.0, 0.0, 0.0))
            w.add_message(gt, 1000 + k, body, 1000 + k)
            w.add_message(odom, 1000 + k, codec.encode(GroundTruthPose(1000 + k, 0.0, 0.0, 0.0)), 1000 + k)
        w.finish()
    report = recover(path, tmp_path / "fixed.mcap")
    assert (report.messages, report.channels, report.lost, report.lost_exact) == (9, 1, 11, True)
    assert any("/odom: its schema foxglove.PoseInFrame" in n and "is damaged" in n for n in report.notes)
    assert any("/ground_truth/pose message at log_time 1004 ns is invalid" in n for n in report.notes)
    assert inspect_recording(tmp_path / "fixed.mcap")["health"] == "ok"
    text = describe(report, "fixed.mcap")
    assert text.startswith("recovered 9 messages of the 20 the file's statistics count on 1 channels into "
                           "fixed.mcap; 11 messages lost")


def test_recover_errors(tmp_path: Path) -> None:
    """Missing input, non-MCAP input and an existing output are refused."""
    with pytest.raises(RecorderError, match="no such file"):
        recover(tmp_path / "nope.mcap", tmp_path / "o.mcap")
    empty = tmp_path / "empty.mcap.partial"
    empty.write_bytes(b"")
    with pytest.raises(DamageError, match="is empty \\(0 bytes\\): nothing was written to it"):
        recover(empty, tmp_path / "o.mcap")
    junk = tmp_path / "junk.mcap"
    junk.write_bytes(b"hello world, not an mcap")
    with pytest.raises(RecorderError, match="not an MCAP"):
        recover(junk, tmp_path / "o.mcap")
    src = big_recording(tmp_path / "a.mcap", 10)
    (tmp_path / "o.mcap").write_bytes(b"x")
    with pytest.raises(RecorderError, match="already exists"):
        recover(src, tmp_path / "o.mcap")


def test_a_damaged_sensor_model_is_dropped_from_the_metadata(tmp_path: Path) -> None:
    """A sensor model whose JSON is damaged (valid UTF-8, bad JSON) is left out, with a note: the output is healthy."""
    from mcap.writer import Writer as McapWriter

    from slamreplay.recorder.writer import METADATA_NAME

    msg = GroundTruthPose(1000, 0.0, 0.0, 0.0)
    src = tmp_path / "a.mcap"
    with open(src, "wb") as f:
        w = McapWriter(f)
        w.start()
        w.add_metadata(METADATA_NAME, {"source": "{}", "sensor_model": '{"range_sigma_m": 0.1\x00}'})
        sid = w.register_schema(codec.schema_name(msg), "protobuf", codec.schema_data(msg))
        cid = w.register_channel("/ground_truth/pose", "protobuf", sid)
        w.add_message(cid, 1000, codec.encode(msg), 1000)
        w.finish()
    assert inspect_recording(src)["health"] == "corrupt"
    report = recover(src, tmp_path / "fixed.mcap")
    assert (report.messages, report.lost) == (1, 0)
    assert report.notes == ("the sensor_model entry of the slamreplay.recording metadata: the recording's sensor "
                            "model is not valid JSON (Expecting ',' delimiter: line 1 column 22 (char 21)); "
                            "re-record it or pass every noise setting with --set",)
    fixed = inspect_recording(tmp_path / "fixed.mcap")
    assert fixed["health"] == "ok", fixed["problems"]
    assert RecordingReader(tmp_path / "fixed.mcap").info.metadata[METADATA_NAME] == {"source": "{}"}
