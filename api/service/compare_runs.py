"""Compare any runs, whatever their pipelines, recordings, seeds or configs.

Two runs compare as ``slamreplay diff`` does (`slamreplay.replay.runs.diff.diff_runs` on their run
directories, without the slow ``.rrd`` content check): what changed (pipeline, recording by the
name it was uploaded with, config key by key, seed, code version) and each metric's delta with
its verdict by the metric's direction. Several runs: their trajectories overlaid on one plot and
their metrics side by side, with a link per pair to the two-run view. What the page draws and what
``GET /compare?runs=`` answers as JSON are built here, from the job store and the run directories.
"""

from __future__ import annotations

import contextlib
import json
import math
from dataclasses import dataclass
from itertools import combinations
from typing import Any

from slamreplay.api.service.errors import ConflictError
from slamreplay.api.service.jobs import JobService
from slamreplay.api.service.store import JobRow
from slamreplay.replay.errors import ReplayError

MAX_RUNS = 20
ALL_PAIRS_UP_TO = 6  # beyond that many runs, each is linked against the first only (n - 1 links, not n(n-1)/2)
FIELD_NAMES = {"pipeline": "pipeline", "recording.sha256": "recording", "seed": "seed",
               "slamreplay.version": "code version", "slamreplay.git_commit": "code commit",
               "window_ns": "time window", "status": "status", "pipeline_origin.distribution": "pipeline package",
               "pipeline_origin.version": "pipeline package version"}


@dataclass(frozen=True, slots=True)
class Run:
    """A job as a comparison shows it: its row and its recording's uploaded file name."""

    job: JobRow
    recording: str

    @property
    def label(self) -> str:
        """``name`` or the short id, then pipeline, recording and seed."""
        j = self.job
        return f"{j.name or j.id[:8]}: {j.pipeline} on {self.recording}, seed {j.seed}"


def parse_runs(text: str) -> list[str]:
    """Job ids from ``id1,id2,...`` (whole ids; the middleware has resolved prefixes), in order, without repeats;
    ReplayError for fewer than two or more than MAX_RUNS."""
    ids = list(dict.fromkeys(p.strip() for p in text.split(",") if p.strip()))
    if len(ids) < 2:
        raise ReplayError("compare needs at least two runs: /compare?runs=ID1,ID2 (ids or their first 8 digits)")
    if len(ids) > MAX_RUNS:
        raise ReplayError(f"{len(ids)} runs: compare at most {MAX_RUNS} at once")
    return ids


def runs_of(jobs: JobService, ids: list[str]) -> list[Run]:
    """The jobs ``ids`` (NotFoundError for an unknown one), each with its recording's file name."""
    out = []
    for i in ids:
        job = jobs.get(i)
        rec = jobs.store.get_recording(job.recording_id)
        out.append(Run(job, rec.filename if rec is not None else job.recording_id[:8]))
    return out


def _specs() -> dict[str, Any]:
    """Every installed pipeline's metric specs by name (unit, direction, meaning); read once per comparison."""
    from slamreplay.api.service.runs_query import metric_specs

    return metric_specs()


def direction_text(better: str, target: float | None) -> str:
    """How to read a metric's change: lower / higher is better, closest to N, or none."""
    if better == "target" and target is not None:
        return f"closest to {target:g}"
    return {"lower": "lower is better", "higher": "higher is better"}.get(better, "none")


def _shown(value: Any) -> str:
    if value is None:
        return "—"
    return value if isinstance(value, str) else json.dumps(value)


def _manifest(jobs: JobService, job_id: str) -> dict[str, Any]:
    with contextlib.suppress(OSError, json.JSONDecodeError):
        doc = json.loads((jobs.run_dir(job_id) / "manifest.json").read_text())
        return doc if isinstance(doc, dict) else {}
    return {}


