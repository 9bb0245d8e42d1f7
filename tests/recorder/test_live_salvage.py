"""A live recording's folder after its process died: salvaged into a recording, or failed with the reason."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

from slamreplay.recorder.importers.live_salvage import live_leftovers, salvage_live
from slamreplay.recorder.messages import OdometryPose
from slamreplay.recorder.writer import Recorder
from slamreplay.replay.engine.reader import RecordingReader

# A recording process killed (SIGKILL) after flushing 50 messages, with 10 more written but not flushed.
KILLED = """
import os, signal, sys
from slamreplay.recorder.messages import OdometryPose
from slamreplay.recorder.writer import Recorder
rec = Recorder(sys.argv[1], source={"importer": "live", "url": "ws://robot:8765"})
rec.open()
for k in range(60):
    rec.write("/odom", OdometryPose(1_000_000_000 + k * 100_000_000, 0.1 * k, 0.0, 0.0))
    if k == 49:
        rec.flush()
os.kill(os.getpid(), signal.SIGKILL)
"""


def _killed_in(folder: Path) -> Path:
    folder.mkdir()
    subprocess.run([sys.executable, "-c", KILLED, str(folder / "live.mcap")], check=False, timeout=120)
    assert not (folder / "live.mcap").exists()
    return folder / "live.mcap.partial"


def test_a_killed_recording_is_salvaged_with_every_flushed_message(tmp_path: Path) -> None:
    """kill -9 after a flush: recovered.mcap holds the 50 messages flushed, in order, and says so in one line."""
    partial = _killed_in(tmp_path / ".live-abc")
    got = salvage_live(tmp_path / ".live-abc")
    assert got.how == "recovered" and got.path == tmp_path / ".live-abc" / "recovered.mcap"
    assert got.report is not None and got.report.messages == 50
    stamps = [e.msg.stamp_ns for e in RecordingReader(got.path).messages()]
    assert stamps == [1_000_000_000 + k * 100_000_000 for k in range(50)]
    assert partial.exists()  # left for the caller, which removes the folder once the recording is stored
    assert got.line().startswith(f"recovered 50 messages on 1 channels into {got.path}")
    again = salvage_live(tmp_path / ".live-abc")  # killed again before storing: the same file, not redone
    assert (again.how, again.path, again.report) == ("recovered", got.path, None)
    assert "salvaged before" in again.line()


def test_an_interrupted_salvage_is_done_again(tmp_path: Path) -> None:
    """A recovered.mcap.partial of a salvage cut short is discarded and the salvage redone."""
    _killed_in(tmp_path / ".live-abc")
    (tmp_path / ".live-abc" / "recovered.mcap.partial").write_bytes(b"\x89MCAP0\r\n half")
    got = salvage_live(tmp_path / ".live-abc")
    assert got.how == "recovered" and got.report is not None and got.report.messages == 50


def test_a_clean_end_not_yet_stored_is_kept_whole(tmp_path: Path) -> None:
    """live.mcap (the recording had ended) is the recording, as it is."""
    folder = tmp_path / ".live-abc"
    folder.mkdir()
    with Recorder(folder / "live.mcap", source={"importer": "live"}) as rec:
        rec.write("/odom", OdometryPose(1, 0.0, 0.0, 0.0))
    got = salvage_live(folder)
    assert (got.how, got.path, got.report) == ("complete", folder / "live.mcap", None)


def test_nothing_to_salvage_fails_with_the_reason(tmp_path: Path) -> None:
    """No file (killed while connecting), or a .partial without a readable message: failed, and why."""
    (tmp_path / ".live-a").mkdir()
    got = salvage_live(tmp_path / ".live-a")
    assert (got.how, got.path) == ("failed", None) and "stopped before it recorded" in got.reason
    (tmp_path / ".live-b").mkdir()
    (tmp_path / ".live-b" / "live.mcap.partial").write_bytes(b"")
    got = salvage_live(tmp_path / ".live-b")
    assert got.how == "failed" and "live.mcap.partial cannot be salvaged" in got.reason and "is empty" in got.reason
    assert got.line() == f"{tmp_path / '.live-b'}: nothing salvaged: {got.reason}"
    assert not (tmp_path / ".live-b" / "recovered.mcap").exists()


def test_leftovers_are_the_prefixed_folders_oldest_first(tmp_path: Path) -> None:
    """Only folders named PREFIX*, by age; a missing root has none."""
    for name in (".live-2", ".live-1", ".upload-x"):
        (tmp_path / name).mkdir()
    (tmp_path / ".live-file").write_text("")
    os.utime(tmp_path / ".live-2", (1, 1))
    assert live_leftovers(tmp_path, ".live-") == [tmp_path / ".live-2", tmp_path / ".live-1"]
    assert live_leftovers(tmp_path / "nowhere", ".live-") == []
