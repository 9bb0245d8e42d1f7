"""Golden results: every pipeline's metrics on its short seeded simulation, and the odometry pipeline's events.

The references live in tests/golden/ and are written only on purpose, never by the test itself:
``pytest tests/replay/test_golden.py --update-golden`` after an intended change, then review the
diff of tests/golden/ like code. A metric matches its reference within the metric's own diff
tolerance (``slamreplay.replay.runs.diff.metric_tolerance``: 0.1 % relative for measured values, exact for
counts), so the same references hold on every supported Python, numpy and BLAS.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import pytest
from conftest import write_tiny_recording

from slamreplay.replay.engine.loop import replay
from slamreplay.replay.engine.observer import MemoryObserver
from slamreplay.replay.engine.pipeline import get_pipeline, resolve_config
from slamreplay.replay.engine.reader import RecordingReader
from slamreplay.replay.evaluation.metrics import format_metrics
from slamreplay.replay.evaluation.score import metric_specs, score
from slamreplay.replay.runs.diff import metric_tolerance

GOLDEN_DIR = Path(__file__).resolve().parents[1] / "golden"
EVENTS = GOLDEN_DIR / "odometry_tiny.json"
PIPELINES = ("odometry", "dslam", "ekfslam", "slsjf", "ifmi", "topometric", "topometric-nav", "dslam-multi")
UPDATE = "pytest tests/replay/test_golden.py --update-golden"


def read_golden(path: Path) -> Any:
    """The reviewed reference at ``path``; fails, naming the command that writes it, when it is missing."""
    if not path.exists():
        pytest.fail(f"golden file {path} is missing: write it on purpose with `{UPDATE}`, review it, commit it")
    return json.loads(path.read_text())


def metric_differences(golden: dict[str, Any], doc: dict[str, Any]) -> list[str]:
    """Metrics of ``doc`` (a metrics.json) that differ from ``golden`` beyond each metric's tolerance, or are
    missing or new."""
    want, got = golden["metrics"], doc["metrics"]
    out = [f"{k}: missing (golden {want[k]['value']})" for k in sorted(set(want) - set(got))]
    out += [f"{k}: new ({got[k]['value']})" for k in sorted(set(got) - set(want))]
    for k in sorted(set(want) & set(got)):
        a, b = float(want[k]["value"]), float(got[k]["value"])
        tol = metric_tolerance(want[k], a)
        if not (math.isfinite(b) and abs(b - a) <= tol):
            out.append(f"{k}: {b!r} against golden {a!r} (tolerance {tol:.3g})")
    return out


@pytest.mark.parametrize("name", PIPELINES)
def test_pipeline_metrics_golden(name: str, pipeline_runs: dict[str, Path], update_golden: bool) -> None:
    """Each pipeline's metrics on its seeded simulation match the reviewed golden file within their tolerances."""
    doc = json.loads((pipeline_runs[name] / "metrics.json").read_text())
    path = GOLDEN_DIR / f"{name}_metrics.json"
    if update_golden:
        path.write_text(json.dumps(doc, sort_keys=True, indent=1) + "\n")
    diffs = metric_differences(read_golden(path), doc)
    assert not diffs, f"{name} metrics changed ({'; '.join(diffs)}); review, then `{UPDATE}`"


def test_a_missing_golden_file_fails_and_names_the_command(tmp_path: Path) -> None:
    """No reference: the test fails with the command that writes one, and writes nothing."""
    path = tmp_path / "absent.json"
    with pytest.raises(pytest.fail.Exception, match=r"missing: write it on purpose with `pytest .* --update-golden`"):
        read_golden(path)
    assert not path.exists()


def test_metric_differences_are_two_sided_within_the_tolerance() -> None:
    """A change within the metric's tolerance passes either way; beyond it, up or down, it fails; counts are exact."""
    golden = {"metrics": {"rmse": {"value": 2.0, "tolerance": 1e-6, "rel_tolerance": 1e-3},
                          "count": {"value": 7.0, "tolerance": 0.0, "rel_tolerance": 0.0}}}

    def doc(rmse: float, count: float = 7.0, **extra: float) -> dict[str, Any]:
        return {"metrics": {"rmse": {"value": rmse}, "count": {"value": count},
                            **{k: {"value": v} for k, v in extra.items()}}}

    assert metric_differences(golden, doc(2.0019)) == metric_differences(golden, doc(1.9981)) == []
    assert len(metric_differences(golden, doc(2.0021))) == len(metric_differences(golden, doc(1.9979))) == 1
    assert metric_differences(golden, doc(2.0, 8.0)) == ["count: 8.0 against golden 7.0 (tolerance 0)"]
    assert metric_differences(golden, doc(float("nan")))
    assert metric_differences(golden, doc(2.0, extra=1.0)) == ["extra: new (1.0)"]
    assert metric_differences(golden, {"metrics": {"rmse": {"value": 2.0}}}) == ["count: missing (golden 7.0)"]


def test_odometry_golden(tmp_path: Path, update_golden: bool) -> None:
    """Events (rounded to 1e-9) and metrics of the odometry pipeline on the tiny recording match the golden file."""
    recording = write_tiny_recording(tmp_path / "golden.mcap", n=25)
    cls = get_pipeline("odometry")
    obs = MemoryObserver()
    stats = score(replay(RecordingReader(recording), cls, resolve_config(cls), obs, seed=0, log=lambda s: None), cls)
    doc = {"metrics": format_metrics(cls.name, {k: round(v, 9) for k, v in stats.metrics.items()},
                                  metric_specs(cls)),
           "events": obs.to_jsonable(decimals=9)}
    text = json.dumps(doc, sort_keys=True, indent=1) + "\n"
    if update_golden:
        EVENTS.write_text(text)
    assert read_golden(EVENTS) == json.loads(text), f"golden changed; review, then `{UPDATE}`"
