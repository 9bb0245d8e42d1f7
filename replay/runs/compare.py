"""Compare two sets of runs cell by cell, and tell a regression from seed noise.

A and B are each a run directory or a suite results directory. Runs are grouped by
(recording, pipeline, variant) and, within a group, paired by their seeds (recording seed,
run seed): the same seeds on both sides, so each pair differs only by the code or the
configuration under test.

The statistic: a two-sided **paired t-test** (``scipy.stats.ttest_rel``) on the per-seed
differences B - A, at ``ALPHA`` = 0.05. Why this one:

- Suites have few seeds (3-5). Wilcoxon's signed-rank test cannot reach p < 0.05 below six
  pairs (its smallest two-sided p is 0.25 with 3 pairs, 0.125 with 4, 0.0625 with 5): with
  it, no regression could ever be detected. The t-test can, when the change is large
  against its spread across seeds, which is exactly the distinction wanted.
- Pairing removes the seed-to-seed variation shared by A and B (one seed's world is harder
  than another's for both versions), so a small but consistent change is seen, while a
  change whose sign flips from seed to seed is not.
- Replays are deterministic: identical code gives identical pairs. All differences equal
  to zero give p = 1; all equal and non-zero (a deterministic shift with no spread) give
  p = 0, where ``ttest_rel`` itself would divide by zero.

A **regression** is a metric that is significantly different (p < ALPHA) *and* worse than
A by more than its tolerance, in its direction (``MetricSpec.better``); an improvement
likewise. A significant change within tolerance, or a change beyond tolerance that is not
significant (seed noise), is ``unchanged`` / ``noise``. With one pair there is no spread to
test against: the verdict falls back to the tolerance alone, as ``slamreplay diff`` judges
it (``slamreplay.replay.runs.diff.judge_metric``). A run that succeeded in A and failed in B is a regression.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
from scipy import stats

from slamreplay.recorder.options import did_you_mean
from slamreplay.replay.errors import ReplayError
from slamreplay.replay.metric_registry import LOST, direction_label, optional_reason, target_distance
from slamreplay.replay.runs.diff import describe_origin, determinism_of, direction_verdict, judge_metric, origin_changes
from slamreplay.replay.runs.suite_run import add_metrics, read_results, unfinished

ALPHA = 0.05
VERDICT_ORDER = ("regression", "failed", LOST, "improvement", "noise", "unchanged", "changed", "missing")
REGRESSION_VERDICTS = ("regression", "failed", LOST)  # what fails the gate (exit 1)
# the "metric" of a cell's runs that failed in B: after succeeding in A, or failing in A as well (then nothing of
# the cell was compared, and a gate that passed would say B is fine)
RUN_STATUS, RUN_STATUS_BOTH = "(run status)", "(run status: failed in A too)"


@dataclass(frozen=True, slots=True)
class MetricResult:
    """One metric of one group: A and B over the paired seeds, and the verdict."""

    recording: str
    pipeline: str
    variant: str
    metric: str
    better: str
    unit: str
    seeds: list[list[int]]
    a: list[float]
    b: list[float]
    a_mean: float | None
    a_sd: float | None
    b_mean: float | None
    b_sd: float | None
    delta: float | None
    tolerance: float
    p_value: float | None
    test: str
    verdict: str  # regression | improvement | noise | unchanged | changed | failed | lost | missing
    target: float | None = None  # the consistent value, with better="target"

    @property
    def direction(self) -> str:
        """lower, higher, ~2 (closest to 2 is better) or none."""
        return direction_label(self.better, self.target)


@dataclass
class Side:
    """What one side of a comparison is: its rows and where they came from."""

    label: str
    rows: list[dict[str, Any]]
    kind: str  # run | results | rev
    code_versions: list[str] = field(default_factory=list)
    sha: str | None = None
    libraries: dict[str, str] = field(default_factory=dict)


@dataclass
class Comparison:
    a: Side
    b: Side
    results: list[MetricResult]
    changes: list[dict[str, Any]]
    commits: list[str] = field(default_factory=list)
    only_a: list[str] = field(default_factory=list)
    only_b: list[str] = field(default_factory=list)
    failures: list[dict[str, Any]] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)  # e.g. cells whose program is not deterministic
    programs: list[dict[str, str]] = field(default_factory=list)  # per cell with an external program: A's, B's

    @property
    def regressions(self) -> list[MetricResult]:
        return [r for r in self.results if r.verdict in REGRESSION_VERDICTS]

    def to_json(self) -> dict[str, Any]:
        return {"a": self.a.label, "b": self.b.label, "code_versions": {"a": self.a.code_versions,
                "b": self.b.code_versions}, "commits": self.commits, "changes": self.changes,
                "only_in_a": self.only_a, "only_in_b": self.only_b, "failures": self.failures, "notes": self.notes,
                "programs": self.programs, "results": [asdict(r) for r in self.results],
                "regressions": [f"{r.recording}/{r.pipeline}/{r.variant}: {r.metric}" for r in self.regressions]}


# ---------------------------------------------------------------------------------------
# Loading


def _run_row(run_dir: Path) -> dict[str, Any]:
    """A results row for a lone run directory (recording named by its file, variant ``default``)."""
    try:
        manifest = json.loads((run_dir / "manifest.json").read_text())
    except FileNotFoundError:
        raise ReplayError(f"{run_dir} has no manifest.json: it is neither a run nor a results directory") from None
    except json.JSONDecodeError as err:
        raise ReplayError(f"{run_dir}/manifest.json is not valid JSON: {err}") from None
    rec = manifest.get("recording", {})
    out: dict[str, Any] = {"recording": Path(rec.get("path", "recording")).name, "recording_seed": None,
                           "pipeline": manifest.get("pipeline"), "variant": "default", "seed": manifest.get("seed", 0),
                           "config": manifest.get("config", {}), "run_dir": str(run_dir),
                           "recording_sha256": rec.get("sha256"), "status": manifest.get("status"),
                           "error": manifest.get("error"), "code_version": manifest.get("slamreplay", {}).get(
                               "git_commit"), "metrics": {}, "better": {}, "tolerance": {}, "units": {}}
    if (deterministic := determinism_of(manifest)) is not None:
        out["deterministic"] = deterministic
    if out["status"] == "succeeded":
        try:
            metrics = json.loads((run_dir / "metrics.json").read_text())["metrics"]
        except (OSError, json.JSONDecodeError, KeyError) as err:
            raise ReplayError(f"{run_dir}/metrics.json is missing or unreadable: {err}") from None
        add_metrics(out, metrics)
    return out


def _origin(rows: Sequence[Mapping[str, Any]]) -> dict[str, Any] | None:
    """The ``pipeline_origin`` of a cell's first run whose manifest records one (None for older runs)."""
    for r in rows:
        try:
            origin = json.loads((Path(r["run_dir"]) / "manifest.json").read_text()).get("pipeline_origin")
        except (OSError, json.JSONDecodeError, KeyError, TypeError):
            continue
        if isinstance(origin, dict):
            return origin
    return None


