"""`record images`: frame order by counter, stamps from the rate, errors."""

from __future__ import annotations

import struct
import zlib
from pathlib import Path

import cv2
import numpy as np
import pytest

from slamreplay.api.cli.command import main
from slamreplay.recorder.errors import RecorderError
from slamreplay.recorder.importers.images import frame_key, import_images
from slamreplay.replay.engine.reader import RecordingReader


def test_sorted_by_frame_counter(tmp_path: Path) -> None:
    """Frames sort by the last number in the name, and stamps follow the rate."""
    for name, value in [("ESC.1_9.0010.png", 10), ("ESC.2_1.0009.png", 9), ("ESC.0_5.0100.png", 100)]:
        cv2.imwrite(str(tmp_path / name), np.full((40, 50), value, np.uint8))
    s = import_images(tmp_path, tmp_path / "out.mcap", rate_hz=2.0)
    msgs = [e.msg for e in RecordingReader(tmp_path / "out.mcap").messages()]
    assert [int(m.pixels[0, 0]) for m in msgs] == [9, 10, 100]  # type: ignore[attr-defined]
    assert [m.stamp_ns for m in msgs] == [1_000_000_000, 1_500_000_000, 2_000_000_000]  # type: ignore[attr-defined]
    assert (s.images, s.width_px, s.height_px) == (3, 50, 40)
    assert frame_key(Path("a.png")) > frame_key(Path("b.0001.png"))


def test_errors(tmp_path: Path) -> None:
    """No folder, no images, mixed sizes and a bad rate are RecorderErrors; the CLI exits 2."""
    with pytest.raises(RecorderError, match="not a directory"):
        import_images(tmp_path / "none", tmp_path / "o.mcap")
    with pytest.raises(RecorderError, match="holds no images"):
        import_images(tmp_path, tmp_path / "o.mcap")
    with pytest.raises(RecorderError, match="rate-hz"):
        import_images(tmp_path, tmp_path / "o.mcap", rate_hz=0.0)
    cv2.imwrite(str(tmp_path / "f1.png"), np.zeros((40, 50), np.uint8))
    cv2.imwrite(str(tmp_path / "f2.png"), np.zeros((30, 50), np.uint8))
    with pytest.raises(RecorderError, match="every frame must have one size"):
        import_images(tmp_path, tmp_path / "o.mcap")
    assert main(["record", "images", str(tmp_path / "none"), "--out", str(tmp_path / "p.mcap"), "-q"]) == 2


def test_a_frame_claiming_40000_squared_pixels_is_refused_unread(tmp_path: Path) -> None:
    """A PNG whose IHDR claims 40,000 x 40,000 pixels is refused from its header, before OpenCV decodes it."""
    _, buf = cv2.imencode(".png", np.zeros((3, 4), np.uint8))
    png = bytearray(buf.tobytes())
    struct.pack_into(">II", png, 16, 40_000, 40_000)
    struct.pack_into(">I", png, 29, zlib.crc32(bytes(png[12:29])))
    (tmp_path / "frame_000.png").write_bytes(bytes(png))
    with pytest.raises(RecorderError, match=r"^frame_000.png: the png header claims 40,000 x 40,000 pixels; "
                                            r"slamreplay decodes at most 33,554,432 pixels per image"):
        import_images(tmp_path, tmp_path / "o.mcap")
