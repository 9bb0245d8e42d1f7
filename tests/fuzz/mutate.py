"""Seeded damage to real recordings: the mutation half of the fuzz harness.

Base recordings are made by slamreplay's own producers, small enough to mutate by the
thousand: ``landmarks`` (``sim-landmarks``, protobuf scans and poses), ``seabed``
(``sim-seabed``, PNG ``foxglove.CompressedImage``), ``corridor`` (``sim-corridor``, raw
``foxglove.RawImage``), ``images`` (``record images``, mono8 PNG frames) and ``ros2`` (a
ROS 2 bag in MCAP storage, CDR odometry, poses and bgr8 images, as rosbag2 writes it).

A mutant is fixed by (kind, seed, index): ``mutant(base, seed, index)`` draws one operator
and its parameters from ``numpy.random.default_rng([seed, index])``, so any mutant of a
campaign is rebuilt exactly from its three numbers. Operators damage bytes (bit flips,
zeroed runs, truncation, overwritten length fields, spliced spans, random bodies between
MCAP magics, dropped records) or content inside valid framing (a schema's
FileDescriptorSet or a message's bytes re-written with valid chunks and CRCs, and byte
damage to an uncompressed, CRC-less copy, as other MCAP writers produce).
"""

from __future__ import annotations

import io
import struct
import sys
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from mcap.reader import make_reader
from mcap.records import Channel, Message, Schema
from mcap.stream_reader import StreamReader
from mcap.writer import CompressionType, Writer

REPO = Path(__file__).resolve().parents[2]
MAGIC = b"\x89MCAP0\r\n"
KINDS = ("landmarks", "seabed", "corridor", "images", "ros2")
# The pipeline `run` uses per kind: one that decodes the kind's characteristic messages. ``landmarks30`` is the
# outsider's base of issue 26 (a 30 s ``sim-landmarks`` recording with its defaults, ~50 KB), not in KINDS.
RUN_PIPELINE = {"landmarks": "dslam", "seabed": "ifmi", "corridor": "ifmi", "images": "ifmi", "ros2": "odometry",
                "landmarks30": "odometry"}


def make_base(kind: str, folder: Path) -> Path:
    """Write the base recording of ``kind`` into ``folder`` (deterministic; 15-45 KB); return its path."""
    from slamreplay.api.cli.command import main

    folder.mkdir(parents=True, exist_ok=True)
    out = folder / f"{kind}.mcap"
    if out.exists():
        return out
    if kind == "landmarks":
        argv = ["record", "sim-landmarks", "--duration-s", "8", "--landmarks", "16", "--seed", "1"]
    elif kind == "landmarks30":
        argv = ["record", "sim-landmarks", "--duration-s", "30"]  # as an outsider types it: the default seed
    elif kind == "seabed":
        argv = ["record", "sim-seabed", "--legs", "1", "--leg-length-m", "1", "--image-px", "64", "--seed", "1"]
    elif kind == "corridor":
        argv = ["record", "sim-corridor", "--image-width", "40", "--image-height", "32", "--route", "left",
                "--camera-rate-hz", "0.2", "--odom-rate-hz", "1", "--compression", "raw", "--seed", "1"]
    elif kind == "images":
        frames = folder / "frames"
        frames.mkdir(exist_ok=True)
        rng = np.random.default_rng(1)
        scene = cv2.GaussianBlur(rng.integers(0, 256, (96, 128), dtype=np.uint8), (0, 0), 2.0)
        for k in range(5):
            cv2.imwrite(str(frames / f"frame_{k:03d}.png"), scene[4 * k:4 * k + 48, 6 * k:6 * k + 64])
        argv = ["record", "images", str(frames)]
    elif kind == "ros2":
        sys.path.insert(0, str(REPO / "tests" / "replay"))
        from ros2_fixtures import write_ros2_bag

        bag = write_ros2_bag(folder / "ros2bag", n=30)
        (bag / "ros2bag_0.mcap").rename(out)
        return out
    else:
        raise ValueError(f"unknown kind {kind!r}; one of {', '.join(KINDS)}")
    rc = main([*argv, "--out", str(out), "--quiet"])
    if rc != 0:
        raise RuntimeError(f"could not make the {kind} base recording: exit {rc}")
    return out


@dataclass(frozen=True, slots=True)
class Mutant:
    """Damaged bytes and what was done to them (``recipe`` is JSON-friendly)."""

    data: bytes
    recipe: dict[str, Any]


def top_level_records(data: bytes) -> list[tuple[int, int, int]]:
    """(offset, opcode, total length) of each top-level record of an intact MCAP."""
    out, pos = [], len(MAGIC)
    while pos + 9 <= len(data) - len(MAGIC):
        opcode = data[pos]
        (length,) = struct.unpack_from("<Q", data, pos + 1)
        out.append((pos, opcode, 9 + length))
        pos += 9 + length
    return out


