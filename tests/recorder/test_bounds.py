"""Bounded work on hostile recordings: chunks claiming gigabytes, zstd bombs, huge image headers, deep schemas."""

from __future__ import annotations

import resource
import struct
import subprocess
import sys
import time
import tracemalloc
import zlib
from pathlib import Path

import cv2
import numpy as np
import pytest
import zstandard
from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage as CompressedImageProto
from foxglove_schemas_protobuf.RawImage_pb2 import RawImage as RawImageProto
from google.protobuf import descriptor_pb2
from mcap.data_stream import RecordBuilder
from mcap.records import Chunk, Header, Schema

from slamreplay.recorder import Recorder
from slamreplay.recorder.codec import TopicDecoder, encode, schema_data, schema_name
from slamreplay.recorder.codec.bounds import MAX_IMAGE_PIXELS, MAX_SCHEMA_DEPTH, check_ros2_schema
from slamreplay.recorder.codec.mcap_io import MAX_CHUNK_BYTES, decompress
from slamreplay.recorder.codec.protobuf import decode_image_bytes, raw_pixels
from slamreplay.recorder.errors import CodecError, DamageError
from slamreplay.recorder.messages import CameraImage, OdometryPose
from slamreplay.replay.engine.reader import RecordingReader

REPO = Path(__file__).resolve().parents[2]
CORPUS = REPO / "tests" / "fuzz" / "corpus" / "mcap"
_F = descriptor_pb2.FieldDescriptorProto


def _limit_address_space() -> None:
    resource.setrlimit(resource.RLIMIT_AS, (3 << 30, 3 << 30))


def _cli(*argv: str) -> tuple[int, str, str, float]:
    """slamreplay ARGV in a subprocess limited to 3 GB of address space: (exit, stdout, stderr, seconds)."""
    t0 = time.perf_counter()
    proc = subprocess.run([sys.executable, "-m", "slamreplay.api.cli", *argv], capture_output=True, text=True,
                          timeout=120, preexec_fn=_limit_address_space, cwd=REPO)
    return proc.returncode, proc.stdout, proc.stderr, time.perf_counter() - t0


def test_a_1_mb_file_whose_chunk_claims_4_gib_is_refused_unallocated(tmp_path: Path) -> None:
    """The first chunk of a 1 MB recording claims 4 GiB: inspect, run and recover refuse it before allocating."""
    src = tmp_path / "a.mcap"
    rng = np.random.default_rng(0)
    with Recorder(src, source={}) as rec:
        for k in range(20000):  # random doubles do not compress: about 1 MB
            rec.write("/odom", OdometryPose(1000 + k, *rng.normal(size=3)))
    data = bytearray(src.read_bytes())
    assert 0.7e6 < len(data) < 1.5e6
    chunk_at = 8  # the first record: walk to the first Chunk
    while data[chunk_at] != 0x06:
        chunk_at += 9 + struct.unpack_from("<Q", data, chunk_at + 1)[0]
    struct.pack_into("<Q", data, chunk_at + 9 + 16, 4 << 30)  # uncompressed_size
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(bytes(data))
    claim = (f"Chunk record at byte {chunk_at} claims 4,294,967,296 bytes uncompressed, above slamreplay's limit of "
             f"{MAX_CHUNK_BYTES:,} bytes per chunk")
    code, out, err, seconds = _cli("inspect", str(bad))
    assert code == 1 and claim in out and seconds < 60, (out, err)
    code, out, err, seconds = _cli("run", str(bad), "--pipeline", "odometry", "--out", str(tmp_path / "run"), "-q")
    assert code == 2 and claim in err and err.count("\n") == 1 and seconds < 60, err
    code, out, err, seconds = _cli("recover", str(bad), "--out", str(tmp_path / "fixed.mcap"))
    assert code == 0 and f"dropped bytes {chunk_at}.." in out and claim in out and seconds < 60, (out, err)


