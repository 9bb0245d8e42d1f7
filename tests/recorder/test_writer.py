"""Recorder: never overwrites, complete-or-partial files, metadata, explicit times."""

from __future__ import annotations

import errno
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from mcap.reader import make_reader

from slamreplay.recorder import GroundTruthPose, OdometryPose, Recorder, RecorderError
from slamreplay.recorder.writer import METADATA_NAME


def test_clean_close_renames_partial(tmp_path: Path) -> None:
    """Inside the block only FILE.partial exists; after a clean close only FILE."""
    path = tmp_path / "r.mcap"
    with Recorder(path, source={"test": 1}, seed=7, parameters={"a": 1}) as rec:
        rec.write("/odom", OdometryPose(5, 1, 2, 0.5), log_time_ns=10, publish_time_ns=11)
        assert (tmp_path / "r.mcap.partial").exists() and not path.exists()
    assert path.exists() and not (tmp_path / "r.mcap.partial").exists()
    with open(path, "rb") as f:
        reader = make_reader(f)
        meta = {m.name: m.metadata for m in reader.iter_metadata()}
        (_, channel, message), = list(reader.iter_messages())
    assert meta[METADATA_NAME]["seed"] == "7" and '"a": 1' in meta[METADATA_NAME]["parameters"]
    assert (message.log_time, message.publish_time, channel.topic) == (10, 11, "/odom")
    assert reader.get_summary().chunk_indexes[0].compression == "zstd"


def test_times_default_to_stamp_never_wall_clock(tmp_path: Path) -> None:
    """Without explicit times, log and publish time are the message stamp."""
    path = tmp_path / "r.mcap"
    with Recorder(path, source={}) as rec:
        rec.write("/odom", OdometryPose(123, 0, 0, 0))
    with open(path, "rb") as f:
        (_, _, m), = list(make_reader(f).iter_messages())
    assert (m.log_time, m.publish_time) == (123, 123)


def test_refuses_to_overwrite(tmp_path: Path) -> None:
    """An existing FILE or FILE.partial is never overwritten."""
    path = tmp_path / "r.mcap"
    path.write_bytes(b"precious")
    with pytest.raises(RecorderError, match="already exists"):
        Recorder(path, source={})
    assert path.read_bytes() == b"precious"
    other = tmp_path / "s.mcap"
    (tmp_path / "s.mcap.partial").write_bytes(b"x")
    with pytest.raises(RecorderError, match="already exists"):
        Recorder(other, source={})


def test_exception_keeps_partial(tmp_path: Path) -> None:
    """When the block raises, the data is kept as FILE.partial and FILE never appears."""
    path = tmp_path / "r.mcap"
    with pytest.raises(RuntimeError), Recorder(path, source={}) as rec:
        rec.write("/odom", OdometryPose(1, 0, 0, 0))
        raise RuntimeError("sensor died")
    assert not path.exists()
    with open(tmp_path / "r.mcap.partial", "rb") as f:
        assert len(list(make_reader(f).iter_messages())) == 1


def test_write_errors(tmp_path: Path) -> None:
    """Wrong type for a topic, schema change on a topic, writing when closed, bad metadata, missing folder."""
    with Recorder(tmp_path / "r.mcap", source={}) as rec:
        with pytest.raises(RecorderError, match="carries OdometryPose"):
            rec.write("/odom", GroundTruthPose(1, 0, 0, 0))
        rec.write("/custom", OdometryPose(1, 0, 0, 0))
        from slamreplay.recorder import RangeBearingScan

        with pytest.raises(RecorderError, match="has schema foxglove.PoseInFrame"):
            rec.write("/custom", RangeBearingScan(1, [], [], []))
    with pytest.raises(RecorderError, match="not open"):
        rec.write("/odom", OdometryPose(1, 0, 0, 0))
    with pytest.raises(RecorderError, match="JSON-serializable"):
        Recorder(tmp_path / "q.mcap", source={"x": object()})
    with pytest.raises(RecorderError, match="does not exist"):
        Recorder(tmp_path / "nope" / "q.mcap", source={})


class _FullDisk:
    """A file that takes ``budget`` bytes, then fails as a full disk does (ENOSPC)."""

    def __init__(self, f: Any, budget: int) -> None:
        self.f, self.budget = f, budget

    def write(self, data: bytes) -> int:
        if len(data) > self.budget:
            self.f.write(data[: self.budget])
            self.budget = 0
            raise OSError(errno.ENOSPC, "No space left on device")
        self.budget -= len(data)
        return int(self.f.write(data))

    def __getattr__(self, name: str) -> Any:
        return getattr(self.f, name)


def test_full_disk_is_a_clear_error_and_keeps_a_recoverable_partial(tmp_path: Path,
                                                                    monkeypatch: pytest.MonkeyPatch) -> None:
    """ENOSPC mid-recording: one RecorderError saying so, no FILE, and a FILE.partial that recover salvages."""
    import slamreplay.recorder.writer as writer_module
    from slamreplay.recorder.recover import recover

    real_open = open
    monkeypatch.setattr(writer_module, "open", lambda p, mode: _FullDisk(real_open(p, mode), 300_000), raising=False)
    path = tmp_path / "full.mcap"
    rng = np.random.default_rng(0)
    full = (r"no space left on the device while writing .*full\.mcap\.partial \(after [\d,]+ messages\): the "
            r"recording is incomplete and kept as full\.mcap\.partial; .*slamreplay recover")
    with pytest.raises(RecorderError, match=full), Recorder(path, source={"test": "full"}) as rec:
        for k in range(100_000):
            rec.write("/ground_truth/pose", GroundTruthPose(1000 + k, *rng.normal(size=3)))
    assert not path.exists() and (tmp_path / "full.mcap.partial").stat().st_size == 300_000
    report = recover(tmp_path / "full.mcap.partial", tmp_path / "fixed.mcap")
    assert report.messages > 1000


def test_partial_holds_header_and_metadata_before_any_message(tmp_path: Path) -> None:
    """While recording, before the first chunk is written, FILE.partial already holds the header and metadata:
    a process killed then leaves a truncated recording that says what it was, not an empty file."""
    from slamreplay.recorder.errors import DamageError
    from slamreplay.recorder.recover import recover
    from slamreplay.replay.tools.inspect import inspect_recording

    rec = Recorder(tmp_path / "r.mcap", source={"simulator": "test"})
    rec.open()
    rec.write("/odom", OdometryPose(5, 0.0, 0.0, 0.0))
    partial = tmp_path / "r.mcap.partial"
    data = partial.read_bytes()
    assert data.startswith(b"\x89MCAP0\r\n") and METADATA_NAME.encode() in data
    assert inspect_recording(partial)["health"] == "truncated"
    with pytest.raises(DamageError, match="holds no readable message"):
        recover(partial, tmp_path / "fixed.mcap")
    rec.close()
