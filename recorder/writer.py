"""`Recorder`: writes messages to an MCAP recording, safely.

- Refuses to overwrite: neither ``FILE`` nor ``FILE.partial`` may exist.
- Writes to ``FILE.partial`` and renames it to ``FILE`` only on a clean close, so a file
  named ``FILE`` is always complete. When the ``with`` block raises, the data written so far
  is finished as a valid MCAP but kept as ``FILE.partial``: nothing looks whole that is not.
- zstd chunks, chunk CRCs on, explicit ``log_time`` and ``publish_time`` on every message
  (never the wall clock), and an MCAP metadata record ``slamreplay.recording``.
"""

from __future__ import annotations

import errno
import json
import os
from collections.abc import Mapping
from pathlib import Path
from types import TracebackType
from typing import IO, Any

from mcap.writer import CompressionType, Writer

from slamreplay.recorder import codec
from slamreplay.recorder.errors import RecorderError
from slamreplay.recorder.messages import TOPIC_TYPES, Message
from slamreplay.recorder.sensor_model import SensorModel, sensor_model_key
from slamreplay.recorder.version import version

METADATA_NAME = "slamreplay.recording"
# A key of a recording's ``source``: true when its /ground_truth topics hold an estimate from the same measurements
# (a batch optimum: Victoria Park), not the truth. A consistent filter's NEES against such a reference has 0 as
# the lower end of its band (the pipelines draw it so).
GROUND_TRUTH_IS_ESTIMATE = "ground_truth_is_estimate"
CHUNK_SIZE = 1 << 20


def partial_path(path: Path) -> Path:
    """Where a recording is written until it is closed cleanly."""
    return path.with_name(path.name + ".partial")


def refuse_existing(path: Path) -> None:
    """RecorderError when ``path`` or its ``.partial`` exists: a recording is never overwritten.

    Importers that read for minutes call it first; `Recorder` checks again when it is made.
    """
    for p in (path, partial_path(path)):
        if p.exists():
            raise RecorderError(f"{p} already exists; slamreplay never overwrites a recording: choose another --out "
                                f"or delete it")


