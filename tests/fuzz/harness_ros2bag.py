"""Coverage-guided fuzzing (atheris, libFuzzer) of the ROS 2 bag importer (recorder/importers/ros2bag.py).

Contract: for any bag folder built from the fuzz input, ``plan_bag`` (what ``slamreplay inspect BAG``
prints) and ``import_ros2_bag`` (``slamreplay record ros2 BAG``) give a result or a ``RecorderError``
whose message is one line. Any other exception, a timeout or a memory blow-up is a finding. The bytes
reach rosbags only through slamreplay's own check (recorder/importers/ros2bag_check.py: the MCAP
storage walked by the bounded reader, metadata.yaml, the storage files, compressed storage), so an
input that passes it fuzzes rosbags' reading of checked bytes, and one that does not fuzzes the check.

The first byte of an input picks what is fuzzed; the rest is that part, the others come from small valid
template bags that ``write_bag`` makes at start-up (and rosbags' Writer re-writes compressed):

- 0: the text of ``metadata.yaml`` (beside the template's ``.mcap`` storage file);
- 1: the ``.db3`` file (sqlite3 storage), 2: the ``.mcap`` file (mcap storage), under the template's metadata;
- 3: one message: the next byte picks a topic of the template, the rest is its raw CDR, written with
  rosbags' Writer into a copy of the template (mcap storage) in place of that topic's messages. Byte-level
  mutation of a .db3 mostly gives "not a database"; this reaches the CDR decoding and the conversions;
- 4: the ``.mcap`` file alone in the folder, no metadata.yaml (as ``slamreplay inspect FILE.mcap`` reads it);
- 5: the ``.mcap`` file, zstd-compressed here, of a ``file``-compressed bag (decompressed by the check);
- 6: the ``.mcap`` file of a ``message``-compressed bag (each message's zstd frame checked).

    .venv/bin/python tests/fuzz/harness_ros2bag.py --seeds tests/fuzz/corpus/ros2bag   # rewrite the seeds
    nice -n 10 .venv/bin/python tests/fuzz/harness_ros2bag.py -max_total_time=600 -timeout=20 \\
        -rss_limit_mb=3072 -max_len=65536 -artifact_prefix=/tmp/fuzz-ros2bag/ /tmp/fuzz-ros2bag/corpus \\
        tests/fuzz/corpus/ros2bag
"""

from __future__ import annotations

import contextlib
import os
import shutil
import sys
import tempfile
from pathlib import Path

try:
    import atheris
except ImportError:  # replaying stored cases (tests/fuzz/test_harness_cases.py) needs no fuzzer
    atheris = None

with atheris.instrument_imports(include=["slamreplay.recorder", "rosbags"]) if atheris else contextlib.nullcontext():
    import zstandard
    from rosbags.highlevel import AnyReader
    from rosbags.rosbag2 import CompressionFormat, CompressionMode, StoragePlugin, Writer

    from slamreplay.recorder.errors import RecorderError
    from slamreplay.recorder.importers.ros2bag import import_ros2_bag, plan_bag
    from slamreplay.recorder.sim.ros2bag import write_bag

# tmpfs when there is one: every execution writes a bag and a recording
_DIR = Path(tempfile.mkdtemp(prefix="fuzz-ros2bag-", dir="/dev/shm" if os.path.isdir("/dev/shm") else None))
_BAG, _OUT = _DIR / "bag", _DIR / "out.mcap"
SECONDS = 0.2  # two odometry steps, one scan, one image of each kind: a template of tens of KB


def _template(storage: str) -> tuple[bytes, bytes]:
    """(metadata.yaml, storage file) of a small valid bag; the same bytes every time (seeded simulation)."""
    path = _DIR / f"template-{storage}"
    write_bag(path, storage, seconds=SECONDS)
    meta = (path / "metadata.yaml").read_bytes()
    store = next(p for p in path.iterdir() if p.name != "metadata.yaml")
    return meta, store.read_bytes()


_META_DB3, _DB3 = _template("sqlite3")
_META_MCAP, _MCAP = _template("mcap")


def _template_messages() -> list[tuple[str, str, str, str, list[tuple[int, bytes]]]]:
    """(topic, type, its .msg definition, its hash, [(bag time, raw CDR)]) of each topic of the mcap template."""
    out = []
    with AnyReader([_DIR / "template-mcap"]) as reader:
        for conn in sorted(reader.connections, key=lambda c: c.topic):
            msgs = [(ns, bytes(raw)) for _, ns, raw in reader.messages(connections=[conn])]
            out.append((conn.topic, conn.msgtype, conn.msgdef.data, conn.digest, msgs))
    return out


_TOPICS = _template_messages()


def _compressed_template(mode: CompressionMode) -> tuple[bytes, str, bytes]:
    """(metadata.yaml, storage file name, storage bytes) of the mcap template re-written with ``mode`` zstd
    compression; for ``file`` mode the storage bytes are the uncompressed MCAP (the harness compresses its input)."""
    path = _DIR / f"template-{mode.name.lower()}"
    writer = Writer(path, version=9, storage_plugin=StoragePlugin.MCAP)
    writer.set_compression(mode, CompressionFormat.ZSTD)
    with writer:
        for topic, msgtype, msgdef, rihs01, msgs in _TOPICS:
            conn = writer.add_connection(topic, msgtype, msgdef=msgdef, rihs01=rihs01)
            for ns, data in msgs:
                writer.write(conn, ns, data)
    store = next(p for p in path.iterdir() if p.name != "metadata.yaml")
    data = store.read_bytes()
    if mode == CompressionMode.FILE:
        data = zstandard.ZstdDecompressor().stream_reader(data, read_across_frames=True).read()
    return (path / "metadata.yaml").read_bytes(), store.name, data


