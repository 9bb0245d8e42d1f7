"""Groups of the runs table (``group=pipeline,recording``, ``group=config.range_sigma_m``): one row per distinct
value of the group keys, with the number of runs and, for each chosen metric, mean, spread (sample standard
deviation), minimum and maximum over the runs that report it.

The view's filters and condition choose the runs, and SQL groups them and sums them up
(`Store.select_groups`: counts, means, extremes, sums of squared deviations, and each group's newest runs),
so that a page of groups reads a row per group rather than every run. Here: labels, standard deviations and
the groups' order. Each group links to the flat view of its runs: the view's condition and'ed with the group's
keys, in the condition grammar.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, replace
from typing import Any

from slamreplay.api.service.runs_grammar import value_text
from slamreplay.api.service.runs_query import DEFAULT_SORT, SORTS, RunsView, metric_specs
from slamreplay.api.service.store_runs import GroupRow, GroupSums, RunsTableMixin


@dataclass(frozen=True)
class Stat:
    """A metric over a group's runs that report it (``std``: the sample standard deviation, None below two)."""

    n: int
    mean: float
    std: float | None
    lo: float
    hi: float

    @classmethod
    def of(cls, values: list[float]) -> Stat | None:
        """The statistics of ``values`` (the finite ones); None when there is none."""
        vs = [float(v) for v in values if isinstance(v, (int, float)) and math.isfinite(v)]
        if not vs:
            return None
        mean = math.fsum(vs) / len(vs)
        return cls.from_sums(len(vs), mean, min(vs), max(vs), math.fsum((v - mean) ** 2 for v in vs))

    @classmethod
    def from_sums(cls, n: int, mean: float, lo: float, hi: float, squares: float) -> Stat:
        """The statistics of ``n`` values from their mean, extremes and sum of squared deviations from the mean."""
        return cls(n, mean, math.sqrt(max(squares, 0.0) / (n - 1)) if n > 1 else None, lo, hi)


@dataclass(frozen=True)
class Group:
    """Runs that share the values of the group keys: ``values`` (raw, None: none/default) and their ``labels``."""

    keys: tuple[str, ...]
    values: tuple[Any, ...]
    labels: tuple[str, ...]
    n: int  # how many runs
    newest: int  # the sequence number of its newest run
    stats: dict[str, Stat | None]
    runs: tuple[GroupRow, ...] = ()  # its newest runs (at most the store's preview), newest first

    @property
    def label(self) -> str:
        """The group's name: its keys' values, ``key=value`` for config keys."""
        return ", ".join(lab if not k.startswith("config.") else f"{k.removeprefix('config.')}={lab}"
                         for k, lab in zip(self.keys, self.labels, strict=True))

    def condition(self) -> str | None:
        """The condition (grammar of ``where``) that keeps exactly this group's runs; None when a value cannot be
        written in it (a list or an object in a config)."""
        parts = []
        for key, value in zip(self.keys, self.values, strict=True):
            if isinstance(value, (list, dict)):
                return None
            try:
                parts.append(f"{key} = {value_text(value, key)}")
            except ValueError:
                return None
        return " and ".join(parts)


def _label(key: str, value: Any, recording_name: str | None) -> str:
    if key == "recording":
        return recording_name or str(value)[:8]
    if value is None:
        return {"variant": "no variant", "commit": "commit unknown"}.get(key, "default")
    if key == "commit":
        return str(value)[:8] + ("-dirty" if str(value).endswith("-dirty") else "")
    if isinstance(value, str):
        return value
    return json.dumps(value, sort_keys=True)


def _hashable(values: tuple[Any, ...]) -> tuple[Any, ...]:
    return tuple(json.dumps(v, sort_keys=True) if isinstance(v, (list, dict)) else (type(v), v) for v in values)


def group_runs(sums: list[GroupSums], runs: list[GroupRow], view: RunsView) -> list[Group]:
    """The groups of a grouped view from the store's sums (`Store.select_groups`) and newest runs of each, in the
    view's order, each with the statistics of the view's metric columns."""
    newest: dict[tuple[Any, ...], list[GroupRow]] = {}
    for r in runs:
        newest.setdefault(_hashable(r.keys), []).append(r)
    groups = []
    for g in sums:
        labels = tuple(_label(k, v, g.recording_name) for k, v in zip(view.group, g.keys, strict=True))
        stats = {m: Stat.from_sums(*g.sums[m]) if m in g.sums else None for m in (*view.cols, view.chart) if m}
        groups.append(Group(view.group, g.keys, labels, g.n, g.newest, stats,
                            tuple(newest.get(_hashable(g.keys), ()))))
    return sort_groups(groups, view.sort)


