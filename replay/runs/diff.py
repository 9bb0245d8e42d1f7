"""Diff two runs: what changed between them, and whether results got better or worse.

- Manifests: pipeline, recording, configuration (key by key), seed, code version and
  commit, library versions.
- Metrics: a delta per metric, judged by its direction (lower or higher is better, or closer
  to a target value such as a NEES's degrees of freedom, on a log scale) and a
  tolerance (``metric_tolerance``: by default relative to run A's value with an absolute floor,
  so numerical noise between environments is "same"; a user's absolute value or ``N%`` of run
  A's value replaces it); ``worse`` lists those that regressed.
- Content: whether the two ``run.rrd`` files hold the same data (``rerun rrd compare``).
- Optionally one comparison ``.rrd`` with both runs under ``runs/A/...`` and ``runs/B/...``.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from slamreplay.recorder.options import did_you_mean
from slamreplay.replay.errors import ReplayError
from slamreplay.replay.metric_registry import LOST, direction_label, normalize, optional_reason, target_distance
from slamreplay.replay.runs.rrd_compare import rrd_content_equal
from slamreplay.replay.tools.determinism import PROGRAM_FIELDS

MANIFEST_FIELDS = ("pipeline", "recording.sha256", "seed", "config_hash", "slamreplay.version",
                   "slamreplay.git_commit", "window_ns", "status")


@dataclass(frozen=True, slots=True)
class MetricDelta:
    name: str
    a: float | None
    b: float | None
    delta: float | None
    better: str
    tolerance: float
    verdict: str  # better | worse | same | changed | added | lost | removed (an optional metric left out)
    target: float | None = None  # the consistent value, with better="target"
    note: str = ""  # why: "missing in B", or the reason an optional metric may be left out

    @property
    def direction(self) -> str:
        """The ``better`` column of a table: lower, higher, ~2 (closest to 2), or none."""
        return direction_label(self.better, self.target)


@dataclass
class RunDiff:
    a: str
    b: str
    changes: list[dict[str, Any]] = field(default_factory=list)
    metrics: list[MetricDelta] = field(default_factory=list)
    rrd_equal: bool | None = None
    rrd_detail: str = ""
    notes: list[str] = field(default_factory=list)  # e.g. a run found not deterministic (docs/external.md)
    programs: dict[str, str] = field(default_factory=dict)  # "A"/"B" -> an external program's identity, in words

    @property
    def worse(self) -> list[str]:
        """Metrics that regressed: worse beyond their tolerance, or lost (in A, not in B)."""
        return [m.name for m in self.metrics if m.verdict in ("worse", LOST)]

    @property
    def lost(self) -> list[str]:
        return [m.name for m in self.metrics if m.verdict == LOST]

    def to_json(self) -> dict[str, Any]:
        return {"a": self.a, "b": self.b, "changes": self.changes, "metrics": [asdict(m) for m in self.metrics],
                "worse": self.worse, "lost": self.lost, "programs": self.programs, "rrd_equal": self.rrd_equal,
                "rrd_detail": self.rrd_detail, "notes": self.notes}


def load_run(run_dir: Path, failed_ok: bool = False) -> tuple[dict[str, Any], dict[str, Any]]:
    """(manifest, metrics document) of a finished run; ReplayError saying what is missing. ``failed_ok``: a
    run that ended (failed, interrupted) has an empty metrics document instead of an error."""
    if not run_dir.is_dir():
        raise ReplayError(f"{run_dir} is not a run directory (it does not exist)")
    try:
        manifest = json.loads((run_dir / "manifest.json").read_text())
    except FileNotFoundError:
        raise ReplayError(f"{run_dir} has no manifest.json: it is not a finished run") from None
    except json.JSONDecodeError as err:
        raise ReplayError(f"{run_dir}/manifest.json is not valid JSON: {err}") from err
    if failed_ok and manifest.get("status") in ("failed", "interrupted"):
        return manifest, {"metrics": {}}
    if manifest.get("status") != "succeeded":
        raise ReplayError(f"{run_dir} did not succeed (status {manifest.get('status')!r}: {manifest.get('error')}); "
                          f"only successful runs can be compared")
    try:
        metrics = json.loads((run_dir / "metrics.json").read_text())
    except (FileNotFoundError, json.JSONDecodeError) as err:
        raise ReplayError(f"{run_dir}/metrics.json is missing or unreadable: {err}") from err
    metrics["metrics"] = normalize(metrics.get("metrics", {}))  # names and directions of older runs
    return manifest, metrics


def parse_tolerances(items: list[str]) -> dict[str, str]:
    """``["ate=0.01", "*=1%"]`` -> mapping; ReplayError for a malformed item."""
    out = {}
    for item in items:
        name, sep, value = item.partition("=")
        if not sep or not name or not value:
            raise ReplayError(f"--tolerance expects NAME=VALUE or NAME=N%, got {item!r}")
        try:
            float(value.rstrip("%"))
        except ValueError:
            raise ReplayError(f"--tolerance {item!r}: {value!r} is not a number or percentage") from None
        out[name] = value
    return out


# What a run's ``pipeline_origin`` says about the code that made it, beside slamreplay's own commit: a plugin's
# distribution and version; an external program's version string, command, build command and the sha256 of its
# executable, its declaration and each file its command names (docs/external.md); an evaluated estimate file's
# sha256. Paths are left out: the same program on another machine is the same program.
ORIGIN_FIELDS = ("distribution", *PROGRAM_FIELDS, "sha256")


def _origin_items(origin: Mapping[str, Any] | None) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for key in ORIGIN_FIELDS:
        value = (origin or {}).get(key)
        if key == "files_sha256" and isinstance(value, Mapping):
            out.update({f"files_sha256.{name}": h for name, h in value.items()})
        elif value not in (None, "", [], {}):
            out[key] = value
    return out


def origin_changes(oa: Mapping[str, Any] | None, ob: Mapping[str, Any] | None, prefix: str = ""
                   ) -> list[dict[str, Any]]:
    """Each field of two runs' ``pipeline_origin`` (``ORIGIN_FIELDS``, a file's hash each) that differs, as a
    change ``{"field": "pipeline_origin.executable_sha256", "a": ..., "b": ...}``; none when either run predates
    origins. Two runs of programs with different hashes are never "nothing changed"."""
    if not oa or not ob:
        return []
    ia, ib = _origin_items(oa), _origin_items(ob)
    return [{"field": f"{prefix}pipeline_origin.{key}", "a": ia.get(key), "b": ib.get(key)}
            for key in sorted(set(ia) | set(ib)) if ia.get(key) != ib.get(key)]


def describe_origin(origin: Mapping[str, Any] | None) -> str:
    """An external program's or estimate file's identity in one line: version, command, build command and
    hashes (12 digits); "" for a built-in or plugin pipeline, whose code is slamreplay's commit or its package."""
    items = _origin_items(origin)
    if not any("sha256" in key for key in items):
        return ""
    words = []
    for key, value in items.items():
        if key == "distribution":
            continue
        if "sha256" in key:
            label = {"executable_sha256": "executable", "declaration_sha256": "declaration",
                     "sha256": "file"}.get(key) or f"file {key.split('.', 1)[1]}"
            words.append(f"{label} {str(value)[:12]}")
        else:
            words.append(f"{key} {' '.join(value) if isinstance(value, list) else value!s}")
    return f"{items.get('distribution', 'program')}: " + ", ".join(words)


