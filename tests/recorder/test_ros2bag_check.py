"""A ROS 2 bag's bytes checked before rosbags reads them (recorder/importers/ros2bag_check.py), and whatever a
third-party parser raises as one BagError line naming the file: one test per kind of damage."""

from __future__ import annotations

import re
import shutil
import sqlite3
import struct
import zlib
from pathlib import Path

import pytest
import zstandard
from mcap.opcode import Opcode
from ros2bag_fixtures import write_bag
from rosbags.highlevel import AnyReader
from rosbags.rosbag2 import CompressionFormat, CompressionMode, ReaderError, StoragePlugin, Writer
from ruamel.yaml.error import YAMLError

from slamreplay.api.cli.command import main
from slamreplay.recorder.codec.mcap_check import check_mcap
from slamreplay.recorder.codec.mcap_io import McapFile
from slamreplay.recorder.errors import RecorderError
from slamreplay.recorder.importers import ros2bag_check
from slamreplay.recorder.importers.ros2bag import import_ros2_bag, open_bag, plan_bag
from slamreplay.recorder.importers.ros2bag_check import BagError, read_metadata, rosbags_error


@pytest.fixture(scope="module")
def bags(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """A 1 s bag of each storage (the MCAP one written by rosbags: one chunk, no CRCs) and the MCAP one re-written
    by the mcap library with CRCs and several chunks."""
    from tests.fuzz.mutate import _rewrite

    base = tmp_path_factory.mktemp("bags")
    out = {s: base / s for s in ("mcap", "sqlite3")}
    for storage, path in out.items():
        write_bag(path, storage, seconds=1.0)
    crc = base / "crc"
    shutil.copytree(out["mcap"], crc)
    f = next(crc.glob("*.mcap"))
    f.write_bytes(_rewrite(f.read_bytes()))
    out["crc"] = crc
    return out


def _copy(bag: Path, tmp_path: Path) -> tuple[Path, Path]:
    """A copy of ``bag`` and its storage file."""
    dest = tmp_path / "bag"
    shutil.copytree(bag, dest)
    return dest, next(p for p in dest.iterdir() if p.suffix in (".mcap", ".db3"))


def _records(path: Path) -> list[tuple[int, int, object]]:
    with McapFile(path) as f:
        return [(pos, opcode, rec) for pos, opcode, rec in f.records()]


def _first(path: Path, opcode: int) -> tuple[int, object]:
    return next((pos, rec) for pos, op, rec in _records(path) if op == opcode)


def _damaged(bag: Path, match: str) -> None:
    """plan_bag and import_ros2_bag both raise one BagError line matching ``match``."""
    with pytest.raises(BagError, match=match) as info:
        plan_bag(bag)
    assert "\n" not in str(info.value)
    with pytest.raises(BagError, match=match):
        import_ros2_bag(bag, bag.parent / "out.mcap")
    assert not (bag.parent / "out.mcap").exists()


def test_intact_bags_pass_the_check(bags: dict[str, Path]) -> None:
    """Every record of an intact bag's MCAP is checked, CRCs and indexes included, and the bag imports."""
    got = check_mcap(next(bags["crc"].glob("*.mcap")))
    assert got.chunks == 3 and got.messages == 40
    assert check_mcap(next(bags["mcap"].glob("*.mcap"))).messages == 40
    for bag in bags.values():
        assert plan_bag(bag).topics


def test_chunk_record_length_overflow(bags: dict[str, Path], tmp_path: Path) -> None:
    """A record inside a CRC-less chunk claiming 2**63-1 bytes: rosbags' skip_exact raised OverflowError (issue 37)."""
    bag, store = _copy(bags["mcap"], tmp_path)
    data = bytearray(store.read_bytes())
    at, chunk = _first(store, Opcode.CHUNK)
    assert chunk.compression == "" and chunk.uncompressed_crc == 0  # type: ignore[attr-defined]  # rosbags' chunks
    head = 9 + 8 + 8 + 8 + 4 + 4 + 8  # up to the records: times, size, CRC, compression "", records length
    struct.pack_into("<Q", data, at + head + 1, 2**63 - 1)  # the length of the first record inside the chunk
    store.write_bytes(bytes(data))
    _damaged(bag, r"Chunk record at byte \d+: the \w+ record at byte 0 of its content claims "
                  r"9,223,372,036,854,775,807 bytes")


def test_top_level_record_length(bags: dict[str, Path], tmp_path: Path) -> None:
    """A top-level record's length past the end of the file."""
    bag, store = _copy(bags["mcap"], tmp_path)
    data = bytearray(store.read_bytes())
    at, _ = _first(store, Opcode.MESSAGE_INDEX)
    struct.pack_into("<Q", data, at + 1, (1 << 64) - 1)
    store.write_bytes(bytes(data))
    _damaged(bag, rf"mcap\.mcap is damaged: MessageIndex record at byte {at} claims 18,446,744,073,709,551,615 bytes")


def test_chunk_index_points_elsewhere(bags: dict[str, Path], tmp_path: Path) -> None:
    """A ChunkIndex whose chunk offset is not where a chunk starts (rosbags would decompress what is there)."""
    bag, store = _copy(bags["mcap"], tmp_path)
    data = bytearray(store.read_bytes())
    at, index = _first(store, Opcode.CHUNK_INDEX)
    struct.pack_into("<Q", data, at + 9 + 16, index.chunk_start_offset + 9)  # type: ignore[attr-defined]
    store.write_bytes(bytes(data))
    _damaged(bag, r"a ChunkIndex (points at byte 52, where no Chunk record starts|puts channel \d+'s MessageIndex at "
                  r"byte \d+, outside the message indexes of its chunk \(bytes 45883\.\.)")


def test_chunk_index_disagrees_with_its_chunk(bags: dict[str, Path], tmp_path: Path) -> None:
    """A ChunkIndex's compressed size unlike its chunk's (rosbags reads that many bytes)."""
    bag, store = _copy(bags["mcap"], tmp_path)
    data = bytearray(store.read_bytes())
    at, index = _first(store, Opcode.CHUNK_INDEX)
    tail = at + 9 + 32 + 4 + 10 * len(index.message_index_offsets) + 8 + 4 + len(index.compression)  # type: ignore
    struct.pack_into("<Q", data, tail, 1 << 40)
    store.write_bytes(bytes(data))
    _damaged(bag, r"the ChunkIndex of the Chunk record at byte 43 gives its compressed size as 1,099,511,627,776")


def test_chunk_crc(bags: dict[str, Path], tmp_path: Path) -> None:
    """A chunk whose records fail its CRC."""
    bag, store = _copy(bags["crc"], tmp_path)
    data = bytearray(store.read_bytes())
    at, _ = _first(store, Opcode.CHUNK)
    data[at + 9 + 24] ^= 0xFF  # the stored CRC
    store.write_bytes(bytes(data))
    _damaged(bag, rf"Chunk record at byte {at} fails its CRC check")


def test_summary_crc(bags: dict[str, Path], tmp_path: Path) -> None:
    """A summary section whose bytes fail the Footer's CRC (a flipped bit in a Statistics count)."""
    bag, store = _copy(bags["crc"], tmp_path)
    data = bytearray(store.read_bytes())
    at, _ = _first(store, Opcode.STATISTICS)
    data[at + 9] ^= 1  # message count: framing intact, only the CRC tells
    store.write_bytes(bytes(data))
    _damaged(bag, r"the summary section \(bytes \d+\.\.\d+\) fails its CRC check")


def test_data_section_crc(bags: dict[str, Path], tmp_path: Path) -> None:
    """A data section whose bytes fail the DataEnd record's CRC (a bit in a MessageIndex's log time)."""
    bag, store = _copy(bags["crc"], tmp_path)
    data = bytearray(store.read_bytes())
    at, _ = _first(store, Opcode.MESSAGE_INDEX)
    data[at + 9 + 2 + 4] ^= 1
    store.write_bytes(bytes(data))
    _damaged(bag, r"the data section \(bytes 0\.\.\d+\) fails its CRC check")


def test_chunk_bomb(bags: dict[str, Path], tmp_path: Path) -> None:
    """A chunk claiming more uncompressed bytes than zstd can give: refused before it is decompressed."""
    bag, store = _copy(bags["mcap"], tmp_path)
    data = bytearray(store.read_bytes())
    at, _ = _first(store, Opcode.CHUNK)
    struct.pack_into("<Q", data, at + 9 + 16, 1 << 40)
    store.write_bytes(bytes(data))
    _damaged(bag, r"claims 1,099,511,627,776 bytes uncompressed, above slamreplay's limit of 134,217,728")


def test_truncated_and_duplicated(bags: dict[str, Path], tmp_path: Path) -> None:
    """A file cut short, and one with a record duplicated (every offset after it moves)."""
    bag, store = _copy(bags["mcap"], tmp_path)
    data = store.read_bytes()
    store.write_bytes(data[:len(data) // 2])
    _damaged(bag, r"mcap\.mcap is damaged: the file does not end with the MCAP magic: it is cut short")
    at, _ = _first(next(bags["mcap"].glob("*.mcap")), Opcode.MESSAGE_INDEX)
    length = 9 + struct.unpack_from("<Q", data, at + 1)[0]
    store.write_bytes(data[:at + length] + data[at:])
    _damaged(bag, r"mcap\.mcap is damaged: .*record at byte \d+ claims [\d,]+ bytes but only [\d,]+ follow it")


def test_storage_file_alone(bags: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """The .mcap alone (`inspect FILE.mcap`): checked too; the CLI prints the plan's error, no internal error."""
    _, store = _copy(bags["mcap"], tmp_path)
    data = bytearray(store.read_bytes())
    at, _ = _first(store, Opcode.MESSAGE_INDEX)
    struct.pack_into("<Q", data, at + 1, 2**63 - 1)
    store.write_bytes(bytes(data))
    with pytest.raises(BagError, match=r"mcap\.mcap is damaged: MessageIndex record at byte \d+ claims"):
        plan_bag(store)
    main(["inspect", str(store)])  # its exit code says what replay's reader finds; the plan's error is printed
    out = capsys.readouterr()
    assert "internal error" not in out.err and "Traceback" not in out.err
    assert re.search(r"`slamreplay record ros2` cannot import it: .*mcap\.mcap is damaged: MessageIndex", out.out)


# ---------------------------------------------------------------------------------------------- metadata.yaml


def _meta(bag: Path, old: str, new: str) -> None:
    meta = bag / "metadata.yaml"
    text = meta.read_text()
    assert old in text
    meta.write_text(text.replace(old, new, 1))


@pytest.mark.parametrize(("old", "new", "match"), [
    ("\n  message_count: 40\n", "\n  message_count: -1\n", r"message_count is -1, outside 0\.\.2\*\*63-1"),
    ("\n  message_count: 40\n", "\n  message_count: 1e400\n", r"message_count is float 'inf', not an integer"),
    ("\n  message_count: 40\n", "\n  message_count: ''\n", r"message_count is str '', not an integer"),
    ("  - message_count: 10", "  - message_count: [1]", r"topics_with_message_count\[0\]\.message_count is list"),
    ("version: 9", "version: 10", r"version 10 is not a rosbag2 metadata version"),
    ("storage_identifier: mcap", "storage_identifier: memory", r"storage_identifier 'memory' is not one"),
    ("custom_data: null", "custom_data: " + "[" * 40 + "]" * 40, r"nests deeper than 16 levels"),
    ("custom_data: null", "custom_data: &a [1]\n  ros2: *a", r"uses a YAML alias \(\*a\)"),
    ("compression_mode: ''", "compression_mode: file", r"compression_format '': rosbags decompresses zstd only"),
    ("rosbag2_bagfile_information:", "rosbag2_bagfile_information: {", r"is not valid YAML"),
])
def test_metadata_yaml(bags: dict[str, Path], tmp_path: Path, old: str, new: str, match: str) -> None:
    """Each value rosbags would take, or choke on, in metadata.yaml: refused, naming the file and the key."""
    bag, store = _copy(bags["mcap"], tmp_path)
    _meta(bag, old, new)
    with pytest.raises(BagError, match=match):
        read_metadata(bag / "metadata.yaml")
    assert plan_bag(bag).topics  # the one storage file is then read alone, as for another writer's metadata
    store.rename(bag / "other.mcap")
    (bag / "second.mcap").write_bytes(b"")
    with pytest.raises(BagError, match=match):  # two storage files: nothing to fall back on
        plan_bag(bag)


def test_metadata_not_utf8_and_too_large(bags: dict[str, Path], tmp_path: Path) -> None:
    """Bytes that are not UTF-8, and a metadata.yaml far larger than rosbag2 writes."""
    bag, _ = _copy(bags["sqlite3"], tmp_path)
    meta = bag / "metadata.yaml"
    meta.write_bytes(b"\xff\xfe" + meta.read_bytes())
    with pytest.raises(BagError, match=r"metadata\.yaml is not valid YAML \('utf-8' codec can't decode"):
        read_metadata(meta)
    with open(meta, "wb") as f:
        f.truncate(ros2bag_check.MAX_METADATA_BYTES + 1)
    with pytest.raises(BagError, match=r"metadata\.yaml is 16,777,217 bytes, above the 16,777,216"):
        read_metadata(meta)


def test_storage_file_not_regular(bags: dict[str, Path], tmp_path: Path) -> None:
    """metadata.yaml naming a FIFO (rosbags would block opening it), a folder, or a file that is not there."""
    import os

    bag, store = _copy(bags["mcap"], tmp_path)
    _meta(bag, f"- {store.name}", "- fifo.mcap")
    os.mkfifo(bag / "fifo.mcap")
    with pytest.raises(BagError, match=r"names storage file fifo\.mcap, which is not a regular file"):
        plan_bag(bag)
    _meta(bag, "- fifo.mcap", "- gone.mcap")
    (bag / "fifo.mcap").unlink()
    store.rename(bag / "other.db3")  # still one storage file for the fallback, which is a .db3 of MCAP bytes
    with pytest.raises(BagError, match=r"other\.db3 is not a sqlite3 database"):
        plan_bag(bag)


# ---------------------------------------------------------------------------------------------- sqlite3, compression


def test_sqlite_header_and_damaged_page(bags: dict[str, Path], tmp_path: Path) -> None:
    """A .db3 that is not a database, and one whose message pages are damaged after it opened."""
    bag, store = _copy(bags["sqlite3"], tmp_path)
    data = bytearray(store.read_bytes())
    store.write_bytes(b"\x00" * 16 + data[16:])
    _damaged(bag, r"\.db3 is not a sqlite3 database \(it starts with b'\\x00")
    with sqlite3.connect(next(bags["sqlite3"].glob("*.db3"))) as con:
        (page,) = con.execute("PRAGMA page_size").fetchone()
    data[len(data) - page:] = b"\xff" * page  # the last page: message rows
    store.write_bytes(bytes(data))
    with pytest.raises(RecorderError, match=r"storage is damaged after message \d+ \(|cannot be read as a ROS 2 bag|"
                                            r"message \d+ on /\w+ \(\w+/msg/\w+\) is damaged \("):
        import_ros2_bag(bag, tmp_path / "out.mcap")


def _compressed(src: Path, dest: Path, mode: CompressionMode, storage: StoragePlugin) -> Path:
    """``src`` re-written by rosbags with ``mode`` zstd compression."""
    writer = Writer(dest, version=9, storage_plugin=storage)
    writer.set_compression(mode, CompressionFormat.ZSTD)
    with AnyReader([src]) as reader, writer:
        conns = {c.id: writer.add_connection(c.topic, c.msgtype, msgdef=c.msgdef.data, rihs01=c.digest)
                 for c in reader.connections}
        for c, t, raw in reader.messages():
            writer.write(conns[c.id], t, raw)
    return dest


@pytest.mark.parametrize("storage", [StoragePlugin.MCAP, StoragePlugin.SQLITE3])
def test_message_compressed_bomb(bags: dict[str, Path], tmp_path: Path, storage: StoragePlugin,
                                 monkeypatch: pytest.MonkeyPatch) -> None:
    """A message-compressed bag imports; one whose message decompresses past MAX_MESSAGE_BYTES is refused first."""
    src = bags["mcap" if storage == StoragePlugin.MCAP else "sqlite3"]
    bag = _compressed(src, tmp_path / "bag", CompressionMode.MESSAGE, storage)
    assert import_ros2_bag(bag, tmp_path / "ok.mcap").messages > 0
    monkeypatch.setattr(ros2bag_check, "MAX_MESSAGE_BYTES", 100)  # every message then decompresses past it
    with pytest.raises(BagError, match=r"is damaged: the zstd-compressed message .* more than the 100 "):
        plan_bag(bag)


def test_file_compressed(bags: dict[str, Path], tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A file-compressed bag is decompressed here (then checked and read); a bomb past the free space and a damaged
    stream are refused; nothing is left in the temporary folder."""
    monkeypatch.setenv("TMPDIR", str(tmp_path / "tmp"))
    (tmp_path / "tmp").mkdir()
    import tempfile

    monkeypatch.setattr(tempfile, "tempdir", None)
    bag = _compressed(bags["mcap"], tmp_path / "bag", CompressionMode.FILE, StoragePlugin.MCAP)
    with open_bag(bag) as opened:
        assert opened.storage == "mcap" and opened.reader.connections
    assert import_ros2_bag(bag, tmp_path / "ok.mcap").messages > 0
    assert not list((tmp_path / "tmp").iterdir())
    margin = ros2bag_check._FREE_MARGIN
    monkeypatch.setattr(ros2bag_check, "_FREE_MARGIN", 1 << 62)
    with pytest.raises(BagError, match=r"decompresses to more than the 0 bytes free in .*: a decompression bomb"):
        plan_bag(bag)
    monkeypatch.setattr(ros2bag_check, "_FREE_MARGIN", margin)
    store = next(bag.glob("*.zstd"))
    store.write_bytes(store.read_bytes()[:-40] + b"\x00" * 40)
    with pytest.raises(BagError, match=r"\.mcap\.zstd does not decompress \(zstd: |\.mcap is damaged"):
        plan_bag(bag)
    assert not list((tmp_path / "tmp").iterdir())


# ---------------------------------------------------------------------------------------------- what rosbags raises


@pytest.mark.parametrize("err", [
    OverflowError("Python int too large to convert to C ssize_t"), MemoryError(), struct.error("unpack requires"),
    KeyError("ros2idlx"), IndexError("list index out of range"), UnicodeDecodeError("utf-8", b"\xff", 0, 1, "bad"),
    sqlite3.DatabaseError("database disk image is malformed"), ReaderError("Chunk checksum mismatch.\nmore"),
    YAMLError("while parsing"), zstandard.ZstdError("Data corruption detected"), zlib.error("bad"), ValueError(""),
    RecursionError("maximum recursion depth exceeded"),
])
def test_any_rosbags_error_is_one_line(bags: dict[str, Path], err: Exception) -> None:
    """Whatever rosbags (or what it calls) raises, while opening or while iterating, is one BagError line naming
    the bag; an error of no text is named by its type."""
    line = str(rosbags_error(err, "/x/bag cannot be read as a ROS 2 bag"))
    assert "\n" not in line and line.startswith("/x/bag cannot be read as a ROS 2 bag (")
    assert type(err).__name__ in line or str(err).splitlines()[0] in line

    class Raising:
        def messages(self, connections: object) -> object:
            yield from ()
            raise err

        def close(self) -> None:
            raise err

    with open_bag(bags["mcap"]) as bag:
        real, bag.reader = bag.reader, Raising()
        with pytest.raises(BagError, match=r"mcap: the bag's storage is damaged after message 0 \(") as info:
            list(bag.messages([]))
        assert info.value.__cause__ is err
    real.close()


def test_signalling_nan_range_is_no_reading() -> None:
    """A LaserScan range whose damaged bytes are a signalling NaN: read as no reading, no RuntimeWarning on stderr
    (found by harness_ros2bag.py's file-compressed mode)."""
    import warnings
    from types import SimpleNamespace

    import numpy as np

    from slamreplay.recorder.importers.poles import PoleConfig
    from slamreplay.recorder.importers.ros2bag import poles_scan

    ranges = np.full(90, 5.0, dtype=np.float32)
    ranges[10:20] = np.frombuffer(struct.pack("<I", 0x7FA00000) * 10, dtype=np.float32)  # signalling NaNs
    scan = SimpleNamespace(ranges=ranges, angle_min=-1.0, angle_increment=0.02, range_min=0.1, range_max=30.0)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        got = poles_scan(1, scan, PoleConfig(), (0.0, 0.0, 0.0))
    assert np.all(np.isfinite(got.ranges_m))


@pytest.mark.parametrize(("old", "new"), [
    ("storage_identifier: mcap", "storage_identifier: sqlite3"),
    ("compression_format: ''\n  compression_mode: ''", "compression_format: zstd\n  compression_mode: file"),
])
def test_metadata_wrong_about_its_storage(bags: dict[str, Path], tmp_path: Path, old: str, new: str) -> None:
    """A metadata.yaml wrong about its one storage file (its storage, a compression it does not have): the file is
    read alone, as it is, as for a metadata.yaml rosbags cannot read; a damaged file read as itself is refused."""
    bag, store = _copy(bags["mcap"], tmp_path)
    _meta(bag, old, new)
    assert plan_bag(bag).storage == "mcap"
    store.write_bytes(store.read_bytes()[:-100])
    with pytest.raises(BagError, match=r"mcap\.mcap is damaged: the file does not end with the MCAP magic"):
        plan_bag(bag)