def _libraries(rows: Sequence[Mapping[str, Any]]) -> dict[str, str]:
    for r in rows:
        try:
            return dict(json.loads((Path(r["run_dir"]) / "manifest.json").read_text()).get("libraries", {}))
        except (OSError, json.JSONDecodeError, KeyError):
            continue
    return {}


def load_side(path: str | Path, label: str | None = None, kind: str | None = None, sha: str | None = None) -> Side:
    """A run directory or a suite results directory as one side of a comparison."""
    p = Path(path)
    if not p.is_dir():
        raise ReplayError(f"{p} does not exist: give a run directory, a suite results directory, "
                          f"or rev:GITREV with --suite")
    if (why := unfinished(p)) is not None:
        raise ReplayError(why)
    if (p / "results.jsonl").is_file():
        rows, k = read_results(p), "results"
    else:
        rows, k = [_run_row(p)], "run"
    if not rows:
        raise ReplayError(f"{p}/results.jsonl has no rows: the suite ran no cells")
    return side_of_rows(label or str(p), rows, kind or k, sha)


def side_of_rows(label: str, rows: list[dict[str, Any]], kind: str, sha: str | None = None) -> Side:
    """One side from results rows (as ``results.jsonl`` holds them), e.g. a suite the service ran."""
    versions = sorted({str(r.get("code_version")) for r in rows})
    return Side(label, rows, kind, versions, sha, _libraries(rows))