def metric_tolerance(entry: Mapping[str, Any], a: float | None, override: str | None = None) -> float:
    """The change of a metric that still counts as "same": ``|B - A| <= metric_tolerance(...)``.

    The one place that decides it (``diff`` and comparisons of suites alike).

    Parameters
    ----------
    entry : a metric's entry in metrics.json: ``tolerance`` (absolute floor) and ``rel_tolerance``
        (fraction of the baseline's value; absent in runs made before it existed: 0)
    a : the baseline's (run A's) value
    override : a user's ``--tolerance`` value, absolute (``"0.01"``) or a percentage of A (``"1%"``);
        it replaces the default

    The default is ``max(tolerance, rel_tolerance * |A|)``: relative, so that floating-point
    noise between environments (other numpy/scipy/BLAS, another summation order) is absorbed at
    any scale, with an absolute floor for values near zero. Measured metrics get 0.1 % and 1e-6
    (``slamreplay.replay.engine.pipeline.MEASURED_REL_TOLERANCE``: a 1 % change is still worse); counts get 0.
    """
    if override is not None:
        if override.endswith("%"):
            return abs(a or 0.0) * float(override[:-1]) / 100.0
        return float(override)
    floor = float(entry.get("tolerance", 0.0))
    rel = float(entry.get("rel_tolerance", 0.0))
    return max(floor, rel * abs(a or 0.0))