def what_changed(changes: list[dict[str, Any]], a: Run, b: Run, topic_maps: tuple[Any, Any]) -> list[dict[str, str]]:
    """The diff's manifest changes in the page's words: recordings by file name, config key by key; the config
    hash is left out (its keys are listed)."""
    out = []
    for c in changes:
        field, va, vb = c["field"], c["a"], c["b"]
        if field == "config_hash":
            continue
        if field == "recording.sha256":
            va, vb = f"{a.recording} ({str(va)[:8]})", f"{b.recording} ({str(vb)[:8]})"
        name = FIELD_NAMES.get(field) or (f"config {field[7:]}" if field.startswith("config.") else
                                          f"library {field[10:]}" if field.startswith("libraries.") else
                                          f"program {field[16:].replace('_sha256', ' sha256')}"
                                          if field.startswith("pipeline_origin.") else field)
        # a config key of one side's pipeline only: listed apart, as there are many when the pipelines differ
        only = field.startswith("config.") and (va is None or vb is None)
        out.append({"field": name, "a": _shown(va), "b": _shown(vb), "only": only})
    if (topic_maps[0] or {}) != (topic_maps[1] or {}):
        out.append({"field": "topic map", "a": _shown(topic_maps[0] or {}), "b": _shown(topic_maps[1] or {}),
                    "only": False})
    return out


def two_runs(jobs: JobService, ids: list[str], tolerances: dict[str, str] | None = None) -> dict[str, Any]:
    """Run B against run A as ``slamreplay diff`` judges it: changes, metric rows and verdict counts (the page adds
    the plots: ``slamreplay.api.web.compare_plots``)."""
    from slamreplay.replay.metric_registry import LOST
    from slamreplay.replay.runs.diff import diff_runs, formatted, verdict_text

    a, b = runs_of(jobs, ids)
    d = diff_runs(jobs.finished_run(a.job.id), jobs.finished_run(b.job.id), tolerances or {}, compare_rrd=False)
    ma, mb = _manifest(jobs, a.job.id), _manifest(jobs, b.job.id)
    maps = (ma.get("recording", {}).get("topic_map"), mb.get("recording", {}).get("topic_map"))
    rows, specs = [], _specs()
    for m in d.metrics:
        spec = specs.get(m.name)
        fa, fb, fd = formatted(m)
        rows.append({"name": m.name, "unit": spec.unit if spec is not None else "", "a": m.a, "b": m.b,
                     "a_text": fa, "b_text": fb, "delta": fd, "verdict": m.verdict, "verdict_text": verdict_text(m),
                     "direction": direction_text(m.better, m.target),
                     "meaning": spec.description if spec is not None else ""})
    rows.sort(key=lambda r: (r["verdict"] != LOST, r["verdict"] in ("added", "removed")))  # lost first, one side's last
    counts = {v: sum(r["verdict"] == v for r in rows) for v in ("better", "worse", "same", "changed", LOST)}
    counts["worse"] += counts.pop(LOST)
    return {"a": a, "b": b, "changes": what_changed(d.changes, a, b, maps), "metrics": rows, "counts": counts,
            "worse": d.worse, "programs": d.programs}


def _best(values: list[float | None], better: str, target: float | None) -> int | None:
    """Index of the best finite value by the metric's direction; None when there is no direction or one value."""
    from slamreplay.replay.metric_registry import target_distance

    finite = [(i, v) for i, v in enumerate(values) if v is not None and math.isfinite(v)]
    if len(finite) < 2 or better not in ("lower", "higher", "target"):
        return None
    if better == "target" and target is not None:
        key = [(target_distance(v, target), i) for i, v in finite]
    else:
        key = [(v if better == "lower" else -v, i) for i, v in finite]
    ranked = sorted(key)
    return None if ranked[0][0] == ranked[-1][0] else ranked[0][1]  # all equal: nothing stands out