def _order_value(value: Any) -> tuple[int, Any]:
    """Numbers before text, each in its order."""
    if isinstance(value, bool):
        return (1, str(value))
    if isinstance(value, (int, float)):
        return (0, value)
    return (1, str(value).lower())


def metric_rank(metric: str, value: float) -> float:
    """How good ``value`` of ``metric`` is, smaller better (a target metric: its ratio to the target, >= 1); for a
    metric that only describes the run, larger first."""
    spec = metric_specs().get(metric)
    better = getattr(spec, "better", "none")
    target = getattr(spec, "target", None)
    if better == "target" and target:
        return max(value / target, target / value) if value > 0 else math.inf
    return value if better == "lower" else -value


def sort_groups(groups: list[Group], sort: str) -> list[Group]:
    """``groups`` in the order of the sort key ``sort`` (``-`` first: descending); groups without a value last."""
    key, desc = sort.lstrip("-"), sort.startswith("-")
    by_label = sorted(groups, key=lambda g: tuple(_order_value(v if v is not None else "~") for v in g.labels))
    if key.startswith("m."):
        name = key[2:]
        spec = metric_specs().get(name)
        target_metric = getattr(spec, "better", "") == "target"

        def value(g: Group) -> float | None:
            s = g.stats.get(name)
            if s is None:
                return None
            return metric_rank(name, s.mean) if target_metric else s.mean

        have = [g for g in by_label if value(g) is not None]
        return sorted(have, key=lambda g: value(g) or 0.0, reverse=desc) + [g for g in by_label if value(g) is None]
    if key == "n":
        return sorted(by_label, key=lambda g: g.n, reverse=desc)
    wanted = {"group": None, "recording": "recording", "pipeline": "pipeline", "variant": "variant",
              "commit": "commit"}.get(key, f"config.{key[2:]}" if key.startswith("c.") else "")
    if wanted is None:
        return list(reversed(by_label)) if desc else by_label
    if groups and wanted in groups[0].keys:
        i = groups[0].keys.index(wanted)

        def order(g: Group) -> tuple[int, Any]:
            return _order_value(g.values[i] if g.values[i] is not None and wanted != "recording" else g.labels[i])

        return sorted(by_label, key=order, reverse=desc)
    return sorted(by_label, key=lambda g: g.newest, reverse=True)  # newest run first


def runs_of(view: RunsView, group: Group) -> str | None:
    """A link to the flat view of a group's runs (None when its keys cannot be written as a condition)."""
    cond = group.condition()
    if cond is None:
        return None
    where = f"({view.where}) and {cond}" if view.where else cond
    sort = view.sort if view.sort.lstrip("-") in SORTS or view.sort.lstrip("-")[:2] in ("m.", "c.") else DEFAULT_SORT
    return replace(view, group=(), where=where, sort=sort, page=1).url()


def best_means(groups: list[Group], metrics: tuple[str, ...]) -> dict[str, float]:
    """The best mean of each metric among ``groups`` (by its direction; none for a descriptive metric)."""
    out = {}
    for m in metrics:
        if getattr(metric_specs().get(m), "better", "none") == "none":
            continue
        means = [s.mean for g in groups if (s := g.stats.get(m)) is not None]
        if len(means) > 1:
            out[m] = min(means, key=lambda v: metric_rank(m, v))
    return out


def select_groups(store: RunsTableMixin, view: RunsView, where: str, args: list[Any], preview: int) -> list[Group]:
    """The groups of a grouped view, in its order (each with its newest runs)."""
    metrics = view.cols if not view.chart or view.chart in view.cols else (*view.cols, view.chart)
    sums, runs = store.select_groups(where, args, view.group, metrics, preview)
    return group_runs(sums, runs, view)


def stat_cell(metric: str, s: Stat | None, n: int, best: float | None) -> dict[str, Any]:
    """A group's metric cell: mean (4 digits) ± standard deviation (2), the count, minimum and maximum on hover."""
    if s is None:
        return {"name": metric, "mean": "", "std": "", "title": f"none of the {n} runs reports it", "best": False}
    return {"name": metric, "mean": f"{s.mean:.4g}", "std": "" if s.std is None else f"{s.std:.2g}",
            "title": f"{s.n} of {n} runs: mean {s.mean:.6g}, std {'-' if s.std is None else f'{s.std:.6g}'}, "
                     f"min {s.lo:.6g}, max {s.hi:.6g}", "best": best is not None and s.mean == best}
