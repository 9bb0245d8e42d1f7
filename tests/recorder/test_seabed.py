"""sim-seabed: determinism, topics, geometry against the registration convention, config errors."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from slamreplay.recorder.errors import RecorderError
from slamreplay.recorder.messages import CameraImage, GroundTruthPose, OdometryPose
from slamreplay.recorder.sim.seabed import SeabedSimConfig, procedural_texture, simulate_seabed
from slamreplay.replay.engine.reader import RecordingReader

SMALL = SeabedSimConfig(image_px=96, legs=2, leg_length_m=1.5, metres_per_pixel=0.01)


def read(path: Path) -> list[object]:
    """Every message of a recording, in order."""
    return [env.msg for env in RecordingReader(path).messages()]


def test_deterministic_and_complete(tmp_path: Path) -> None:
    """Same seed, same messages; every image has a ground-truth pose and odometry at its stamp."""
    a = simulate_seabed(tmp_path / "a.mcap", SMALL, seed=3)
    simulate_seabed(tmp_path / "b.mcap", SMALL, seed=3)
    ma, mb = read(tmp_path / "a.mcap"), read(tmp_path / "b.mcap")
    images = [m for m in ma if isinstance(m, CameraImage)]
    assert len(images) == a.images == sum(isinstance(m, GroundTruthPose) for m in ma)
    assert sum(isinstance(m, OdometryPose) for m in ma) == a.images
    assert images[0].pixels.shape == (96, 96)
    for x, y in zip(ma, mb, strict=True):
        if isinstance(x, CameraImage):
            np.testing.assert_array_equal(x.pixels, y.pixels)  # type: ignore[union-attr]


def test_procedural_texture_is_seeded() -> None:
    """The texture depends on the generator only."""
    a = procedural_texture(200, 100, np.random.default_rng(1))
    b = procedural_texture(200, 100, np.random.default_rng(1))
    assert a.shape == (100, 200) and a.dtype == np.uint8 and np.array_equal(a, b) and a.std() > 10


def test_texture_errors(tmp_path: Path) -> None:
    """A missing texture, an unreadable one and an empty folder are RecorderErrors."""
    with pytest.raises(RecorderError, match="does not exist"):
        simulate_seabed(tmp_path / "x.mcap", SeabedSimConfig(texture=str(tmp_path / "none.png")), seed=0)
    (tmp_path / "bad.png").write_text("not an image")
    with pytest.raises(RecorderError, match="not an image"):
        simulate_seabed(tmp_path / "y.mcap", SeabedSimConfig(texture=str(tmp_path / "bad.png")), seed=0)
    (tmp_path / "empty").mkdir()
    with pytest.raises(RecorderError, match="no readable images"):
        simulate_seabed(tmp_path / "z.mcap", SeabedSimConfig(texture=str(tmp_path / "empty")), seed=0)


def test_config_validation() -> None:
    """Each config error names its field."""
    for kwargs, match in [({"image_px": 8}, "image_px"), ({"legs": 0}, "legs"), ({"leg_spacing": 2.0}, "leg_spacing"),
                          ({"vignetting": 1.0}, "vignetting"), ({"noise_sigma": -1.0}, "noise_sigma"),
                          ({"metres_per_pixel": 0.0}, "metres_per_pixel"), ({"scale_amplitude": 0.5}, "scale")]:
        with pytest.raises(ValueError, match=match):
            SeabedSimConfig(**kwargs)  # type: ignore[arg-type]
