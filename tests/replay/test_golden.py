"""Golden: the odometry pipeline's observer events and metrics on the tiny recording.

Rewrite with `pytest tests/replay/test_golden.py --update-golden` after an intended change,
and review the diff of tests/golden/ like code.
"""

from __future__ import annotations

import json
from pathlib import Path

from conftest import write_tiny_recording

from replay.engine import replay
from replay.metrics import format_metrics
from replay.observer import MemoryObserver
from replay.pipeline import get_pipeline, resolve_config
from replay.reader import RecordingReader

GOLDEN = Path(__file__).resolve().parents[1] / "golden" / "odometry_tiny.json"


def test_odometry_golden(tmp_path: Path, update_golden: bool) -> None:
    """Events (rounded to 1e-9) and metrics match the reviewed golden file."""
    recording = write_tiny_recording(tmp_path / "golden.mcap", n=25)
    cls = get_pipeline("odometry")
    obs = MemoryObserver()
    stats = replay(RecordingReader(recording), cls, resolve_config(cls), obs, seed=0, log=lambda s: None)
    doc = {"metrics": format_metrics(cls.name, {k: round(v, 9) for k, v in stats.metrics.items()}, cls.metrics),
           "events": obs.to_jsonable(decimals=9)}
    text = json.dumps(doc, sort_keys=True, indent=1) + "\n"
    if update_golden or not GOLDEN.exists():
        GOLDEN.write_text(text)
    assert json.loads(GOLDEN.read_text()) == json.loads(text), "golden changed; review, then --update-golden"