def _chunk(data: bytes, compression: str, size: int) -> Chunk:
    return Chunk(compression=compression, data=data, message_start_time=0, message_end_time=0, uncompressed_crc=0,
                 uncompressed_size=size)


def test_a_size_no_compression_can_give_is_refused_before_decompressing() -> None:
    """100 MB claimed from 1 KB of zstd (at most 32,768 to 1), lz4 (255 to 1) or none (1 to 1) is damage."""
    with pytest.raises(DamageError, match=r"claims 100,000,000 bytes uncompressed from 1,000 compressed bytes, more "
                                          r"than zstd can give \(at most 32,768 to 1\)"):
        decompress(_chunk(bytes(1000), "zstd", 100_000_000), 77)
    with pytest.raises(DamageError, match=r"more than lz4 can give \(at most 255 to 1\)"):
        decompress(_chunk(bytes(1000), "lz4", 1_000_000), 77)
    with pytest.raises(DamageError, match=r"claims 1,010 bytes uncompressed from 1,000 compressed bytes, more than "
                                          r"no compression can give"):
        decompress(_chunk(bytes(1000), "", 1010), 77)


def test_a_zstd_frame_larger_than_its_chunk_claims_is_refused_from_its_header() -> None:
    """A frame whose header says 64 MiB inside a chunk that claims 1 MiB is refused before decompressing."""
    frame = zstandard.ZstdCompressor(write_content_size=True).compress(bytes(64 << 20))
    with pytest.raises(DamageError, match=r"Chunk record at byte 77 holds a zstd frame of 67,108,864 bytes, more "
                                          r"than the 1,048,576 it records"):
        decompress(_chunk(frame, "zstd", 1 << 20), 77)


def test_a_zstd_bomb_is_decompressed_only_to_the_declared_size() -> None:
    """1 GiB of zeros (32 KB of zstd, no size in the frame) in a chunk claiming 8 MiB: stopped past 8 MiB."""
    cobj = zstandard.ZstdCompressor(write_content_size=False).compressobj()
    zero = bytes(1 << 20)
    bomb = b"".join(cobj.compress(zero) for _ in range(1024)) + cobj.flush()
    assert len(bomb) < 100_000
    tracemalloc.start()
    t0 = time.perf_counter()
    with pytest.raises(DamageError, match=r"Chunk record at byte 77 decompresses to more than the 8,388,608 bytes it "
                                          r"records"):
        decompress(_chunk(bomb, "zstd", 8 << 20), 77)
    seconds = time.perf_counter() - t0
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    assert peak < 64 << 20 and seconds < 5, (peak, seconds)


def _huge_png() -> bytes:
    """A valid 4 x 3 PNG whose IHDR is re-written (with its CRC) to claim 40,000 x 40,000 pixels."""
    ok, buf = cv2.imencode(".png", np.zeros((3, 4), np.uint8))
    assert ok
    png = bytearray(buf.tobytes())
    struct.pack_into(">II", png, 16, 40_000, 40_000)
    struct.pack_into(">I", png, 29, zlib.crc32(bytes(png[12:29])))
    return bytes(png)


def _huge_jpeg() -> bytes:
    """A valid 8 x 8 JPEG whose start-of-frame header claims 40,000 x 40,000 pixels."""
    ok, buf = cv2.imencode(".jpg", np.zeros((8, 8, 3), np.uint8))
    assert ok
    jpg = bytearray(buf.tobytes())
    sof = jpg.index(b"\xff\xc0")
    struct.pack_into(">HH", jpg, sof + 5, 40_000, 40_000)
    return bytes(jpg)