def direction_verdict(delta: float, better: str, distance_delta: float = 0.0) -> str:
    """better | worse | changed for a change beyond the tolerance: by its sign, or for a ``target`` metric by
    ``distance_delta``, how much further from the target B is than A (``metric_registry.target_distance``)."""
    if better == "target":
        return "worse" if distance_delta > 0 else "better" if distance_delta < 0 else "changed"
    if better not in ("lower", "higher"):
        return "changed"
    return "better" if (delta < 0 if better == "lower" else delta > 0) else "worse"


def _verdict(a: float | None, b: float | None, better: str, tol: float, target: float | None = None
             ) -> tuple[float | None, str]:
    if a is None and b is None:
        return None, "same"
    if a is None:
        return None, "added"
    if b is None:
        return None, "worse" if better != "none" else "changed"
    delta = b - a
    if abs(delta) <= tol:
        return delta, "same"
    away = target_distance(b, target) - target_distance(a, target) if better == "target" and target else 0.0
    return delta, direction_verdict(delta, better, away)


def judge_metric(a: float, b: float, better: str, entry: Mapping[str, Any], tolerance_spec: str | None = None
                 ) -> tuple[float, float | None, str]:
    """(tolerance, B - A, verdict) of one metric, judged exactly as ``diff_runs`` judges it.

    ``entry`` holds the metric's own ``tolerance``, ``rel_tolerance`` and, for ``better="target"``, its
    ``target`` (metrics.json); ``tolerance_spec`` is a ``--tolerance`` value (absolute, or ``N%`` of A) that
    replaces the tolerances. Verdicts: better | worse | same | changed.
    """
    tol = metric_tolerance(entry, a, tolerance_spec)
    delta, verdict = _verdict(a, b, better, tol, entry.get("target"))
    return tol, delta, verdict


def _get(doc: Mapping[str, Any], dotted: str) -> Any:
    for part in dotted.split("."):
        doc = doc.get(part, {}) if isinstance(doc, Mapping) else {}
    return None if doc == {} else doc


def diff_runs(a_dir: str | Path, b_dir: str | Path, tolerances: Mapping[str, str] | None = None,
              compare_rrd: bool = True) -> RunDiff:
    """Compare run B against run A (the baseline)."""
    a_dir, b_dir = Path(a_dir), Path(b_dir)
    (ma, xa), (mb, xb) = load_run(a_dir), load_run(b_dir, failed_ok=True)  # B failing is its worst regression
    tolerances = dict(tolerances or {})
    known = set(xa.get("metrics", {})) | set(xb.get("metrics", {}))
    unknown = set(tolerances) - known - {"*"}
    if unknown:
        hint = "".join(did_you_mean(name, known, quote=True) for name in sorted(unknown))
        raise ReplayError(f"--tolerance names unknown metrics: {', '.join(sorted(unknown))}{hint}; "
                          f"the runs have: {', '.join(sorted(known))}")
    out = RunDiff(str(a_dir), str(b_dir))
    for side, m in (("A", ma), ("B", mb)):
        if determinism_of(m) is False:
            out.notes.append(f"run {side} is not deterministic (--check-determinism: two runs of its program on the "
                             f"same input differed): a metric change within the tolerances is noise, and the run.rrd "
                             f"content is not expected to match; compare over seeds (`slamreplay compare`)")
    if mb.get("status") != "succeeded":
        out.notes.append(f"run B {mb.get('status')}: {mb.get('error')}; every metric of A is missing in B")
    for key in MANIFEST_FIELDS:
        va, vb = _get(ma, key), _get(mb, key)
        if va != vb:
            out.changes.append({"field": key, "a": va, "b": vb})
    out.changes += origin_changes(ma.get("pipeline_origin"), mb.get("pipeline_origin"))
    shown = {side: describe_origin(m.get("pipeline_origin")) for side, m in (("A", ma), ("B", mb))}
    out.programs = {side: text for side, text in shown.items() if text}
    for section in ("config", "libraries"):
        ca, cb = ma.get(section, {}), mb.get(section, {})
        for key in sorted(set(ca) | set(cb)):
            if ca.get(key) != cb.get(key):
                out.changes.append({"field": f"{section}.{key}", "a": ca.get(key), "b": cb.get(key)})
    for name in sorted(known):
        ea, eb = xa["metrics"].get(name), xb["metrics"].get(name)
        spec = eb or ea
        if ea is None:
            out.metrics.append(MetricDelta(name, None, eb["value"], None, spec["better"], 0.0, "added",
                                           spec.get("target")))
            continue
        if eb is None:
            why = optional_reason(name, ea)
            failed = mb.get("status") != "succeeded"  # a run that failed lost even its optional metrics
            out.metrics.append(MetricDelta(name, ea["value"], None, None, spec["better"], 0.0,
                                           "removed" if why and not failed else LOST, spec.get("target"),
                                           f"optional: {why}" if why and not failed else "missing in B"))
            continue
        tol = metric_tolerance(spec, ea["value"], tolerances.get(name, tolerances.get("*")))
        delta, verdict = _verdict(ea["value"], eb["value"], spec["better"], tol, spec.get("target"))
        out.metrics.append(MetricDelta(name, ea["value"], eb["value"], delta, spec["better"], tol, verdict,
                                       spec.get("target")))
    if compare_rrd and mb.get("status") != "succeeded":
        out.rrd_detail = "run B has no run.rrd (it did not succeed)"
    elif compare_rrd:
        out.rrd_equal, out.rrd_detail = rrd_content_equal(a_dir / "run.rrd", b_dir / "run.rrd")
    return out


