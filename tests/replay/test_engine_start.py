"""The start pose found in the replay stream equals the one read from the file (engine.start_pose)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from slamreplay.recorder import GroundTruthPose, OdometryPose, Recorder
from slamreplay.replay.engine import loop as engine
from slamreplay.replay.engine.loop import start_from_stream, start_pose
from slamreplay.replay.engine.reader import RecordingReader
from slamreplay.replay.errors import ReplayError

TOPICS = ["/odom", "/ground_truth/pose"]


def _record(path: Path, truth_times: list[int], odom_times: list[int]) -> Path:
    with Recorder(path, source={}) as rec:
        for t in sorted(set(truth_times) | set(odom_times)):
            if t in truth_times:
                rec.write("/ground_truth/pose", GroundTruthPose(t, 0.01 * t, -0.02 * t, 1e-3 * t))
            if t in odom_times:
                rec.write("/odom", OdometryPose(t, 5.0, 6.0, 0.5))
    return path


@pytest.mark.parametrize(("truth", "odom", "window"), [
    ([100, 200, 300], [150, 250], (None, None)),  # interpolated
    ([100, 200, 300], [200, 250], (None, None)),  # truth at t0 exactly
    ([300, 400], [150, 250], (None, None)),  # truth starts after t0: its first pose
    ([100, 120], [150, 250], (None, None)),  # truth ends before t0: its last pose
    ([100, 200, 300, 400], [150, 250, 350], (240, 330)),  # a window: truth after it counts, as in start_pose
    ([100, 200, 300, 400], [150, 250, 350], (240, 300)),  # truth at/after t0 only past the window's end
])
def test_same_as_start_pose(tmp_path: Path, truth: list[int], odom: list[int],
                            window: tuple[int | None, int | None]) -> None:
    """Every case of ground truth around t0 gives start_pose's answer, and the held messages come first."""
    reader = RecordingReader(_record(tmp_path / "r.mcap", truth, odom))
    stream = reader.messages(TOPICS, start_ns=window[0], end_ns=window[1])
    t0, pose, held = start_from_stream(reader, stream, TOPICS, "/odom", *window)
    t0_ref, pose_ref = start_pose(reader, "/odom", *window)
    assert t0 == t0_ref
    assert (pose is None) == (pose_ref is None) and (pose is None or np.array_equal(pose, pose_ref))
    replayed = [e.index for e in held] + [e.index for e in stream]
    assert replayed == [e.index for e in reader.messages(TOPICS, start_ns=window[0], end_ns=window[1])]


def test_without_truth_topic_in_pipeline(tmp_path: Path) -> None:
    """A pipeline that does not read ground truth still starts at it (read from the file)."""
    reader = RecordingReader(_record(tmp_path / "r.mcap", [100, 200], [150]))
    stream = reader.messages(["/odom"])
    t0, pose, held = start_from_stream(reader, stream, ["/odom"], "/odom", None, None)
    assert t0 == 150 and held == [] and np.allclose(pose, [1.5, -3.0, 0.15])


def test_buffer_bound_falls_back(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Past START_BUFFER held messages the file is read again; the answer is the same."""
    monkeypatch.setattr(engine, "START_BUFFER", 2)
    reader = RecordingReader(_record(tmp_path / "r.mcap", [400], [100, 200, 300]))
    t0, pose, held = start_from_stream(reader, reader.messages(TOPICS), TOPICS, "/odom", None, None)
    assert t0 == 100 and len(held) == 2 and np.allclose(pose, [4.0, -8.0, 0.4])


def test_no_start_message_in_window(tmp_path: Path) -> None:
    """No start-topic message in the window: the one-line error of start_pose."""
    reader = RecordingReader(_record(tmp_path / "r.mcap", [100], [150]))
    with pytest.raises(ReplayError, match="no /odom message in the chosen time window"):
        start_from_stream(reader, reader.messages(TOPICS, start_ns=200), TOPICS, "/odom", 200, None)