@pytest.mark.parametrize(("fmt", "make"), [("png", _huge_png), ("jpeg", _huge_jpeg)])
def test_an_image_header_claiming_40000_squared_pixels_is_refused_undecoded(fmt: str, make: object) -> None:
    """PNG IHDR and JPEG SOF dimensions are read first: 1.6 Gpx is refused at once, nothing is allocated."""
    data = make()  # type: ignore[operator]
    tracemalloc.start()
    with pytest.raises(CodecError, match=rf"the {fmt} header claims 40,000 x 40,000 pixels; slamreplay decodes at most "
                                         rf"{MAX_IMAGE_PIXELS:,} pixels per image"):
        decode_image_bytes(data, fmt)
    assert tracemalloc.get_traced_memory()[1] < 1 << 20
    tracemalloc.stop()


def test_huge_images_are_refused_through_the_topic_decoder() -> None:
    """A CompressedImage message with the huge PNG and a RawImage claiming 40,000 x 40,000 give one-line errors."""
    for msg in (CameraImage(5, np.zeros((3, 4), np.uint8), "camera", "png"),
                CameraImage(5, np.zeros((3, 4), np.uint8), "camera", "raw")):
        schema = Schema(id=1, name=schema_name(msg), encoding="protobuf", data=schema_data(msg))
        dec = TopicDecoder("/camera/image", CameraImage, schema, "protobuf")
        assert dec(encode(msg), 5).pixels.shape == (3, 4)  # the honest message decodes
        proto = (CompressedImageProto if msg.compression == "png" else RawImageProto).FromString(encode(msg))
        if msg.compression == "png":
            proto.data = _huge_png()
        else:
            proto.width = proto.height = proto.step = 40_000
        with pytest.raises(CodecError, match=r"^/camera/image message at log_time 5 ns is invalid \(\d+ bytes\): the "
                                             r"(png|raw image) header claims 40,000 x 40,000 pixels"):
            dec(proto.SerializeToString(), 5)


def test_raw_pixels_refuses_a_huge_header_before_the_length_check() -> None:
    """A raw image claiming 40,000 x 40,000 names the pixel bound, not the buffer length."""
    with pytest.raises(CodecError, match="the raw image header claims 40,000 x 40,000 pixels"):
        raw_pixels(b"", 40_000, 40_000, 40_000, "mono8")


def _pose_decoder(fds: descriptor_pb2.FileDescriptorSet) -> TopicDecoder:
    schema = Schema(id=1, name="foxglove.PoseInFrame", encoding="protobuf", data=fds.SerializeToString())
    return TopicDecoder("/odom", OdometryPose, schema, "protobuf")


def _file(fds: descriptor_pb2.FileDescriptorSet, name: str = "foxglove/PoseInFrame.proto") -> object:
    return fds.file.add(name=name, package="foxglove", syntax="proto3")


def test_a_protobuf_schema_chained_a_thousand_deep_is_refused() -> None:
    """PoseInFrame -> T0 -> ... -> T999 through message fields: refused before the pool recurses."""
    fds = descriptor_pb2.FileDescriptorSet()
    f = _file(fds)
    names = ["PoseInFrame", *(f"T{k}" for k in range(1000))]
    for k, name in enumerate(names):
        m = f.message_type.add(name=name)  # type: ignore[attr-defined]
        if k + 1 < len(names):
            m.field.add(name="x", number=1, type=_F.TYPE_MESSAGE, type_name=names[k + 1])  # relative names
    t0 = time.perf_counter()
    with pytest.raises(CodecError, match=rf"topic /odom: its schema foxglove.PoseInFrame \(protobuf, \d+ bytes\) is "
                                         rf"damaged and cannot be parsed: CodecError: the schema nests message-typed "
                                         rf"fields 1001 deep, beyond slamreplay's limit of {MAX_SCHEMA_DEPTH}"):
        _pose_decoder(fds)
    assert time.perf_counter() - t0 < 2


