"""TrajectoryLog: at every step the latest pieces of its levels together draw the whole polyline so far."""

from __future__ import annotations

import numpy as np
import pytest

from slamreplay.algorithms.observe import LineStrips
from slamreplay.replay.engine.trajectory import TrajectoryLog


class Latest:
    """Keeps each entity's latest strip (what a latest-at query at the current time shows) and counts points."""

    def __init__(self) -> None:
        self.latest: dict[str, np.ndarray] = {}
        self.points = 0
        self.calls = 0

    def log(self, path: str, item: LineStrips) -> None:
        strip = np.array(item.strips[0]) if item.strips else np.zeros((0, 2))
        self.latest[path] = strip
        self.points += len(strip)
        self.calls += 1


def drawn(obs: Latest, log: TrajectoryLog) -> np.ndarray:
    """The pieces joined coarse to fine; each piece starts where the one above it ends (shared point)."""
    pieces = [obs.latest[p] for p in log.paths if p in obs.latest and len(obs.latest[p])]
    out = pieces[0]
    for piece in pieces[1:]:
        assert np.array_equal(out[-1], piece[0])  # continuous: no gap, no overlap beyond the joint
        out = np.vstack([out, piece[1:]])
    return out


@pytest.mark.parametrize("levels", [1, 2, 3, 4])
def test_pieces_draw_the_whole_polyline_at_every_step(levels: int) -> None:
    rng = np.random.default_rng(levels)
    pts = np.cumsum(rng.normal(size=(3000, 2)), axis=0)
    obs = Latest()
    log = TrajectoryLog(obs, "world/trajectory/estimate", min_spacing_m=0.0, levels=levels)  # type: ignore[arg-type]
    assert log.paths == ["world/trajectory/estimate" + "/tail" * k for k in range(levels)]
    for k, (x, y) in enumerate(pts):
        log.append(float(x), float(y))
        if k % 37 == 0 or k > 2990:
            np.testing.assert_array_equal(drawn(obs, log), pts[: k + 1])
    log.finish()
    np.testing.assert_array_equal(obs.latest[log.path], pts)
    assert all(len(obs.latest[p]) == 0 for p in log.paths[1:])
    # points logged: O(n^(1 + 1/levels)); the finest piece is logged once per kept point
    n = len(pts)
    assert obs.points <= 3 * n ** (1 + 1 / levels) + 20 * n
    if levels >= 2:
        assert obs.calls <= 1.2 * n


def test_three_levels_log_far_fewer_points_than_two() -> None:
    pts = np.cumsum(np.random.default_rng(0).normal(size=(20000, 2)), axis=0)
    counts = {}
    for levels in (2, 3):
        obs = Latest()
        log = TrajectoryLog(obs, "t", min_spacing_m=0.0, levels=levels)  # type: ignore[arg-type]
        for x, y in pts:
            log.append(float(x), float(y))
        counts[levels] = obs.points
    assert counts[3] < counts[2] / 3  # measured: 0.82 million against 2.8 million


def test_close_points_are_dropped_and_the_last_one_kept_at_the_end() -> None:
    obs = Latest()
    log = TrajectoryLog(obs, "t", min_spacing_m=1.0)  # type: ignore[arg-type]
    for x in (0.0, 0.2, 0.4, 1.5, 1.6):
        log.append(x, 0.0)
    np.testing.assert_array_equal(log.array(), [[0.0, 0.0], [1.5, 0.0]])
    log.finish()
    np.testing.assert_array_equal(obs.latest["t"], [[0.0, 0.0], [1.5, 0.0], [1.6, 0.0]])
    with pytest.raises(ValueError, match="levels must be >= 1"):
        TrajectoryLog(obs, "t", levels=0)  # type: ignore[arg-type]
