"""Estimated trajectories exported as TUM files: format, round trip, and the run artifact."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from slamreplay.replay.engine.trajectory import read_tum, to_tum
from slamreplay.replay.runs.run import run_recording


def test_tum_round_trip() -> None:
    """Times to the nanosecond, positions and yaw survive a write and a read."""
    t = np.array([1_000_000_001, 2_500_000_000], np.int64)
    poses = np.array([[1.0, -2.0, 0.3], [3.5, 4.25, -3.0]])
    text = to_tum(t, poses).decode()
    assert text.splitlines()[1].startswith("1.000000001 1 -2 0 0 0 ")
    t_s, back = read_tum(text)
    assert t_s == pytest.approx([1.000000001, 2.5])
    assert back == pytest.approx(poses, abs=1e-8)
    with pytest.raises(ValueError, match="differ in length"):
        to_tum(t, poses[:1])
    with pytest.raises(ValueError, match="line 1: expected 8 fields"):
        read_tum("1 2 3\n")


def test_run_writes_its_estimate(tiny_recording: Path, tmp_path: Path) -> None:
    """An odometry run lists trajectory.tum among its artifacts; one pose per estimate."""
    res = run_recording(tiny_recording, "odometry", tmp_path / "run")
    assert "trajectory.tum" in res.manifest["artifacts"]
    t_s, poses = read_tum((res.run_dir / "trajectory.tum").read_text())
    assert len(t_s) == 100 and np.all(np.diff(t_s) > 0)
    assert poses[0] == pytest.approx([0.0, 0.0, 0.0], abs=1e-9)
