"""Read a recording back for recorder tests: every message with its topic and log time."""

from __future__ import annotations

from pathlib import Path
from typing import TypeVar

import numpy as np
from numpy.typing import NDArray

from slamreplay.recorder.messages import Message, PlanarPose
from slamreplay.replay.engine.reader import RecordingReader

M = TypeVar("M")


def read_recording(path: Path) -> list[tuple[str, int, Message]]:
    """All messages of a recording as (topic, log_time_ns, message), in log-time order."""
    return [(e.topic, e.log_time_ns, e.msg) for e in RecordingReader(path).messages()]


def by_topic(msgs: list[tuple[str, int, Message]], topic: str, kind: type[M]) -> list[M]:
    """The messages of one topic, in order, checked to be of type ``kind``."""
    out: list[M] = []
    for t, _, m in msgs:
        if t == topic:
            assert isinstance(m, kind), f"{topic}: {type(m).__name__} is not a {kind.__name__}"
            out.append(m)
    return out


def poses(msgs: list[tuple[str, int, Message]], topic: str) -> tuple[NDArray[np.int64], NDArray[np.float64]]:
    """Stamps (n,) and [x, y, yaw] (n, 3) of a pose topic."""
    items = by_topic(msgs, topic, PlanarPose)
    return (np.array([p.stamp_ns for p in items], dtype=np.int64),
            np.array([[p.x_m, p.y_m, p.yaw_rad] for p in items]))