def _rewrite(data: bytes, *, compression: CompressionType = CompressionType.ZSTD, crcs: bool = True,
             schema_edit: Callable[[Schema], bytes] | None = None,
             message_edit: Callable[[int, bytes], bytes] | None = None) -> bytes:
    """Re-write an MCAP record by record, optionally editing schema data or message data."""
    out = io.BytesIO()
    writer = Writer(out, chunk_size=16 * 1024, compression=compression, enable_crcs=crcs, enable_data_crcs=crcs)
    header = make_reader(io.BytesIO(data)).get_header()
    writer.start(profile=header.profile, library=header.library)
    schemas: dict[int, int] = {}
    channels: dict[int, int] = {}
    pending: dict[int, Channel] = {}
    index = 0
    for record in StreamReader(io.BytesIO(data), skip_magic=False).records:
        if isinstance(record, Schema) and record.id not in schemas:
            body = schema_edit(record) if schema_edit else record.data
            schemas[record.id] = writer.register_schema(record.name, record.encoding, body)
        elif isinstance(record, Channel) and record.id not in channels:
            pending[record.id] = record
            channels[record.id] = writer.register_channel(record.topic, record.message_encoding,
                                                          schemas.get(record.schema_id, 0), record.metadata)
        elif isinstance(record, Message):
            body = message_edit(index, record.data) if message_edit else record.data
            writer.add_message(channels[record.channel_id], record.log_time, body, record.publish_time,
                               record.sequence)
            index += 1
        elif type(record).__name__ == "Metadata":
            writer.add_metadata(record.name, record.metadata)  # type: ignore[attr-defined]
    writer.finish()  # type: ignore[no-untyped-call]
    return out.getvalue()


def _flip(buf: bytearray, rng: np.random.Generator, lo: int, hi: int, n: int) -> list[list[int]]:
    done = []
    for _ in range(n):
        at, bit = int(rng.integers(lo, max(lo + 1, hi))), int(rng.integers(0, 8))
        if at < len(buf):
            buf[at] ^= 1 << bit
            done.append([at, bit])
    return done


# Huge little-endian lengths an outsider writes at any offset (issue 26): near 2**64, 2**40, past 2**63...
HUGE = (0xFFFF_FFFF_FFFF_FFF0, 1 << 40, 1 << 63, (1 << 64) - 1, 1 << 32, 0xFFFF_FFFF, 0x7FFF_FFFF, 1 << 48)
LENGTHS = (0, 1, 7, 0xFF, 0xFFFF, 0x7FFF_FFFF, 0xFFFF_FFFF, 1 << 32, 1 << 40, 1 << 62, (1 << 63) - 1, (1 << 64) - 1)


def _byte_op(data: bytes, rng: np.random.Generator, op: str, records: list[tuple[int, int, int]]) -> Mutant:
    """One byte-level operator on ``data`` (an intact MCAP whose records are ``records``)."""
    buf, n = bytearray(data), len(data)
    if op == "bitflip":
        return Mutant(bytes(buf), {"op": op, "flips": _flip(buf, rng, 0, n, int(rng.integers(1, 9)))})
    if op == "zero_run":
        at, length = int(rng.integers(0, n)), int(rng.integers(1, 513))
        buf[at:at + length] = bytes(len(buf[at:at + length]))
        return Mutant(bytes(buf), {"op": op, "at": at, "length": length})
    if op == "truncate":
        at = int(rng.integers(0, n))
        return Mutant(bytes(buf[:at]), {"op": op, "at": at})
    if op == "record_length":
        at, opcode, _ = records[int(rng.integers(0, len(records)))]
        value = int(LENGTHS[int(rng.integers(0, len(LENGTHS)))]) if rng.random() < 0.7 else int(
            rng.integers(0, 1 << 62))
        struct.pack_into("<Q", buf, at + 1, value)
        return Mutant(bytes(buf), {"op": op, "record_at": at, "opcode": opcode, "value": value})
    if op == "field_length":  # a u32 string/bytes/map length or a u64 size inside a record's body
        at, opcode, total = records[int(rng.integers(0, len(records)))]
        width = 4 if rng.random() < 0.6 else 8
        if total - 9 < width:
            return _byte_op(data, rng, "bitflip", records)
        field = at + 9 + int(rng.integers(0, total - 9 - width + 1))
        value = int(LENGTHS[int(rng.integers(0, len(LENGTHS)))]) & ((1 << (8 * width)) - 1)
        struct.pack_into("<I" if width == 4 else "<Q", buf, field, value)
        return Mutant(bytes(buf), {"op": op, "record_at": at, "opcode": opcode, "field_at": field, "value": value})
    if op == "splice":  # copy a span elsewhere, overwriting or inserting
        a, b = sorted(int(x) for x in rng.integers(0, n, 2))
        b = min(b, a + 4096)
        to = int(rng.integers(0, n))
        span = bytes(buf[a:b])
        if rng.random() < 0.5:
            buf[to:to + len(span)] = span
            how = "overwrite"
        else:
            buf[to:to] = span
            how = "insert"
        return Mutant(bytes(buf), {"op": op, "from": [a, b], "to": to, "how": how})
    if op == "overwrite8":  # 8 random bytes over whatever is at a random offset
        at = int(rng.integers(0, max(1, n - 8)))
        junk = rng.integers(0, 256, 8, dtype=np.uint8).tobytes()
        buf[at:at + 8] = junk
        return Mutant(bytes(buf[:n]), {"op": op, "at": at, "bytes": junk.hex()})
    if op == "huge_length":  # a huge u64 (or u32) length at a random offset, record boundary or not
        value = int(HUGE[int(rng.integers(0, len(HUGE)))])
        width = 8 if value > 0xFFFF_FFFF or rng.random() < 0.5 else 4
        at = int(rng.integers(0, max(1, n - width)))
        struct.pack_into("<Q" if width == 8 else "<I", buf, at, value)
        return Mutant(bytes(buf), {"op": op, "at": at, "value": value, "width": width})
    if op == "drop_record":
        at, opcode, total = records[int(rng.integers(0, len(records)))]
        del buf[at:at + total]
        return Mutant(bytes(buf), {"op": op, "record_at": at, "opcode": opcode, "length": total})
    if op == "random_body":
        size = int(rng.integers(0, 4097))
        body = rng.integers(0, 256, size, dtype=np.uint8).tobytes()
        if rng.random() < 0.5:  # keep the real header record, as a writer that died after start() would
            head = data[:records[0][0] + records[0][2]]
            return Mutant(head + body + MAGIC, {"op": op, "size": size, "header": True})
        return Mutant(MAGIC + body + MAGIC, {"op": op, "size": size, "header": False})
    if op == "summary":  # damage in the summary section, which the indexed reader trusts first
        ends = [r for r in records if r[1] == 0x0F]  # DataEnd
        lo = ends[0][0] + ends[0][2] if ends else n // 2
        return Mutant(bytes(buf), {"op": op, "flips": _flip(buf, rng, lo, n - len(MAGIC), int(rng.integers(1, 4)))})
    raise ValueError(f"unknown operator {op!r}")