def many_runs(jobs: JobService, ids: list[str]) -> dict[str, Any]:
    """Several runs side by side: their metrics (one column per run, units and direction from the registry, the
    best marked) and a link per pair to the two-run view (the page adds the plots)."""
    runs = runs_of(jobs, ids)
    values = [(r.job.metrics if r.job.metrics is not None else
               jobs.metric_values(r.job.id) if r.job.status == "succeeded" else {}) for r in runs]
    rows, specs = [], _specs()
    for name in sorted({n for v in values for n in v}):
        spec = specs.get(name)
        better, target = (spec.better, spec.target) if spec is not None else ("none", None)
        cells = [v.get(name) for v in values]
        rows.append({"name": name, "unit": spec.unit if spec is not None else "", "values": cells,
                     "direction": direction_text(better, target), "best": _best(cells, better, target),
                     "meaning": spec.description if spec is not None else ""})
    indexes = list(range(len(runs)))
    pairs = (list(combinations(indexes, 2)) if len(runs) <= ALL_PAIRS_UP_TO else [(0, i) for i in indexes[1:]])
    links = [{"a": runs[i], "b": runs[j], "ia": i + 1, "ib": j + 1,
              "href": f"/ui/compare?runs={runs[i].job.id},{runs[j].job.id}"} for i, j in pairs]
    return {"runs": runs, "metrics": rows, "pairs": links,
            "not_succeeded": [r for r in runs if r.job.status != "succeeded"]}


def runs_json(jobs: JobService, ids: list[str]) -> dict[str, Any]:
    """What ``GET /compare?runs=`` answers: for two runs the diff (changes, metric deltas and verdicts), for more
    the metrics side by side."""
    if len(ids) == 2:
        ctx = two_runs(jobs, ids)
        return {"a": ids[0], "b": ids[1], "a_label": ctx["a"].label, "b_label": ctx["b"].label,
                "changes": ctx["changes"], "worse": ctx["worse"], "programs": ctx["programs"],
                "metrics": [{k: r[k] for k in ("name", "unit", "a", "b", "delta", "verdict", "direction")}
                            for r in ctx["metrics"]], "page": f"/ui/compare?runs={','.join(ids)}"}
    ctx = many_runs(jobs, ids)
    return {"runs": [{"id": r.job.id, "label": r.label, "status": r.job.status} for r in ctx["runs"]],
            "metrics": [{"name": m["name"], "unit": m["unit"], "direction": m["direction"],
                         "values": [_finite(v) for v in m["values"]]} for m in ctx["metrics"]],
            "page": f"/ui/compare?runs={','.join(ids)}"}


def _finite(v: float | None) -> float | None:
    return v if v is not None and math.isfinite(v) else None


def require_succeeded(runs: list[Run]) -> None:
    """ConflictError naming the runs of a two-run diff that have not succeeded (a diff needs their metrics)."""
    bad = [r for r in runs if r.job.status != "succeeded"]
    if bad:
        raise ConflictError("; ".join(f"run {r.job.name or r.job.id[:8]} is {r.job.status}" for r in bad)
                            + ": only succeeded runs can be diffed; compare three or more to see any run's status")


def describe_side(side: Any) -> str:
    """One side of a suite comparison in a few words: ``odometry on sim.mcap (default, seed 1)``, or for a suite
    its cells and seeds."""
    rows = side.rows
    if len(rows) == 1:
        r = rows[0]
        return f"{r['pipeline']} on {r['recording']} ({r['variant']}, seed {r.get('seed', 0)})"
    cells = sorted({f"{r['pipeline']} on {r['recording']} ({r['variant']})" for r in rows})
    seeds = sorted({int(r.get("seed") or 0) for r in rows})
    shown = "; ".join(cells[:3]) + (f" and {len(cells) - 3} more" if len(cells) > 3 else "")
    return f"{len(rows)} runs: {shown}, seeds {', '.join(map(str, seeds))}"


def unpaired_reason(side_a: Any, side_b: Any) -> str:
    """Why nothing pairs, in one sentence."""
    return (f"A and B share no recording/pipeline/variant/seed cell, so there is nothing to pair: "
            f"A is {describe_side(side_a)}, B is {describe_side(side_b)}.")


def job_ids_of(side: Any, most: int = MAX_RUNS) -> list[str]:
    """The job ids of a side's rows (a suite's cells; not those deleted since), at most ``most``."""
    return list(dict.fromkeys(str(r["job_id"]) for r in side.rows
                              if r.get("job_id") and r.get("status") != "deleted"))[:most]
