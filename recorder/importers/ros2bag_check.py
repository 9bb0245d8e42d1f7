"""A ROS 2 bag's bytes checked before ``rosbags`` reads them, and what rosbags raises as one line naming the file.

rosbags trusts what it reads. From ``metadata.yaml`` (ruamel): aliases, which it expands as it walks
the topics (a billion laughs), any nesting, counts of any type (a string, a list, 1e400), and the
storage files it names, opened whatever they are (a FIFO blocks forever). From the MCAP storage:
every length and offset (``OverflowError``, ``MemoryError``; :mod:`slamreplay.recorder.codec.mcap_check`).
Compressed bags: a ``file``-compressed storage file is decompressed into a temporary folder with no
bound on its size, then read unchecked; a ``message``-compressed message is decompressed with no
bound either. So before rosbags opens a bag, :func:`checked_bag`:

- reads ``metadata.yaml`` (at most MAX_METADATA_BYTES, UTF-8, no alias, nesting at most MAX_YAML_DEPTH)
  and checks every key rosbags reads: its type, and counts and times within 0..2**63-1;
- checks that each storage file it names is a regular file of the bag's folder;
- checks each storage file: MCAP by :func:`~slamreplay.recorder.codec.mcap_check.check_mcap` (every
  record, chunk, CRC and index), sqlite3 by its header (sqlite reports damage found later itself:
  :class:`BagError` via :func:`rosbags_error`); every message of a ``message``-compressed bag
  decompresses within MAX_MESSAGE_BYTES; a ``file``-compressed bag is decompressed here, as a
  stream, into a temporary folder (never past the space free there), checked, and that folder is
  what rosbags opens.

A bag that passes can still hold damage rosbags finds (a sqlite page, a CDR message): every call
into rosbags is wrapped, and whatever it raises becomes a :class:`BagError` (:func:`rosbags_error`).
"""

from __future__ import annotations

import io
import json
import shutil
import sqlite3
import stat
import tempfile
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path, PurePath
from typing import Any, Final

import zstandard

from slamreplay.recorder.codec.mcap_check import check_mcap
from slamreplay.recorder.codec.mcap_io import MAX_CHUNK_BYTES, zstd_bounded
from slamreplay.recorder.errors import RecorderError

MAX_METADATA_BYTES: Final = 16 << 20  # rosbag2 writes ~300 bytes per topic and per file
MAX_YAML_DEPTH: Final = 16  # rosbag2's metadata nests 5 deep (topics, topic_metadata, QoS profiles, durations)
MAX_COUNT: Final = 2**63 - 1  # counts and times are int64 in rosbag2
MAX_MESSAGE_BYTES: Final = MAX_CHUNK_BYTES  # a compressed message decompresses to no more than a chunk may hold
STORAGES: Final = {"mcap": ".mcap", "sqlite3": ".db3"}
SQLITE_MAGIC: Final = b"SQLite format 3\x00"
_PIECE = 1 << 20
_FREE_MARGIN = 1 << 30  # a file-compressed bag is decompressed leaving this much free in the temporary folder
_DAMAGED = "re-record the bag or copy it again"


class BagError(RecorderError):
    """A ROS 2 bag that cannot be read: one line naming the file, what is wrong and what to do."""


@dataclass
class CheckedBag:
    """What rosbags opens (a folder or a storage file), checked: its storage and a lone storage file to read
    alone when rosbags cannot read the folder (None: none)."""

    path: Path
    storage: str
    fallback: Path | None = None
    temp: tempfile.TemporaryDirectory[str] | None = None  # the decompressed copy of a file-compressed bag

    def cleanup(self) -> None:
        if self.temp is not None:
            self.temp.cleanup()
            self.temp = None