BYTE_OPS = ("bitflip", "zero_run", "truncate", "record_length", "field_length", "splice", "drop_record",
            "random_body", "summary")
CONTENT_OPS = ("schema_data", "message_data", "raw_inner")
OPS = BYTE_OPS + CONTENT_OPS
# The five kinds of the outsider's campaign of issue 26; only drawn when ``mutant(..., op=...)`` names one.
OUTSIDER_OPS = ("splice", "zero_run", "truncate", "overwrite8", "huge_length")


def mutant(base: bytes, seed: int, index: int, op: str | None = None) -> Mutant:
    """Mutant number ``index`` of campaign ``seed`` of ``base``; ``op`` forces the operator."""
    rng = np.random.default_rng([seed, index])
    chosen = OPS[int(rng.integers(0, len(OPS)))]
    op = op or chosen
    if op in BYTE_OPS or op in OUTSIDER_OPS:
        m = _byte_op(base, rng, op, top_level_records(base))
    elif op == "schema_data":
        picks: dict[int, list[list[int]]] = {}

        def edit_schema(schema: Schema) -> bytes:
            body = bytearray(schema.data)
            if rng.random() < 0.5 and body:
                picks[schema.id] = _flip(body, rng, 0, len(body), int(rng.integers(1, 6)))
                return bytes(body)
            if rng.random() < 0.3:
                cut = int(rng.integers(0, len(body) + 1))
                picks[schema.id] = [[cut, -1]]
                return bytes(body[:cut])
            return bytes(body)

        m = Mutant(_rewrite(base, schema_edit=edit_schema), {"op": op, "schemas": picks})
    elif op == "message_data":
        count = sum(1 for r in StreamReader(io.BytesIO(base)).records if isinstance(r, Message))
        targets = {int(t) for t in rng.integers(0, count, int(rng.integers(1, 4)))}
        changes: dict[int, Any] = {}

        def edit_message(i: int, body: bytes) -> bytes:
            if i not in targets:
                return body
            buf = bytearray(body)
            how = int(rng.integers(0, 3))
            if how == 0 and buf:
                changes[i] = _flip(buf, rng, 0, len(buf), int(rng.integers(1, 9)))
                return bytes(buf)
            if how == 1:
                cut = int(rng.integers(0, len(buf) + 1))
                changes[i] = ["cut", cut]
                return bytes(buf[:cut])
            junk = rng.integers(0, 256, int(rng.integers(1, 64)), dtype=np.uint8).tobytes()
            changes[i] = ["junk", len(junk)]
            return junk + bytes(buf) if rng.random() < 0.5 else bytes(buf) + junk

        m = Mutant(_rewrite(base, message_edit=edit_message), {"op": op, "messages": changes})
    elif op == "raw_inner":  # an uncompressed, CRC-less copy (as other writers make), then byte damage
        plain = _rewrite(base, compression=CompressionType.NONE, crcs=False)
        inner = str(BYTE_OPS[int(rng.integers(0, 7))])  # bitflip .. drop_record
        m = _byte_op(plain, rng, inner, top_level_records(plain))
        m = Mutant(m.data, {"op": op, "inner": m.recipe})
    else:
        raise ValueError(f"unknown operator {op!r}")
    return Mutant(m.data, {"seed": seed, "index": index, **m.recipe})
