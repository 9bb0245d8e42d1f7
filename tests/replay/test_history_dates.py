"""A suite's history over the days it ran: nightly recordings pooled, one point a day, the same change detection."""

from __future__ import annotations

from typing import Any

import pytest

from slamreplay.replay.errors import ReplayError
from slamreplay.replay.runs.changepoints import detect_changes
from slamreplay.replay.runs.history import series
from slamreplay.replay.runs.history_dates import ALL_RECORDINGS, day_of, history_by_date

CODE, OTHER = "c" * 40, "d" * 40


def cell(recording: str, seed: int, value: float, when: str, code: str = CODE, **extra: Any) -> dict[str, Any]:
    """A results row of a dslam cell whose landmark_rmse_m is ``value``, run at ``when``."""
    return {"recording": recording, "recording_seed": None, "pipeline": "dslam", "variant": "default", "seed": seed,
            "key": f"{recording}-{seed}-{code[:4]}-{when}", "status": "succeeded", "code_version": code,
            "ran_at": when, "metrics": {"landmark_rmse_m": value}, "better": {"landmark_rmse_m": "lower"},
            "units": {"landmark_rmse_m": "m"}, "tolerance": {"landmark_rmse_m": 1e-6},
            "rel_tolerance": {"landmark_rmse_m": 1e-3}, **extra}


def nights(n: int, worse_from: int) -> list[dict[str, Any]]:
    """The same code each night on that night's new recording (seeds 0-2); from night ``worse_from`` the data are
    harder and the error doubles. Night-to-night variation of a few percent."""
    rows = []
    for i in range(n):
        level = (0.2 if i >= worse_from else 0.1) * (1 + 0.02 * ((i * 7) % 3 - 1))
        rows += [cell(f"night-{i:02d}", s, level + 0.001 * s, f"2024-05-{i + 1:02d}T02:00:00+00:00") for s in range(3)]
    return rows


def test_nightly_recordings_pooled_and_the_harder_night_found() -> None:
    """Ten nights, each its own recording: one series (all recordings), one point a night, the one change at the
    night the data got harder, judged from the night before it."""
    h = history_by_date(nights(10, 6), suite="nightly")
    assert [c.sha for c in h.commits] == [f"2024-05-{i + 1:02d}" for i in range(10)]
    assert list(series(h)) == [(ALL_RECORDINGS, "dslam", "default")]  # each recording met once: only the pool
    assert sorted((r["recording"], bool(r.get("alone"))) for r in h.cells("2024-05-01")) == [
        (ALL_RECORDINGS, False)] * 3 + [("night-00", True)] * 3  # its runs still listed with their day
    assert h.commits[0].subject == f"code {CODE[:10]}" and h.status["2024-05-01"]["versions"] == [CODE]
    changes = detect_changes(h)
    assert [(ch.previous, ch.commit, ch.verdict) for ch in changes] == [("2024-05-06", "2024-05-07", "regression")]
    assert changes[0].mean_before == pytest.approx(0.101, rel=0.03)


def test_recurring_recordings_reruns_versions_and_days() -> None:
    """A recording run every night keeps its own series beside the pool; a cell run twice a day counts by its latest
    run; --version keeps one code version's runs; days are UTC; a row that cannot be dated is left out."""
    rows = nights(3, 9) + [cell("fixed", 0, 0.5, f"2024-05-0{i + 1}T03:00:00+00:00") for i in range(3)]
    rows.append(cell("fixed", 0, 0.9, "2024-05-02T23:30:00-04:00", OTHER))  # a backfill, 03:30 on the 3rd in UTC
    rows.append(cell("fixed", 1, 0.4, "", run_dir=None))  # no manifest, no time: not on any day
    h = history_by_date(rows)
    assert set(series(h)) == {(ALL_RECORDINGS, "dslam", "default"), ("fixed", "dslam", "default")}
    fixed = series(h)[("fixed", "dslam", "default")]["landmark_rmse_m"]
    assert fixed == [{0: 0.5}, {0: 0.5}, {0: 0.9}]  # the 3rd's latest run of the cell is the backfill's
    assert h.status["2024-05-03"]["versions"] == [CODE, OTHER]
    mine = history_by_date(rows, version=CODE[:8])
    assert series(mine)[("fixed", "dslam", "default")]["landmark_rmse_m"] == [{0: 0.5}] * 3
    with pytest.raises(ReplayError, match="no run of code version 'abcdef12'"):
        history_by_date(rows, version="abcdef12")
    assert day_of("2024-05-02T22:30:00-02:00") == "2024-05-03" and day_of("2024-05-02T23:00:00") == "2024-05-02"
    assert day_of("yesterday") is None
