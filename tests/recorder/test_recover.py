"""recover: salvages truncated and damaged recordings into valid ones and says how much it kept."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from recorder import GroundTruthPose, Recorder, RecorderError
from recorder.recover import recover
from replay.reader import RecordingReader


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
    reader = RecordingReader(tmp_path / "fixed.mcap")
    got = [e.log_time_ns for e in reader.messages()]
    assert got == list(range(1000, 1000 + report.messages))
    assert reader.info.metadata["slamreplay.recording"]["source"] == "{}"


def test_whole_file_is_copied(tmp_path: Path) -> None:
    """An undamaged file is copied entirely and reported as such."""
    src = big_recording(tmp_path / "a.mcap", 500)
    report = recover(src, tmp_path / "b.mcap")
    assert (report.messages, report.channels, report.stopped_at) == (500, 1, None)


def test_crc_damage_stops_at_bad_chunk(tmp_path: Path) -> None:
    """A flipped byte inside the second chunk keeps the first chunk's messages."""
    src = big_recording(tmp_path / "a.mcap")
    from mcap.reader import make_reader

    with open(src, "rb") as f:
        chunks = make_reader(f).get_summary().chunk_indexes
    data = bytearray(src.read_bytes())
    second = chunks[1]
    data[second.chunk_start_offset + second.chunk_length - 100] ^= 0xFF
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(bytes(data))
    report = recover(bad, tmp_path / "fixed.mcap")
    assert report.messages == chunks[0].message_end_time - 1000 + 1
    assert report.stopped_at is not None  # zstd or the chunk CRC notices, whichever reads first


def test_recover_errors(tmp_path: Path) -> None:
    """Missing input, non-MCAP input and an existing output are refused."""
    with pytest.raises(RecorderError, match="no such file"):
        recover(tmp_path / "nope.mcap", tmp_path / "o.mcap")
    junk = tmp_path / "junk.mcap"
    junk.write_bytes(b"hello world, not an mcap")
    with pytest.raises(RecorderError, match="not an MCAP"):
        recover(junk, tmp_path / "o.mcap")
    src = big_recording(tmp_path / "a.mcap", 10)
    (tmp_path / "o.mcap").write_bytes(b"x")
    with pytest.raises(RecorderError, match="already exists"):
        recover(src, tmp_path / "o.mcap")
