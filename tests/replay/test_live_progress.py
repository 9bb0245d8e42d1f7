"""A running replay's live file (replay.runs.live): it grows as the run goes, and changes none of its results."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from slamreplay.replay.engine.loop import replay
from slamreplay.replay.engine.observer import MemoryObserver
from slamreplay.replay.engine.pipeline import Pipeline, get_pipeline
from slamreplay.replay.engine.reader import RecordingReader
from slamreplay.replay.runs.live import LIVE_FILE, LiveWriter, MetricTap, read_live, thin_index
from slamreplay.replay.runs.run import run_recording


def _watched(base: type[Pipeline], live: Path, seen: list[dict[str, Any]]) -> type[Pipeline]:
    """``base``, reading the live file every 40 messages (as a job page would, mid-run)."""

    class Watched(base):  # type: ignore[valid-type,misc]
        steps = 0

        def step(self, env: Any) -> None:
            super().step(env)
            Watched.steps += 1
            if Watched.steps % 40 == 0:
                doc = read_live(live.parent)
                if doc is not None:
                    seen.append(doc)

    return Watched


def test_live_file_grows_while_running(tiny_recording: Path, tmp_path: Path) -> None:
    """Mid-run the file holds more messages, a longer trajectory, the position error and the pipeline's series."""
    seen: list[dict[str, Any]] = []
    writer = LiveWriter(tmp_path / LIVE_FILE, period_s=0.0)  # every message: no waiting in a test
    cls = _watched(get_pipeline("dslam"), writer.path, seen)
    reader = RecordingReader(tiny_recording)
    cfg = cls.Config()
    replay(reader, cls, cfg, MemoryObserver(), seed=0, log=lambda _: None, live=writer)
    assert len(seen) >= 3
    done = [d["messages_done"] for d in seen]
    assert done == sorted(done) and len(set(done)) == len(done)
    poses = [len(d["trajectory"]["xy"]) for d in seen]
    assert poses == sorted(poses) and poses[-1] > poses[0]
    assert all(d["online"]["position_error_m"] is not None and d["online"]["ape_rmse_m"] >= 0 for d in seen)
    assert seen[-1]["truth"]["xy"] and seen[-1]["error"]["m"]
    assert "ci_omega" in seen[-1]["series"] and seen[-1]["series"]["ci_omega"]["n"] > seen[0]["series"].get(
        "ci_omega", {"n": 0})["n"]
    final = json.loads(writer.path.read_text())  # the last update comes after the last message
    assert final["messages_done"] == final["messages_total"]
    writer.close()
    assert not writer.path.exists()


def test_tap_forwards_everything(tiny_recording: Path) -> None:
    """The observer behind the tap gets exactly the events it gets without one."""
    cls = get_pipeline("dslam")
    plain, tapped = MemoryObserver(), MemoryObserver()
    replay(RecordingReader(tiny_recording), cls, cls.Config(), plain, seed=0, log=lambda _: None)
    tap = MetricTap(tapped)
    replay(RecordingReader(tiny_recording), cls, cls.Config(), tap, seed=0, log=lambda _: None)
    assert plain.to_jsonable() == tapped.to_jsonable()
    assert tap.series  # and it counted the pipeline's metrics/ scalars


def test_run_leaves_no_live_file(tiny_recording: Path, tmp_path: Path) -> None:
    """A finished run has no live file, and its metrics.json is the same byte for byte run after run."""
    a = run_recording(tiny_recording, "dslam", tmp_path / "a", seed=1)
    b = run_recording(tiny_recording, "dslam", tmp_path / "b", seed=1)
    assert not (a.run_dir / LIVE_FILE).exists()
    assert (a.run_dir / "metrics.json").read_bytes() == (b.run_dir / "metrics.json").read_bytes()


def test_thin_index() -> None:
    """At most the asked number of indices, first and last kept, all of them when few."""
    assert list(thin_index(5, 10)) == [0, 1, 2, 3, 4]
    idx = thin_index(10_000, 300)
    assert len(idx) <= 300 and idx[0] == 0 and idx[-1] == 9_999