_FILE_META, _FILE_NAME, _FILE_MCAP = _compressed_template(CompressionMode.FILE)
_MESSAGE_META, _MESSAGE_NAME, _MESSAGE_MCAP = _compressed_template(CompressionMode.MESSAGE)


_OURS = str(Path(str(sys.modules[RecorderError.__module__].__file__)).parents[1])  # the repository: our code


def _one_line(err: Exception) -> None:
    """A finding when one of our errors is not the promised single line, or relabels a bug of our own code:
    the importer turns rosbags' and sqlite's errors into RecorderError, which must not hide ours."""
    text = str(err)
    if not text or "\n" in text:
        raise AssertionError(f"{type(err).__name__} message is not one line: {text[:300]!r}")
    cause = err.__cause__
    if cause is not None and not isinstance(cause, RecorderError) and cause.__traceback__ is not None:
        tb = cause.__traceback__
        while tb.tb_next is not None:
            tb = tb.tb_next
        where = tb.tb_frame.f_code.co_filename
        if where.startswith(_OURS) and "/site-packages/" not in where:  # a venv inside the checkout is not ours
            raise AssertionError(f"RecorderError relabels {type(cause).__name__} raised in slamreplay at "
                                 f"{where}:{tb.tb_lineno}: {cause}") from cause


def _write_with_message(pick: int, raw: bytes) -> None:
    """The mcap template rewritten with ``raw`` as the only message of topic number ``pick``."""
    index = pick % len(_TOPICS)
    with Writer(_BAG, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        for i, (topic, msgtype, msgdef, rihs01, msgs) in enumerate(_TOPICS):
            conn = writer.add_connection(topic, msgtype, msgdef=msgdef, rihs01=rihs01)
            for ns, data in ([(msgs[0][0], raw)] if i == index else msgs):
                writer.write(conn, ns, data)


def build_bag(data: bytes) -> None:
    """The bag folder ``_BAG`` made from a fuzz input (see the module docstring)."""
    shutil.rmtree(_BAG, ignore_errors=True)
    mode, body = (data[0] % 7, data[1:]) if data else (0, b"")
    if mode == 3:
        _write_with_message(body[0] if body else 0, body[1:])
        return
    _BAG.mkdir()
    if mode == 4:
        (_BAG / "template-mcap.mcap").write_bytes(body)
    elif mode == 5:
        (_BAG / "metadata.yaml").write_bytes(_FILE_META)
        (_BAG / _FILE_NAME).write_bytes(zstandard.ZstdCompressor(level=1).compress(body))
    elif mode == 6:
        (_BAG / "metadata.yaml").write_bytes(_MESSAGE_META)
        (_BAG / _MESSAGE_NAME).write_bytes(body)
    elif mode == 1:
        (_BAG / "metadata.yaml").write_bytes(_META_DB3)
        (_BAG / "template-sqlite3.db3").write_bytes(body)
    else:
        (_BAG / "metadata.yaml").write_bytes(body if mode == 0 else _META_MCAP)
        (_BAG / "template-mcap.mcap").write_bytes(_MCAP if mode == 0 else body)


def test_one_input(data: bytes) -> None:
    """Plan and import the bag built from ``data``; only a plan, a recording or a one-line RecorderError."""
    build_bag(data)
    try:
        plan_bag(_BAG, ground_truth_frame="map")
    except RecorderError as err:
        _one_line(err)
    _OUT.unlink(missing_ok=True)
    try:
        import_ros2_bag(_BAG, _OUT)
    except RecorderError as err:
        _one_line(err)


def write_seeds(out: Path) -> None:
    """The seed corpus: each part of the templates, unchanged, prefixed by its mode byte."""
    out.mkdir(parents=True, exist_ok=True)
    (out / "metadata.yaml.in").write_bytes(b"\x00" + _META_MCAP)
    (out / "sqlite3.db3.in").write_bytes(b"\x01" + _DB3)
    (out / "mcap.mcap.in").write_bytes(b"\x02" + _MCAP)
    (out / "mcap-alone.mcap.in").write_bytes(b"\x04" + _MCAP)
    (out / "mcap-file-compressed.mcap.in").write_bytes(b"\x05" + _FILE_MCAP)
    (out / "mcap-message-compressed.mcap.in").write_bytes(b"\x06" + _MESSAGE_MCAP)
    for i, (topic, *_, msgs) in enumerate(_TOPICS):
        (out / f"message{topic.replace('/', '_')}.in").write_bytes(b"\x03" + bytes([i]) + msgs[0][1])


def main() -> None:
    """libFuzzer's command line (see the module docstring), or ``--seeds DIR`` to write the seed corpus."""
    if sys.argv[1:2] == ["--seeds"]:
        write_seeds(Path(sys.argv[2]))
        return
    atheris.Setup(sys.argv, test_one_input)
    atheris.Fuzz()


if __name__ == "__main__":
    main()