def rosbags_error(err: BaseException, prefix: str,
                  hint: str = "check that it is a complete rosbag2 folder, .db3 or .mcap (re-record or copy it "
                              "again)") -> BagError:
    """``err`` (rosbags', sqlite's, zstd's, YAML's: any type) as one line: ``prefix (what err says); hint``."""
    if isinstance(err, BagError):
        return err
    text = (str(err).strip().splitlines() or [""])[0][:300]
    if not text or isinstance(err, MemoryError | OverflowError | RecursionError):
        text = f"{type(err).__name__}: {text}" if text else type(err).__name__
    return BagError(f"{prefix} ({text}); {hint}")


def checked_bag(path: Path) -> CheckedBag:
    """The bag at ``path`` (a folder, a ``.db3`` or ``.mcap`` file), every byte rosbags will read checked.

    Raises
    ------
    BagError : ``path`` is missing or no bag, its metadata.yaml or a storage file is damaged (naming it).
    """
    if not path.exists():
        raise BagError(f"{path} does not exist: pass a ROS 2 bag folder, or its .db3 or .mcap file")
    if not path.is_dir():
        storage = next((s for s, suffix in STORAGES.items() if path.suffix == suffix), None)
        if storage is None:
            raise BagError(f"{path} is not a ROS 2 bag: expected a bag folder, a .db3 or a .mcap file")
        check_storage(path, storage)
        return CheckedBag(path, storage)
    files = sorted(p for suffix in STORAGES.values() for p in path.glob(f"*{suffix}"))
    lone = files[0] if len(files) == 1 else None
    meta = path / "metadata.yaml"
    if not meta.exists():
        if lone is None:
            what = "no .db3 or .mcap file" if not files else f"{len(files)} storage files but no metadata.yaml"
            raise BagError(f"{path} is not a ROS 2 bag: it holds no metadata.yaml and {what}")
        return _alone(lone)
    failed_as_itself = False  # the one storage file failed its check as the storage its name says
    try:
        info = read_metadata(meta)
        paths = [path / PurePath(p).name for p in info["relative_file_paths"]]  # as rosbags joins them
        for p in paths:
            _regular(p, f"{meta} names storage file {p.name}, which")
        storage, mode = info["storage_identifier"], info["compression_mode"]
        if mode == "file":
            return _decompressed(info, paths)
        for p in paths:
            try:
                check_storage(p, storage, message_compressed=mode == "message")
            except BagError:
                failed_as_itself = p == lone and p.suffix == STORAGES[storage]
                raise
    except BagError:
        if lone is None or failed_as_itself:
            raise
        return _alone(lone)  # a metadata.yaml of another writer (or hand-written): its one storage file alone
    return CheckedBag(path, storage, lone)


def _alone(file: Path) -> CheckedBag:
    storage = "sqlite3" if file.suffix == ".db3" else "mcap"
    check_storage(file, storage)
    return CheckedBag(file, storage)


def _regular(path: Path, what: str) -> None:
    try:
        mode = path.stat().st_mode
    except OSError as err:
        raise BagError(f"{what} cannot be read ({err.strerror}); {_DAMAGED}") from err
    if not stat.S_ISREG(mode):
        raise BagError(f"{what} is not a regular file (a folder, a pipe or a device): rosbags would block or fail "
                       f"on it")


def check_storage(path: Path, storage: str, *, message_compressed: bool = False) -> None:
    """BagError when the storage file ``path`` (``mcap`` or ``sqlite3``) is damaged where rosbags would trust it."""
    _regular(path, str(path))
    try:
        if storage == "mcap":
            check_mcap(path, each_message=_compressed_message() if message_compressed else None)
            return
        with open(path, "rb") as f:
            head = f.read(len(SQLITE_MAGIC))
        if head != SQLITE_MAGIC:
            raise BagError(f"{path} is not a sqlite3 database (it starts with {head[:16]!r}); {_DAMAGED}")
        if message_compressed:
            _sqlite_messages(path)
    except RecorderError as err:
        if isinstance(err, BagError):
            raise
        raise BagError(f"{path} is damaged: {err}; {_DAMAGED}") from err


def _compressed_message() -> Callable[[bytes, str], None]:
    def check(data: bytes, where: str) -> None:
        zstd_bounded(data, MAX_MESSAGE_BYTES, f"the zstd-compressed message {where}")
    return check