class Recorder:
    """Write slamreplay messages to an MCAP file.

    Parameters
    ----------
    path : where the recording goes; must not exist yet (nor ``path.partial``).
    source : what produced the data, e.g. ``{"simulator": "sim-landmarks"}`` or
        ``{"importer": "mrclam", "dataset": "MRCLAM Dataset6", "robot": 1}``.
    seed : the seed of a simulator, if any.
    parameters : the generating parameters (JSON-serializable).
    robot : a description of the robot and its sensors (JSON-serializable).
    sensor_model : the sensors' noise and limits (`slamreplay.recorder.sensor_model.SensorModel`); pipelines
        use it where the user sets nothing (see `slamreplay inspect`). Several robots in one
        recording: a mapping of each robot's topic namespace (``/robot1``) to its model.

    Examples
    --------
    >>> with Recorder(Path("run.mcap"), source={"simulator": "mine"}) as rec:  # doctest: +SKIP
    ...     rec.write("/odom", OdometryPose(0, 0.0, 0.0, 0.0))
    """

    def __init__(self, path: str | Path, *, source: Mapping[str, Any], seed: int | None = None,
                 parameters: Mapping[str, Any] | None = None, robot: Mapping[str, Any] | None = None,
                 sensor_model: SensorModel | Mapping[str, SensorModel] | None = None) -> None:
        self.path = Path(path)
        self.partial = partial_path(self.path)
        refuse_existing(self.path)
        if not self.path.parent.is_dir():
            raise RecorderError(f"directory {self.path.parent} does not exist: create it first")
        try:
            self._metadata = {
                "source": json.dumps(dict(source), sort_keys=True),
                "seed": "" if seed is None else str(int(seed)),
                "parameters": json.dumps(dict(parameters or {}), sort_keys=True),
                "robot": json.dumps(dict(robot or {}), sort_keys=True),
                "slamreplay_version": version(),
            }
            models = {"": sensor_model} if isinstance(sensor_model, SensorModel) else dict(sensor_model or {})
            for namespace, model in models.items():
                if not isinstance(model, SensorModel):
                    raise RecorderError(f"sensor_model must be a SensorModel or a mapping of topic namespaces to "
                                        f"SensorModels, got {type(model).__name__}")
                self._metadata[sensor_model_key(namespace)] = model.to_json()
        except TypeError as err:
            raise RecorderError(f"source, parameters and robot must be JSON-serializable: {err}") from err
        self._file: IO[bytes] | None = None
        self._writer: Writer | None = None
        self._channels: dict[str, tuple[int, str]] = {}
        self._schemas: dict[str, int] = {}
        self._sequence: dict[str, int] = {}
        self._failed = False  # a write failed: the file is not finished, it stays FILE.partial
        self.message_count = 0

    def __enter__(self) -> Recorder:
        self.open()
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.close(keep_partial=exc_type is not None)

    def open(self) -> None:
        """Start writing to ``path.partial`` (done by ``with``)."""
        if self._writer is not None:
            raise RecorderError("recorder is already open")
        try:
            self._file = open(self.partial, "xb")  # noqa: SIM115 -- closed in close()
        except FileExistsError as err:
            raise RecorderError(f"{self.partial} already exists; delete it or choose another --out") from err
        self._writer = Writer(self._file, chunk_size=CHUNK_SIZE, compression=CompressionType.ZSTD,
                              enable_crcs=True, enable_data_crcs=False)
        self._writer.start(profile="", library=f"slamreplay/{version()}")
        self._writer.add_metadata(METADATA_NAME, self._metadata)
        # on disk now: a process killed before the first chunk leaves a .partial that says what it was
        # (header and metadata, no message), not an empty file
        self._file.flush()

    def write(self, topic: str, msg: Message, *, log_time_ns: int | None = None,
              publish_time_ns: int | None = None, encoded: tuple[bytes, bytes] | None = None) -> None:
        """Append one message.

        ``log_time_ns`` (the replay clock) defaults to the message's ``stamp_ns``;
        ``publish_time_ns`` defaults to ``log_time_ns``. Both are always written explicitly.
        A topic keeps the schema of its first message. ``encoded``: (schema data, bytes) of ``msg`` as received in
        the protobuf schema slamreplay writes it with, kept as they came (``record live``) instead of re-encoded.
        """
        if self._writer is None:
            raise RecorderError("recorder is not open: use it as `with Recorder(...) as rec:`")
        expected = TOPIC_TYPES.get(topic)
        if expected is not None and not isinstance(msg, expected):
            raise RecorderError(f"topic {topic} carries {expected.__name__}, got {type(msg).__name__}")
        log_time = msg.stamp_ns if log_time_ns is None else int(log_time_ns)
        publish_time = log_time if publish_time_ns is None else int(publish_time_ns)
        if log_time < 0 or publish_time < 0:
            raise RecorderError(f"{topic}: log_time and publish_time must be >= 0 ns")
        name = codec.schema_name(msg)
        channel = self._channels.get(topic)
        if channel is None:
            schema_id = self._schemas.get(name)
            if schema_id is None:
                data = encoded[0] if encoded is not None else codec.schema_data(msg)
                schema_id = self._writer.register_schema(name, "protobuf", data)
                self._schemas[name] = schema_id
            channel = (self._writer.register_channel(topic, "protobuf", schema_id), name)
            self._channels[topic] = channel
        elif channel[1] != name:
            raise RecorderError(f"topic {topic} has schema {channel[1]}; cannot write a {name} to it")
        seq = self._sequence.get(topic, 0)
        self._sequence[topic] = seq + 1
        try:
            data = encoded[1] if encoded is not None else codec.encode(msg)
            self._writer.add_message(channel[0], log_time, data, publish_time, seq)
        except OSError as err:  # a full disk, a quota, an I/O error: the file holds what was flushed before
            self._failed = True
            raise self._write_error(err) from err
        self.message_count += 1

    def flush(self) -> None:
        """End the chunk in progress and hand the file's bytes to the OS: a process killed later (kill -9) leaves a
        ``.partial`` holding every message written before (``record live`` calls it every second)."""
        if self._writer is None:
            raise RecorderError("recorder is not open: use it as `with Recorder(...) as rec:`")
        try:
            self._writer.flush()  # type: ignore[no-untyped-call]  # unannotated in mcap (since 1.5)
        except OSError as err:
            self._failed = True
            raise self._write_error(err) from err

    def add_metadata(self, name: str, data: Mapping[str, str]) -> None:
        """Append an MCAP metadata record ``name`` and flush (``record live`` writes one per gap in the stream)."""
        if self._writer is None:
            raise RecorderError("recorder is not open: use it as `with Recorder(...) as rec:`")
        self._writer.add_metadata(name, {str(k): str(v) for k, v in data.items()})
        self.flush()

    def _write_error(self, err: OSError) -> RecorderError:
        what = "no space left on the device" if err.errno == errno.ENOSPC else (err.strerror or str(err))
        return RecorderError(f"{what} while writing {self.partial} (after {self.message_count:,} messages): the "
                             f"recording is incomplete and kept as {self.partial.name}; once the cause is fixed, "
                             f"salvage it with `slamreplay recover {self.partial} --out FIXED.mcap`")

    def close(self, *, keep_partial: bool = False) -> None:
        """Finish the file; rename ``FILE.partial`` to ``FILE`` unless ``keep_partial``."""
        if self._writer is None or self._file is None:
            return
        error: OSError | None = None
        try:
            if not self._failed:
                self._writer.finish()  # type: ignore[no-untyped-call]  # mcap's Writer.finish is unannotated
                self._file.flush()
                os.fsync(self._file.fileno())
        except OSError as err:
            error = err
        finally:
            try:
                self._file.close()
            except OSError as err:  # the buffer could not be flushed either: the .partial ends where it ends
                error = error or err
            self._writer, self._file = None, None
        if error is not None and not keep_partial:
            raise self._write_error(error) from error
        if error is None and not keep_partial and not self._failed:
            os.replace(self.partial, self.path)
