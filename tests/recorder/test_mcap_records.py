"""The bounds-checked MCAP record parser: the library's records back, or one DamageError naming field and offset."""

from __future__ import annotations

import re
import struct

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from mcap.data_stream import RecordBuilder
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

from slamreplay.recorder.codec.mcap_records import parse_record
from slamreplay.recorder.errors import DamageError

RECORDS = [
    Header(profile="ros2", library="slamreplay/0.1"),
    Footer(summary_start=123, summary_offset_start=456, summary_crc=789),
    Schema(id=3, name="foxglove.PoseInFrame", encoding="protobuf", data=b"\x01\x02\x03"),
    Channel(id=5, topic="/odom", message_encoding="protobuf", metadata={"k": "v", "é": "ü"}, schema_id=3),
    Message(channel_id=5, sequence=7, log_time=1_000, publish_time=1_001, data=b"payload"),
    Chunk(compression="zstd", data=b"abcdef", message_start_time=1, message_end_time=2, uncompressed_crc=99,
          uncompressed_size=600),
    MessageIndex(5, [(1_000, 0), (1_001, 40)]),
    ChunkIndex(chunk_start_offset=8, chunk_length=100, compression="zstd", compressed_size=6, message_end_time=2,
               message_index_length=30, message_index_offsets={5: 108, 6: 130}, message_start_time=1,
               uncompressed_size=600),
    Statistics(attachment_count=0, channel_count=2, channel_message_counts={5: 10, 6: 4}, chunk_count=1,
               message_count=14, message_end_time=2, message_start_time=1, metadata_count=1, schema_count=1),
    Metadata(name="slamreplay.recording", metadata={"source": "{}"}),
    MetadataIndex(offset=10, length=20, name="slamreplay.recording"),
]


def _framed(record: object) -> tuple[int, bytes]:
    """(opcode, body) of a record as the mcap library writes it."""
    b = RecordBuilder()
    record.write(b)  # type: ignore[attr-defined]
    raw = b.end()
    return raw[0], raw[9:]


@pytest.mark.parametrize("record", RECORDS, ids=[type(r).__name__ for r in RECORDS])
def test_every_record_type_round_trips(record: object) -> None:
    """What the mcap library writes parses back to an equal record of the library's own class."""
    opcode, body = _framed(record)
    assert parse_record(opcode, body, "at byte 8") == record


def test_fields_after_the_known_ones_are_ignored() -> None:
    """A later MCAP version may append fields: bytes after the last known field are not damage."""
    opcode, body = _framed(RECORDS[0])
    assert parse_record(opcode, body + b"\x00" * 7, "at byte 8") == RECORDS[0]


def _patched(record: object, at: int, fmt: str, value: int) -> tuple[int, bytes]:
    opcode, body = _framed(record)
    buf = bytearray(body)
    struct.pack_into(fmt, buf, at, value)
    return opcode, bytes(buf)


# (record, offset in the body, format, value written there, the error's known text)
DAMAGE = [
    (RECORDS[5], 36, "<Q", 0xFFFF_FFFF_FFFF_FFF0,
     "Chunk record at byte 1022 is damaged: its records length at byte 36 of the record claims "
     "18,446,744,073,709,551,600 bytes but only 6 follow it"),
    (RECORDS[5], 36, "<Q", 1 << 40, "its records length at byte 36 of the record claims 1,099,511,627,776 bytes but "
                                    "only 6 follow it"),
    (RECORDS[2], 2, "<I", 0xFFFF_FFFF,
     "Schema record at byte 1022 is damaged: its name length at byte 2 of the record claims 4,294,967,295 bytes "
     "but only 39 follow it"),
    (RECORDS[2], 38, "<I", 4, "its data length at byte 38 of the record claims 4 bytes but only 3 follow it"),
    (RECORDS[3], 25, "<I", 8, "its metadata value length at byte 34 of the record needs 4 bytes but only 3 are left"),
    (RECORDS[3], 29, "<I", 1 << 20, "its metadata key length at byte 29 of the record claims 1,048,576 bytes but only "
                                    "18 follow it"),
    (RECORDS[6], 2, "<I", 17, "its records at byte 2 of the record holds 17 bytes, not a whole number of 16-byte "
                              "entries"),
    (RECORDS[7], 32, "<I", 0xFFFF_FFF0, "its message index offsets length at byte 32 of the record claims "
                                        "4,294,967,280 bytes"),
    (RECORDS[8], 42, "<I", 15, "Statistics record at byte 1022 is damaged: its channel message counts at byte 42 of "
                               "the record holds 15 bytes, not a whole number of 10-byte entries"),
    (RECORDS[9], 0, "<I", 0x7FFF_FFFF, "Metadata record at byte 1022 is damaged: its name length at byte 0 of the "
                                       "record claims 2,147,483,647 bytes"),
]


@pytest.mark.parametrize(("record", "at", "fmt", "value", "expected"), DAMAGE,
                         ids=[f"{type(d[0]).__name__}@{d[1]}:{d[3]:#x}" for d in DAMAGE])
def test_a_length_past_the_record_is_named(record: object, at: int, fmt: str, value: int, expected: str) -> None:
    """Every length inside a record is checked before use; the error names the record, field and offset."""
    opcode, body = _patched(record, at, fmt, value)
    with pytest.raises(DamageError, match=re.escape(expected)) as info:
        parse_record(opcode, body, "at byte 1022")
    assert "\n" not in str(info.value)


def test_bad_utf8_and_short_message_are_named() -> None:
    """A string that is not UTF-8 and a Message shorter than its fixed fields give their own one-line errors."""
    opcode, body = _framed(Header(profile="ab", library=""))
    with pytest.raises(DamageError, match=r"Header record at byte 8 is damaged: its profile at byte 0 of the record "
                                          r"is not UTF-8 \(invalid start byte at byte 0 of it\)"):
        parse_record(opcode, body[:4] + b"\xff" + body[5:], "at byte 8")
    with pytest.raises(DamageError, match="holds 10 bytes, fewer than the 22 of a Message's fixed fields"):
        parse_record(0x05, bytes(10), "at byte 8")


@settings(max_examples=300, deadline=None)
@given(index=st.integers(0, len(RECORDS) - 1), cut=st.integers(0, 200), at=st.integers(0, 200),
       junk=st.binary(min_size=1, max_size=8))
def test_any_damage_gives_a_record_or_damage_error(index: int, cut: int, at: int, junk: bytes) -> None:
    """Overwritten and truncated bodies of every record type: a record or DamageError, never another exception."""
    opcode, body = _framed(RECORDS[index])
    buf = bytearray(body)
    buf[at:at + len(junk)] = junk
    damaged = bytes(buf[:cut])
    try:
        parse_record(opcode, damaged, "at byte 8")
    except DamageError as err:
        assert "\n" not in str(err)
