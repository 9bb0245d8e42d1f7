"""Where a metric's level changed over a history of commits: binary segmentation with two gates.

Input, per cell group (recording, pipeline, variant) and metric: at each commit the values of its
seeds (recording seed x run seed). The detector works on the per-commit means and says a commit
starts a new level when all three of these hold:

1. **Step against the commit-to-commit noise.** Binary segmentation (Vostrikova 1981; the
   threshold of Fryzlewicz 2014, "Wild binary segmentation"): in a segment of the history the
   split maximizing the CUSUM statistic ``sqrt(nL nR / (nL + nR)) |mean(left) - mean(right)|`` is a
   candidate if that statistic exceeds ``C sigma sqrt(2 ln n)``, with n the commits with data,
   ``C`` = ``THRESHOLD_C``, n at least ``MIN_LOG_N`` (in a short history sigma, from few
   differences, is itself uncertain), and ``sigma`` the noise of the per-commit means estimated
   robustly from their successive differences other than the candidate's own
   (``1.4826 median|diff| / sqrt 2``: a few steps among many commits do not inflate it, and
   two or three commits are not taken for their own noise). Over n commits of pure noise the
   largest CUSUM statistic stays below that threshold with high probability, so a flat metric is
   not split however long its history. Replays are deterministic: a metric that no commit
   touches has identical means and zero statistics, and is never split.
2. **Step against the seed spread.** The per-seed means of the two sides are compared exactly as
   ``slamreplay compare`` compares two revisions (:func:`slamreplay.replay.runs.compare.judge`: a
   paired t-test over the seeds at ``ALPHA``, tolerance, direction): a shift that is not consistent
   across seeds (the worlds disagree) is noise, not a change.
3. **Beyond the metric's tolerance**, in its direction from the metric registry (lower, higher, a
   target value, or none: "changed"), also from ``judge``.

Segments are split recursively until no candidate passes. Each change is then judged again
between the whole segments around it (its size is the difference of their means), and named by
the first commit of the new level and the commit with data before it.

Why not ``ruptures``: its penalized detectors need the same noise scale (which has to come from
somewhere, here the differences), it knows nothing of seeds or of a metric's direction and
tolerance, and this is forty lines of numpy over histories of at most a few hundred commits.
Measured on synthetic histories (``benchmarks/history_changepoints.py``): see docs/compare.md.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from slamreplay.replay.metric_registry import LOST, optional_reason
from slamreplay.replay.runs.compare import judge

if TYPE_CHECKING:
    from slamreplay.replay.runs.history import History

THRESHOLD_C = 1.3
MIN_LOG_N = 50  # short histories: sigma from few differences is itself uncertain
CHANGE_VERDICTS = ("regression", "improvement", "changed")


@dataclass(frozen=True, slots=True)
class Step:
    """A change in one series: ``index`` the first point of the new level, ``before`` the point before it."""

    index: int
    before: int
    mean_before: float
    mean_after: float
    delta: float
    p_value: float | None
    verdict: str  # regression | improvement | changed


@dataclass(frozen=True, slots=True)
class Change:
    """A change of one metric of one cell group at one commit, with the commit before it."""

    recording: str
    pipeline: str
    variant: str
    metric: str
    unit: str
    better: str
    commit: str
    previous: str
    index: int  # position of ``commit`` in the history's commits
    mean_before: float
    mean_after: float | None  # None: lost (the cell ran and did not report the metric)
    delta: float | None
    relative: float | None
    p_value: float | None
    verdict: str  # regression | improvement | changed | lost
    report: str | None = None  # the compare report of previous -> commit, relative to the history directory

    @property
    def cell(self) -> str:
        return f"{self.recording}/{self.pipeline}/{self.variant}"

    def to_json(self) -> dict[str, Any]:
        return asdict(self)


def noise_sigma(means: Sequence[float]) -> float:
    """Robust standard deviation of a series' noise from its successive differences (median absolute value)."""
    d = np.abs(np.diff(np.asarray(means, float)))
    return float(1.4826 * np.median(d) / math.sqrt(2)) if len(d) else 0.0


def _seed_means(points: Sequence[dict[int, float]]) -> dict[int, float]:
    """Each seed's mean over the points of a segment."""
    acc: dict[int, list[float]] = {}
    for p in points:
        for s, v in p.items():
            acc.setdefault(s, []).append(v)
    return {s: float(np.mean(v)) for s, v in acc.items()}


def _judge(left: Sequence[dict[int, float]], right: Sequence[dict[int, float]], better: str, tolerance: float,
           rel_tolerance: float, target: float | None) -> tuple[float | None, float | None, str]:
    """(delta of the paired means, p-value, verdict) of two segments, as ``compare`` judges two revisions."""
    a, b = _seed_means(left), _seed_means(right)
    seeds = sorted(set(a) & set(b))
    if not seeds:
        return None, None, "missing"
    with warnings.catch_warnings():  # differences equal up to rounding: scipy warns of its precision, p is ~0
        warnings.simplefilter("ignore", RuntimeWarning)
        _tol, delta, p, _test, verdict = judge([a[s] for s in seeds], [b[s] for s in seeds], better, tolerance,
                                               None, rel_tolerance, target)
    return delta, p, verdict