def run_row(run_dir: Path) -> dict[str, Any]:
    """A results row for one run directory (recording named by its file, variant ``default``)."""
    return _run_row(run_dir)


# ---------------------------------------------------------------------------------------
# Statistics


def paired_test(a: Sequence[float], b: Sequence[float]) -> tuple[float | None, str]:
    """Two-sided p-value that B - A is centred on zero, and the test's name (see the module docstring)."""
    d = np.asarray(b, float) - np.asarray(a, float)
    if len(d) < 2:
        return None, "tolerance (one seed)"
    if np.all(d == 0):
        return 1.0, f"paired t-test, n={len(d)}"
    if np.ptp(d) == 0:
        return 0.0, f"paired t-test, n={len(d)} (constant shift)"
    p = float(stats.ttest_rel(b, a).pvalue)
    return (1.0 if math.isnan(p) else p), f"paired t-test, n={len(d)}"


def _sd(x: Sequence[float]) -> float | None:
    return float(np.std(x, ddof=1)) if len(x) > 1 else (0.0 if len(x) == 1 else None)


def judge(a: Sequence[float], b: Sequence[float], better: str, default_tolerance: float,
          tolerance_spec: str | None = None, rel_tolerance: float = 0.0, target: float | None = None
          ) -> tuple[float, float | None, float | None, str, str]:
    """(tolerance, delta of the means, p-value, test, verdict) of paired samples of one metric.

    ``default_tolerance`` and ``rel_tolerance`` are the metric's own (metrics.json), as ``diff`` uses them.
    A ``target`` metric (a NEES) is judged on each seed's distance from its target
    (``metric_registry.target_distance``): worse when B is further from it on average, and the paired
    test runs on those distances, so a filter that turns overconfident on every seed is a regression
    even where the raw values spread widely."""
    ma, mb = float(np.mean(a)), float(np.mean(b))
    entry = {"tolerance": default_tolerance, "rel_tolerance": rel_tolerance}
    plain = better if better != "target" else "lower" if target is not None else "none"  # "lower": a placeholder
    tol, delta, by_tol = judge_metric(ma, mb, plain, entry, tolerance_spec)
    if better == "target" and target is not None:
        da = [target_distance(x, target) for x in a]
        db = [target_distance(x, target) for x in b]
        if by_tol != "same":
            by_tol = direction_verdict(mb - ma, "target", float(np.mean(db)) - float(np.mean(da)))
        p, test = paired_test(da, db)
    else:
        p, test = paired_test(a, b)
    if by_tol == "same":
        return tol, delta, p, test, "unchanged"
    if by_tol == "changed":
        return tol, delta, p, test, "changed"
    significant = p is None or p < ALPHA
    if not significant:
        return tol, delta, p, test, "noise"
    return tol, delta, p, test, "regression" if by_tol == "worse" else "improvement"


def _key(r: Mapping[str, Any]) -> tuple[str, str, str]:
    return (str(r["recording"]), str(r["pipeline"]), str(r["variant"]))


def _replicate(r: Mapping[str, Any]) -> tuple[int, int]:
    rs = r.get("recording_seed")
    return (-1 if rs is None else int(rs), int(r.get("seed") or 0))