def test_nested_declarations_and_file_chains_are_bounded() -> None:
    """Message declarations nested 80 deep, 200 files each importing the next, 10,001 types: each refused."""
    fds = descriptor_pb2.FileDescriptorSet()
    m = _file(fds).message_type.add(name="PoseInFrame")  # type: ignore[attr-defined]
    for k in range(80):
        m = m.nested_type.add(name=f"N{k}")
    with pytest.raises(CodecError, match="nests message declarations 65 deep"):
        _pose_decoder(fds)
    fds = descriptor_pb2.FileDescriptorSet()
    for k in range(200):
        f = _file(fds, f"f{k}.proto")
        if k + 1 < 200:
            f.dependency.append(f"f{k + 1}.proto")  # type: ignore[attr-defined]
    with pytest.raises(CodecError, match="nests file dependencies 200 deep"):
        _pose_decoder(fds)
    fds = descriptor_pb2.FileDescriptorSet()
    f = _file(fds)
    for k in range(10_001):
        f.message_type.add(name=f"T{k}")  # type: ignore[attr-defined]
    with pytest.raises(CodecError, match="declares more than 10,000 message types"):
        _pose_decoder(fds)


def test_ros2_schemas_chained_deep_or_recursive_are_refused() -> None:
    """A ros2msg chain of 1000 definitions and a type containing itself are refused; real definitions pass."""
    chain = "\n".join(["pkg/T0 a"] + [f"{'=' * 80}\nMSG: pkg/T{k}\npkg/T{k + 1} a" for k in range(1000)])
    with pytest.raises(CodecError, match="nests message-typed fields 100[12] deep"):
        check_ros2_schema(chain, "pkg/msg/Top")
    with pytest.raises(CodecError, match="a message type that contains itself"):
        check_ros2_schema("float64 x\nTop[] children", "pkg/msg/Top")
    from mcap.reader import make_reader

    with open(CORPUS / "ros2_cdr.mcap", "rb") as f:
        schemas = make_reader(f).get_summary().schemas.values()  # type: ignore[union-attr]
    assert {s.name for s in schemas} >= {"nav_msgs/msg/Odometry", "sensor_msgs/msg/Image"}
    for s in schemas:
        check_ros2_schema(s.data.decode(), s.name)


@pytest.mark.parametrize("path", sorted(CORPUS.glob("*.mcap")), ids=lambda p: p.name)
def test_the_seed_corpus_reads_whole(path: Path) -> None:
    """Every seed of the coverage-guided harness (zstd, lz4, uncompressed, PNG, raw, CDR) reads without damage."""
    assert path.stat().st_size < 16_000
    reader = RecordingReader(path)
    assert sum(1 for _ in reader.messages()) == reader.info.message_count > 0