def _sqlite_messages(path: Path) -> None:
    """Every message of a message-compressed sqlite3 bag decompresses within MAX_MESSAGE_BYTES."""
    check = _compressed_message()
    try:
        con = sqlite3.connect(f"{path.resolve().as_uri()}?immutable=1&mode=ro", uri=True)
        try:
            for row_id, data in con.execute("SELECT id, data FROM messages"):
                check(bytes(data) if isinstance(data, bytes | memoryview) else b"", f"of row {row_id}")
        finally:
            con.close()
    except sqlite3.Error as err:
        raise rosbags_error(err, f"{path} is a damaged sqlite3 database", _DAMAGED) from err


def _decompressed(info: dict[str, Any], paths: list[Path]) -> CheckedBag:
    """A file-compressed bag decompressed into a temporary folder, as a stream and within the space free there,
    with a metadata.yaml that says it is not compressed; its storage files checked."""
    temp = tempfile.TemporaryDirectory(prefix="slamreplay-bag-")
    try:
        folder = Path(temp.name) / "bag"
        folder.mkdir()
        names = []
        for p in paths:
            out = folder / p.stem  # rosbags' name: bag_0.mcap.zstd -> bag_0.mcap
            if out.exists():
                raise BagError(f"{p.parent / 'metadata.yaml'} lists storage files that decompress to one name "
                               f"({out.name}) twice: it is damaged")
            _unzstd(p, out)
            check_storage(out, info["storage_identifier"])
            names.append(out.name)
        # YAML is a superset of JSON: rosbags reads this metadata.yaml as it reads rosbag2's
        (folder / "metadata.yaml").write_text(json.dumps({"rosbag2_bagfile_information": {
            **info, "compression_mode": "", "compression_format": "", "relative_file_paths": names,
            "files": []}}))
    except BaseException:
        temp.cleanup()
        raise
    return CheckedBag(folder, info["storage_identifier"], None, temp)


def _unzstd(src: Path, out: Path) -> None:
    limit = max(0, shutil.disk_usage(out.parent).free - _FREE_MARGIN)
    written = 0
    try:
        with open(src, "rb") as f, open(out, "xb") as w:
            reader = zstandard.ZstdDecompressor().stream_reader(f, read_across_frames=True)
            while piece := reader.read(_PIECE):
                written += len(piece)
                if written > limit:
                    raise BagError(f"{src} decompresses to more than the {limit:,} bytes free in {out.parent} "
                                   f"(leaving {_FREE_MARGIN >> 30} GiB): a decompression bomb, or decompress it "
                                   f"where there is room")
                w.write(piece)
    except zstandard.ZstdError as err:
        raise BagError(f"{src} does not decompress (zstd: {err}); {_DAMAGED}") from err
    except OSError as err:  # the temporary folder: no space left, or not writable
        raise BagError(f"{src} cannot be decompressed into {out.parent} ({err.strerror}); free space there or set "
                       f"TMPDIR") from err


# ------------------------------------------------------------------------------------------------
# metadata.yaml