def compare(a: Side, b: Side, tolerances: Mapping[str, str] | None = None) -> Comparison:
    """Judge every metric of every group A and B have in common; ReplayError when they share none."""
    tolerances = dict(tolerances or {})
    if a.kind == "run" and b.kind == "run" and _key(a.rows[0]) != _key(b.rows[0]):
        b.rows[0] = {**b.rows[0], "recording": a.rows[0]["recording"]}  # two lone runs: compare them as one cell
    ga: dict[tuple[str, str, str], list[dict[str, Any]]] = {}
    gb: dict[tuple[str, str, str], list[dict[str, Any]]] = {}
    for rows, groups in ((a.rows, ga), (b.rows, gb)):
        for r in rows:
            groups.setdefault(_key(r), []).append(r)
    common = [k for k in ga if k in gb]
    if not common:
        raise ReplayError(f"{a.label} and {b.label} have no cell in common (cells are matched by recording, "
                          f"pipeline and variant): A has {', '.join('/'.join(k) for k in sorted(ga))}; "
                          f"B has {', '.join('/'.join(k) for k in sorted(gb))}")
    known = {m for r in (*a.rows, *b.rows) for m in r.get("metrics", {})}
    unknown = set(tolerances) - known - {"*"}
    if unknown:
        hint = "".join(did_you_mean(name, known, quote=True) for name in sorted(unknown))
        raise ReplayError(f"--tolerance names unknown metrics: {', '.join(sorted(unknown))}{hint}; "
                          f"the runs have: {', '.join(sorted(known))}")
    out = Comparison(a, b, [], [], only_a=["/".join(k) for k in ga if k not in gb],
                     only_b=["/".join(k) for k in gb if k not in ga])
    for key in common:
        ra = {_replicate(r): r for r in ga[key]}
        rb = {_replicate(r): r for r in gb[key]}
        seeds = sorted(set(ra) & set(rb))
        ok = [s for s in seeds if ra[s]["status"] == "succeeded" and rb[s]["status"] == "succeeded"]
        for s in seeds:
            for side, rr in (("A", ra[s]), ("B", rb[s])):
                if rr["status"] != "succeeded":
                    out.failures.append({"side": side, "cell": "/".join(key), "seeds": list(s),
                                         "error": rr.get("error"), "run_dir": rr.get("run_dir")})
        failed_b = [s for s in seeds if rb[s]["status"] != "succeeded"]
        for name, which in ((RUN_STATUS, [s for s in failed_b if ra[s]["status"] == "succeeded"]),
                            (RUN_STATUS_BOTH, [s for s in failed_b if ra[s]["status"] != "succeeded"])):
            if which:  # a B that does not run fails the gate, whether or not A ran: nothing else says it broke
                out.results.append(MetricResult(*key, name, "none", "", [list(s) for s in which], [], [],
                                                None, None, None, None, None, 0.0, None, "status", "failed"))
        oa, ob = _origin(ga[key]), _origin(gb[key])
        out.changes += origin_changes(oa, ob, prefix=f"{'/'.join(key)} ")
        if describe_origin(oa) or describe_origin(ob):
            out.programs.append({"cell": "/".join(key), "A": describe_origin(oa), "B": describe_origin(ob)})
        cfg_a, cfg_b = ga[key][0].get("config", {}), gb[key][0].get("config", {})
        for k in sorted(set(cfg_a) | set(cfg_b)):
            if cfg_a.get(k) != cfg_b.get(k):
                out.changes.append({"field": f"{'/'.join(key)} config.{k}", "a": cfg_a.get(k), "b": cfg_b.get(k)})
        names = sorted({m for s in ok for m in (*ra[s]["metrics"], *rb[s]["metrics"])})
        for name in names:
            pairs = [s for s in ok if name in ra[s]["metrics"] and name in rb[s]["metrics"]]
            spec = next(r for r in (*[rb[s] for s in ok], *[ra[s] for s in ok]) if name in r["metrics"])
            better, unit = spec["better"].get(name, "none"), spec.get("units", {}).get(name, "")
            lost = [s for s in ok if name in ra[s]["metrics"] and name not in rb[s]["metrics"]]
            if lost and not optional_reason(name, {"optional": spec.get("optional", {}).get(name)}):
                va = [float(ra[s]["metrics"][name]) for s in lost]
                out.results.append(MetricResult(*key, name, better, unit, [list(s) for s in lost], va, [],
                                                float(np.mean(va)), _sd(va), None, None, None, 0.0, None,
                                                f"missing in B ({len(lost)} of {len(ok)} seeds)", LOST,
                                                spec.get("targets", {}).get(name)))
                continue
            if not pairs:
                out.results.append(MetricResult(*key, name, better, unit, [], [], [], None, None, None, None,
                                                None, 0.0, None, "", "missing"))
                continue
            va = [float(ra[s]["metrics"][name]) for s in pairs]
            vb = [float(rb[s]["metrics"][name]) for s in pairs]
            target = spec.get("targets", {}).get(name)
            tol, delta, p, test, verdict = judge(va, vb, better, float(spec["tolerance"].get(name, 0.0)),
                                                 tolerances.get(name, tolerances.get("*")),
                                                 float(spec.get("rel_tolerance", {}).get(name, 0.0)), target)
            out.results.append(MetricResult(*key, name, better, unit, [list(s) for s in pairs], va, vb,
                                            float(np.mean(va)), _sd(va), float(np.mean(vb)), _sd(vb), delta, tol,
                                            p, test, verdict, target))
    for lib in sorted(set(a.libraries) | set(b.libraries)):
        if a.libraries.get(lib) != b.libraries.get(lib):
            out.changes.append({"field": f"library {lib}", "a": a.libraries.get(lib), "b": b.libraries.get(lib)})
    flaky = sorted({"/".join(_key(r)) for r in (*a.rows, *b.rows) if r.get("deterministic") is False})
    if flaky:
        out.results = judge_not_deterministic(out.results, set(flaky))
        out.notes.append(f"not deterministic (two runs of its program on the same input differed): "
                         f"{', '.join(flaky)}; judged by the spread over seeds alone (paired t-tests, Holm-adjusted "
                         f"over all their metrics; one seed: no verdict), never by the tolerances alone")
    return out


