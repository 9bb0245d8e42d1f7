"""inspect: a recording with no messages is only healthy when nothing in it says it should hold some."""

from __future__ import annotations

from pathlib import Path

import pytest
from mcap.writer import Writer

from slamreplay.api.cli.command import main
from slamreplay.recorder import GroundTruthPose, Recorder, codec
from slamreplay.replay.tools.inspect import empty_contradiction, inspect_recording


def test_recorder_closed_without_messages_is_empty(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A Recorder closed with nothing written has slamreplay.recording metadata naming its producer: not ok."""
    path = tmp_path / "none.mcap"
    with Recorder(path, source={"simulator": "sim-landmarks"}):
        pass
    report = inspect_recording(path)
    assert report["health"] == "empty" and report["message_count"] == 0
    assert "holds no messages, yet its slamreplay.recording metadata says it was produced by" in report["problems"][0]
    assert main(["inspect", str(path)]) == 1
    assert "health: empty" in capsys.readouterr().out


def test_channels_without_messages_are_empty(tmp_path: Path) -> None:
    """Declared channels with no message (what recover used to write from a random body) are not ok."""
    path = tmp_path / "channels.mcap"
    with open(path, "wb") as f:
        w = Writer(f)
        w.start()
        msg = GroundTruthPose(0, 0.0, 0.0, 0.0)
        sid = w.register_schema(codec.schema_name(msg), "protobuf", codec.schema_data(msg))
        w.register_channel("/ground_truth/pose", "protobuf", sid)
        w.finish()
    report = inspect_recording(path)
    assert report["health"] == "empty"
    assert "it declares 1 channel(s) (/ground_truth/pose)" in report["problems"][0]


def test_bare_empty_mcap_is_ok(tmp_path: Path) -> None:
    """An MCAP with no channel and no metadata claims nothing, so holding nothing contradicts nothing."""
    path = tmp_path / "bare.mcap"
    with open(path, "wb") as f:
        w = Writer(f)
        w.start()
        w.finish()
    assert inspect_recording(path)["health"] == "ok"
    assert empty_contradiction({}, []) is None