def formatted(m: MetricDelta) -> tuple[str, str, str]:
    """A, B and B - A of a metric as a diff shows them ("-" where absent)."""
    fa = "-" if m.a is None else f"{m.a:.6g}"
    fb = "-" if m.b is None else f"{m.b:.6g}"
    fd = "" if m.delta is None or not math.isfinite(m.delta) else f"{m.delta:+.4g}"
    return fa, fb, fd


def verdict_text(m: MetricDelta) -> str:
    """A metric's verdict as every view of a diff shows it: WORSE, better, same, "WORSE (missing in B)", ..."""
    if m.verdict == LOST:
        return "WORSE (missing in B)"
    if m.verdict == "removed":
        return f"only in A ({m.note})" if m.note else "only in A"
    if m.verdict == "added":
        return "only in B"
    return "WORSE" if m.verdict == "worse" else m.verdict


def determinism_of(manifest: Mapping[str, Any]) -> bool | None:
    """Whether a run's program was found deterministic (``--check-determinism``); None when not checked."""
    run = manifest.get("pipeline_run")
    det = run.get("determinism") if isinstance(run, Mapping) else None
    value = det.get("deterministic") if isinstance(det, Mapping) else None
    return value if isinstance(value, bool) else None


def format_table(diff: RunDiff) -> str:
    """Human-readable diff."""
    lines = [f"A: {diff.a}", f"B: {diff.b}", ""]
    lines += [f"note: {n}" for n in diff.notes] + ([""] if diff.notes else [])
    if diff.changes:
        lines.append("What changed:")
        for c in diff.changes:
            lines.append(f"  {c['field']}: {json.dumps(c['a'])} -> {json.dumps(c['b'])}")
    else:
        lines.append("What changed: nothing (same recording, pipeline, config, seed and code" +
                     (", same program" if diff.programs else "") + ")")
    lines += [f"  program {side}: {text}" for side, text in diff.programs.items()]
    lines.append("")
    width = max([len(m.name) for m in diff.metrics] + [6])
    lines.append(f"  {'metric':<{width}}  {'A':>14}  {'B':>14}  {'B - A':>12}  better  verdict")
    for m in diff.metrics:
        fa, fb, fd = formatted(m)
        lines.append(f"  {m.name:<{width}}  {fa:>14}  {fb:>14}  {fd:>12}  {m.direction:<6}  {verdict_text(m)}")
    lines.append("")
    rrd = {True: "identical content", False: f"content differs ({diff.rrd_detail})", None: diff.rrd_detail}
    lines.append(f"run.rrd: {rrd[diff.rrd_equal]}")
    lines.append(f"Result: {len(diff.worse)} metric(s) worse" + (f": {', '.join(diff.worse)}" if diff.worse else ""))
    return "\n".join(lines)