def judge_not_deterministic(results: list[MetricResult], cells: set[str]) -> list[MetricResult]:
    """The verdicts of ``cells`` (their program is not deterministic) judged by seed spread alone.

    The same seed gives another result at each run, so a change beyond the tolerance says nothing by itself:
    with one seed there is nothing to judge ("noise", the test says why), and with several the paired
    t-tests of all these cells' metrics are adjusted together by Holm's step-down method (Holm 1979), so
    that one comparison of unchanged code reports a regression with probability at most ``ALPHA`` however
    many metrics the program reports (a plain test per metric would: 8 metrics, about 1 in 3)."""
    mine = [i for i, r in enumerate(results) if f"{r.recording}/{r.pipeline}/{r.variant}" in cells and
            r.verdict in ("regression", "improvement", "noise")]
    out = list(results)
    tested = sorted((i for i in mine if results[i].p_value is not None), key=lambda i: results[i].p_value or 0.0)
    running = 0.0
    for rank, i in enumerate(tested):
        r = results[i]
        running = max(running, min(1.0, (len(tested) - rank) * float(r.p_value or 0.0)))
        verdict = r.verdict if r.verdict == "noise" or running < ALPHA else "noise"
        out[i] = replace(r, p_value=running, test=f"{r.test}, Holm over {len(tested)}", verdict=verdict)
    for i in mine:
        if results[i].p_value is None:
            out[i] = replace(results[i], verdict="noise", test="one seed of a program that is not deterministic: "
                                                               "no spread to judge a change by; run more seeds")
    return out