def test_the_search_for_a_clean_chunk_is_bounded(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """200 chunks of 32 MiB of zeros (1 KB of zstd each, bad CRCs) after a broken record: recover decompresses
    only as many as its budget (64 x the file's size + MAX_CHUNK_BYTES) allows, not all 200 (6.4 GB)."""
    import slamreplay.recorder.recover as recover_module

    cobj = zstandard.ZstdCompressor(write_content_size=False).compressobj()
    frame = b"".join(cobj.compress(bytes(1 << 20)) for _ in range(32)) + cobj.flush()
    b = RecordBuilder()
    b.write(b"\x89MCAP0\r\n")
    Header(profile="", library="hostile").write(b)
    b.write(b"\x05" + struct.pack("<Q", 1 << 40))  # a Message record claiming a terabyte: the scan starts here
    for _ in range(200):
        Chunk(compression="zstd", data=frame, message_start_time=0, message_end_time=0, uncompressed_crc=1,
              uncompressed_size=32 << 20).write(b)
    src = tmp_path / "hostile.mcap"
    src.write_bytes(b.end())
    calls = []
    real = recover_module.decompress
    monkeypatch.setattr(recover_module, "decompress", lambda c, o: calls.append(o) or real(c, o))
    with pytest.raises(DamageError, match="holds no readable message"):
        recover_module.recover(src, tmp_path / "out.mcap")
    budget = recover_module.RESYNC_BYTES_PER_BYTE * src.stat().st_size + MAX_CHUNK_BYTES
    # each candidate costs its record (about 1 KB) plus the 32 MiB it claims: the budget (148 MB) pays for 4
    assert len(calls) == budget // (32 << 20) == 4


def test_a_chunk_of_a_million_tiny_records_is_refused() -> None:
    """1,000,001 empty records (9 MB, compressing to almost nothing) in one chunk: refused, not listed."""
    from slamreplay.recorder.codec.mcap_io import MAX_CHUNK_RECORDS, chunk_messages, chunk_records

    data = b"\x7f" + bytes(8)  # an unknown opcode with an empty body
    data *= MAX_CHUNK_RECORDS + 1
    for read in (chunk_messages, lambda d, o: list(chunk_records(d, o))):
        with pytest.raises(DamageError, match="Chunk record at byte 77 holds more than 1,000,000 records, above "
                                              "slamreplay's limit per chunk"):
            read(data, 77)


def test_metadata_json_nested_a_hundred_thousand_deep_is_refused(tmp_path: Path,
                                                                   capsys: pytest.CaptureFixture[str]) -> None:
    """A sensor model of 100,000 nested arrays in the metadata: inspect reports it in one line, no recursion."""
    from mcap.writer import Writer

    from slamreplay.api.cli.command import main
    from slamreplay.recorder.sensor_model import sensor_model_key
    from slamreplay.recorder.writer import METADATA_NAME

    msg = OdometryPose(1000, 0.0, 0.0, 0.0)
    path = tmp_path / "deep.mcap"
    with open(path, "wb") as f:
        w = Writer(f)
        w.start()
        w.add_metadata(METADATA_NAME, {"source": "{}", sensor_model_key(""): "[" * 100_000})
        sid = w.register_schema(schema_name(msg), "protobuf", schema_data(msg))
        cid = w.register_channel("/odom", "protobuf", sid)
        w.add_message(cid, 1000, encode(msg), 1000)
        w.finish()
    code = main(["inspect", str(path)])
    out, err = capsys.readouterr()
    assert code == 1 and err == "" and "health: corrupt" in out
    assert "  problem: the recording's sensor model nests 100,000 deep (at most 64): it is damaged" in out
    code = main(["run", str(path), "--pipeline", "odometry", "--out", str(tmp_path / "run"), "-q"])
    out, err = capsys.readouterr()
    assert code == 2 and err.count("\n") == 1 and "sensor model nests 100,000 deep" in err


def test_a_png_of_a_hundred_thousand_empty_chunks_is_refused() -> None:
    """Chunks are walked in Python for their CRCs: more than MAX_PNG_CHUNKS is refused after that many, quickly."""
    from slamreplay.recorder.codec.bounds import MAX_PNG_CHUNKS

    empty = struct.pack(">I4s", 0, b"tEXt") + struct.pack(">I", zlib.crc32(b"tEXt"))
    data = _huge_png()[:33] + empty * 100_000  # signature and IHDR (its claim is not reached), then the chunks
    t0 = time.perf_counter()
    with pytest.raises(CodecError, match=f"PNG data holds more than {MAX_PNG_CHUNKS:,} chunks"):
        decode_image_bytes(data, "png")
    assert time.perf_counter() - t0 < 2


def test_json_depth_skips_strings_and_stays_linear() -> None:
    """Brackets inside strings (escaped quotes too) do not count; 500,000 unterminated escapes take one pass."""
    from slamreplay.recorder.codec.bounds import json_depth

    assert json_depth('{"a": [1, {"b": "[[[["}]}') == 3
    assert json_depth('["a\\\\"]') == 1 and json_depth('"\\"[" ') == 0
    t0 = time.perf_counter()
    assert json_depth('"\\' * 500_000) == 0
    assert time.perf_counter() - t0 < 1