def find_steps(values: Sequence[dict[int, float]], better: str, tolerance: float = 0.0, rel_tolerance: float = 0.0,
               target: float | None = None, c: float = THRESHOLD_C) -> list[Step]:
    """The changes of level in one series (see the module docstring).

    Parameters
    ----------
    values : per point (commit, in history order) the values by seed index; empty where no run succeeded
    better, tolerance, rel_tolerance, target : the metric's direction and diff tolerance (its metrics.json)
    c : the threshold's constant (``THRESHOLD_C``)
    """
    pts = [k for k, v in enumerate(values) if v]
    if len(pts) < 2:
        return []
    m = np.array([np.mean(list(values[k].values())) for k in pts])
    diffs = np.abs(np.diff(m))
    scale = c * math.sqrt(2 * math.log(max(len(pts), MIN_LOG_N)))
    cuts: list[int] = []

    def split(a: int, b: int) -> None:
        if b - a < 2:
            return
        ks = np.arange(a + 1, b)
        csum = np.cumsum(m[a:b])
        nl = ks - a
        nr = b - ks
        left = csum[nl - 1] / nl
        right = (csum[-1] - csum[nl - 1]) / nr
        stat = np.sqrt(nl * nr / (nl + nr)) * np.abs(left - right)
        j = int(np.argmax(stat))
        k = int(ks[j])
        # the noise from every step but this candidate's own: two or three commits are not their own noise
        sigma = float(1.4826 * np.median(np.delete(diffs, k - 1)) / math.sqrt(2)) if len(diffs) > 1 else 0.0
        if not stat[j] > scale * sigma:
            return
        _d, _p, verdict = _judge([values[i] for i in pts[a:k]], [values[i] for i in pts[k:b]], better, tolerance,
                                 rel_tolerance, target)
        if verdict not in CHANGE_VERDICTS:
            return
        cuts.append(k)
        split(a, k)
        split(k, b)

    split(0, len(pts))
    cuts.sort()
    bounds = [0, *cuts, len(pts)]
    out = []
    for i, k in enumerate(cuts):
        left = [values[j] for j in pts[bounds[i]:k]]
        right = [values[j] for j in pts[k:bounds[i + 2]]]
        delta, p, verdict = _judge(left, right, better, tolerance, rel_tolerance, target)
        if verdict not in CHANGE_VERDICTS or delta is None:
            continue
        out.append(Step(pts[k], pts[k - 1], float(np.mean(m[bounds[i]:k])), float(np.mean(m[k:bounds[i + 2]])),
                        float(np.mean(m[k:bounds[i + 2]]) - np.mean(m[bounds[i]:k])), p, verdict))
    return out


def _succeeded(history: History) -> dict[tuple[str, str, str], list[bool]]:
    """Per cell group, at each commit (history order): whether any of its cells succeeded there."""
    out: dict[tuple[str, str, str], list[bool]] = {}
    for k, c in enumerate(history.commits):
        for r in history.cells(c.sha):
            if r.get("alone"):  # drawn only in a pool (history_dates)
                continue
            g = (str(r["recording"]), str(r["pipeline"]), str(r["variant"]))
            out.setdefault(g, [False] * len(history.commits))[k] |= r.get("status") == "succeeded"
    return out


def _lost_at(values: Sequence[dict[int, float]], ran: Sequence[bool]) -> list[tuple[int, int]]:
    """(commit, commit before it) where a metric stopped being reported: the cells ran and succeeded, and the
    last commit where they succeeded before reported it. Judged as a regression (``LOST``), as ``diff`` does."""
    out, before = [], None
    for k, ok in enumerate(ran):
        if not ok:
            continue
        if not values[k] and before is not None and values[before]:
            out.append((k, before))
        before = k
    return out


def detect_changes(history: History, metrics: Sequence[str] = ()) -> list[Change]:
    """Every change of every cell group's metric (``metrics``: only these) over the history, oldest first."""
    from slamreplay.replay.runs.history import series

    specs: dict[str, dict[str, Any]] = {}
    for rows in history.rows.values():
        for r in rows:
            for name in r.get("metrics", {}):
                specs.setdefault(name, {"better": r.get("better", {}).get(name, "none"),
                                        "unit": r.get("units", {}).get(name, ""),
                                        "tolerance": float(r.get("tolerance", {}).get(name, 0.0)),
                                        "rel_tolerance": float(r.get("rel_tolerance", {}).get(name, 0.0)),
                                        "target": r.get("targets", {}).get(name),
                                        "optional": r.get("optional", {}).get(name)})
    ran = _succeeded(history)
    out = []
    for (rec, pipe, variant), by_metric in series(history).items():
        for name, values in sorted(by_metric.items()):
            if metrics and name not in metrics:
                continue
            s = specs[name]
            if not optional_reason(name, s):
                for k, before in _lost_at(values, ran[(rec, pipe, variant)]):
                    mean = float(np.mean(list(values[before].values())))
                    out.append(Change(rec, pipe, variant, name, s["unit"], s["better"], history.commits[k].sha,
                                      history.commits[before].sha, k, mean, None, None, None, None, LOST))
            for st in find_steps(values, s["better"], s["tolerance"], s["rel_tolerance"], s["target"]):
                rel = st.delta / abs(st.mean_before) if st.mean_before else None
                out.append(Change(rec, pipe, variant, name, s["unit"], s["better"], history.commits[st.index].sha,
                                  history.commits[st.before].sha, st.index, st.mean_before, st.mean_after, st.delta,
                                  rel, st.p_value, st.verdict))
    out.sort(key=lambda ch: (ch.index, ch.cell, ch.metric))
    return out