def read_metadata(path: Path) -> dict[str, Any]:
    """``rosbag2_bagfile_information`` of ``metadata.yaml``, with every key rosbags reads checked; BagError
    naming the file and the key otherwise. ``compression_mode`` comes back as ``""``, ``file`` or ``message``."""
    from ruamel.yaml import YAML
    from ruamel.yaml.error import YAMLError
    from ruamel.yaml.events import AliasEvent, CollectionEndEvent, CollectionStartEvent

    _regular(path, str(path))
    if (size := path.stat().st_size) > MAX_METADATA_BYTES:
        raise BagError(f"{path} is {size:,} bytes, above the {MAX_METADATA_BYTES:,} a rosbag2 metadata.yaml "
                       f"takes: it is damaged or not a bag's")
    try:
        text = path.read_bytes().decode("utf-8")
        depth = 0
        for event in YAML(typ="safe", pure=True).parse(io.StringIO(text)):  # events: nothing built yet
            if isinstance(event, AliasEvent):
                raise BagError(f"{path} uses a YAML alias (*{event.anchor}), which rosbag2 never writes: it is "
                               f"damaged or not a bag's")
            depth += isinstance(event, CollectionStartEvent) - isinstance(event, CollectionEndEvent)
            if depth > MAX_YAML_DEPTH:
                raise BagError(f"{path} nests deeper than {MAX_YAML_DEPTH} levels, which rosbag2 never writes: it is "
                               f"damaged or not a bag's")
        doc = YAML(typ="safe", pure=True).load(text)
    except (UnicodeDecodeError, YAMLError) as err:
        raise BagError(f"{path} is not valid YAML ({(str(err).splitlines() or [''])[0][:200]}); {_DAMAGED}") from err
    if not isinstance(doc, dict):
        raise BagError(f"{path} holds a YAML {type(doc).__name__}, not a rosbag2 metadata mapping; {_DAMAGED}")
    info = _get(path, doc, "rosbag2_bagfile_information", dict)
    version = _get(path, info, "version", int)
    if not 1 <= version <= 9:
        raise BagError(f"{path}: version {version} is not a rosbag2 metadata version rosbags reads (1 to 9)")
    storage = _get(path, info, "storage_identifier", str)
    if storage not in STORAGES:
        raise BagError(f"{path}: storage_identifier {storage[:40]!r} is not one rosbags reads (mcap, sqlite3)")
    files = _get(path, info, "relative_file_paths", list)
    if not files or not all(isinstance(f, str) and PurePath(f).name for f in files):
        raise BagError(f"{path}: relative_file_paths must list the storage files' names, got {str(files)[:80]}")
    _count(path, info, "message_count")
    _count(path, _get(path, info, "duration", dict), "nanoseconds", "duration.")
    _count(path, _get(path, info, "starting_time", dict), "nanoseconds_since_epoch", "starting_time.")
    for i, topic in enumerate(_get(path, info, "topics_with_message_count", list)):
        where = f"topics_with_message_count[{i}]."
        if not isinstance(topic, dict):
            raise BagError(f"{path}: {where[:-1]} is {type(topic).__name__}, not a mapping")
        _count(path, topic, "message_count", where)
        tm = _get(path, topic, "topic_metadata", dict, where)
        for key in ("name", "type", "serialization_format"):
            _get(path, tm, key, str, f"{where}topic_metadata.")
    if not isinstance(info.get("files", []), list):
        raise BagError(f"{path}: files is {type(info['files']).__name__}, not a list")
    mode = info.get("compression_mode") or ""
    fmt = info.get("compression_format") or ""
    if not isinstance(mode, str) or mode.lower() not in ("", "none", "file", "message"):
        raise BagError(f"{path}: compression_mode {str(mode)[:40]!r} is not one of none, file, message")
    mode = "" if mode.lower() == "none" else mode.lower()
    if mode and fmt != "zstd":
        raise BagError(f"{path}: compression_format {str(fmt)[:40]!r}: rosbags decompresses zstd only")
    return {**info, "compression_mode": mode}


def _get(path: Path, d: dict[str, Any], key: str, kind: type, where: str = "") -> Any:
    if key not in d:
        raise BagError(f"{path} lacks {where}{key}, which rosbags needs: it is damaged or not a bag's")
    value = d[key]
    if not isinstance(value, kind) or isinstance(value, bool):
        raise BagError(f"{path}: {where}{key} is {type(value).__name__} {str(value)[:40]!r}, not "
                       f"{'an integer' if kind is int else kind.__name__}")
    return value


def _count(path: Path, d: dict[str, Any], key: str, where: str = "") -> int:
    value: int = _get(path, d, key, int, where)
    if not 0 <= value <= MAX_COUNT:
        raise BagError(f"{path}: {where}{key} is {value}, outside 0..2**63-1: it is damaged")
    return value