def format_table(c: Comparison) -> str:
    """Plain-text table for the terminal."""
    lines = [f"A: {c.a.label}  ({', '.join(c.a.code_versions)})", f"B: {c.b.label}  ({', '.join(c.b.code_versions)})"]
    if c.commits:
        lines.append(f"commits A..B: {len(c.commits)}")
        lines += [f"  {line}" for line in c.commits[:20]]
    for ch in c.changes:
        lines.append(f"changed: {ch['field']}: {ch['a']!r} -> {ch['b']!r}")
    lines += program_lines(c)
    lines.append("")
    lines.append(f"  {'cell':<40} {'metric':<26} {'A mean±sd':>20} {'B mean±sd':>20} {'B - A':>11} {'p':>7}  verdict")
    for r in c.results:
        cell = f"{r.recording}/{r.pipeline}/{r.variant}"
        verdict = r.verdict.upper() if r.verdict in REGRESSION_VERDICTS else r.verdict
        lines.append(f"  {cell:<40} {r.metric:<26} {fmt_ms(r.a_mean, r.a_sd):>20} {fmt_ms(r.b_mean, r.b_sd):>20} "
                     f"{fmt(r.delta, signed=True):>11} {fmt(r.p_value, 3):>7}  {verdict}")
    for f in c.failures:
        lines.append(f"failed in {f['side']}: {f['cell']} seeds {f['seeds']}: {f['error']}")
    lines += [f"note: {n}" for n in c.notes]
    if c.only_a or c.only_b:
        lines.append(f"not compared: only in A: {', '.join(c.only_a) or '-'}; only in B: {', '.join(c.only_b) or '-'}")
    reg = c.regressions
    lines.append(f"Result: {len(reg)} regression(s)" + (": " + ", ".join(
        f"{r.recording}/{r.pipeline}/{r.variant} {r.metric}" for r in reg) if reg else ""))
    return "\n".join(lines)


def program_lines(c: Comparison) -> list[str]:
    """The external programs each side ran, per cell (one line when A's and B's are the same)."""
    out = []
    for p in c.programs:
        if p["A"] == p["B"]:
            out.append(f"program {p['cell']}: {p['A']} (A and B)")
        else:
            out += [f"program {p['cell']} A: {p['A'] or '-'}", f"program {p['cell']} B: {p['B'] or '-'}"]
    return out


def variants_table(rows: list[dict[str, Any]]) -> str:
    """One results directory's figures side by side: per recording and pipeline, each metric (a row) by variant
    (a column), the mean ± sd over the cell's seeds that succeeded. What ``suite run`` prints at its end."""
    tables: dict[tuple[str, str], dict[str, list[dict[str, Any]]]] = {}
    for r in rows:
        tables.setdefault((r["recording"], r["pipeline"]), {}).setdefault(r["variant"], []).append(r)
    lines: list[str] = []
    for (recording, pipeline), variants in tables.items():
        ok = {v: [r for r in rs if r["status"] == "succeeded"] for v, rs in variants.items()}
        better: dict[str, str] = {}
        for rs in ok.values():
            for r in rs:
                better.update({m: r.get("better", {}).get(m, "none") for m in r.get("metrics", {})})
        heads = [f"{v} ({len(ok[v])}/{len(rs)} ok)" for v, rs in variants.items()]
        width = max([20, *map(len, heads)])
        lines.append(f"{recording} / {pipeline}")
        lines.append(f"  {'metric':<30}   " + " ".join(f"{h:>{width}}" for h in heads))
        for m in sorted(better):
            cells = []
            for v in variants:
                vals = np.array([r["metrics"][m] for r in ok[v] if r["metrics"].get(m) is not None], dtype=float)
                vals = vals[np.isfinite(vals)]
                cells.append("-" if not vals.size else fmt_ms(float(vals.mean()),
                                                               float(vals.std(ddof=1)) if vals.size > 1 else None))
            arrow = {"lower": "l", "higher": "h", "target": "t"}.get(better[m], " ")
            lines.append(f"  {m:<30} {arrow} " + " ".join(f"{c:>{width}}" for c in cells))
        lines.append("")
    if lines:
        lines.append("(l: lower is better, h: higher, t: closest to its target, e.g. a NEES; blank: neither; "
                     "mean ± sd over the seeds; "
                     "`slamreplay compare` tests A against B)")
    return "\n".join(lines)


def fmt(x: float | None, digits: int = 4, signed: bool = False) -> str:
    if x is None or not math.isfinite(x):
        return "-"
    return f"{x:+.{digits}g}" if signed else f"{x:.{digits}g}"


def fmt_ms(mean: float | None, sd: float | None) -> str:
    return "-" if mean is None else f"{mean:.4g} ± {fmt(sd, 2)}"
