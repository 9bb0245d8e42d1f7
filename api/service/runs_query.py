"""The runs table's state, as it lives in the page's URL, and the SQL it selects.

Every part of a view (filters, dates, condition, columns, groups, sort, page) is a query
parameter, so a link shows the same view. Parsing never raises: a part that does not parse
is left out of the view and explained in ``RunsView.errors`` (one line each), which the page
shows above the table; `strict_view` (the API's) raises the first instead. The condition's
grammar is `slamreplay.api.service.runs_grammar`'s. Values reach SQL only as ``?`` arguments; what is
spliced into the SQL text (column expressions, JSON paths of metric names and config keys)
comes from fixed tables or from names that matched ``NAME_RE``.
"""

from __future__ import annotations

import calendar
import datetime as dt
import functools
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING, Any
from urllib.parse import urlencode

from slamreplay.api.service.runs_grammar import (
    DAY_S,
    NAME_RE,
    OPERATORS,
    Clause,
    Condition,
    Expr,
    condition_sql,
    config_sql,
    metric_sql,
    parse_conditions,
    parse_where,
    unknown_metric,
)
from slamreplay.api.service.store import JOB_STATUSES

if TYPE_CHECKING:
    from slamreplay.replay.metric_registry import MetricSpec

__all__ = ["NAME_RE", "OPERATORS", "Clause", "Condition", "Expr", "RunsView", "metric_specs", "order_sql",
           "parse_conditions", "parse_view", "strict_view", "where_sql"]
DEFAULT_SORT = "-created"
PAGE_SIZES = (25, 50, 100, 200)
DEFAULT_COLS = ("ape_rmse_m",)  # when the URL names none: the trajectory metric most pipelines have
# sort key -> SQL expression over j (jobs), r (recordings), v (variant)
SORTS = {
    "name": "j.name COLLATE NOCASE", "tags": "tags", "note": "j.note COLLATE NOCASE",
    "recording": "r.filename COLLATE NOCASE", "pipeline": "j.pipeline", "variant": "v.variant", "seed": "j.seed",
    "created": "j.seq", "started": "j.started", "finished": "j.finished", "duration": "(j.finished - j.started)",
    "status": "j.status", "commit": "j.git_commit", "made_by": "j.made_by",
}
GROUP_SORTS = ("n", "group")  # a grouped view's: its number of runs, its name
# The columns besides the name and the metrics, which the column menu shows, hides and orders (``show``)
COLUMNS = {"status": "status", "recording": "recording", "pipeline": "pipeline", "variant": "variant",
           "seed": "seed", "config": "config keys that differ", "commit": "commit", "made_by": "made by",
           "tags": "tags", "note": "note", "created": "created (UTC)", "started": "started", "finished": "finished",
           "duration": "duration"}
DEFAULT_SHOW = ("status", "recording", "pipeline", "variant", "seed", "config", "commit", "made_by", "tags", "note",
                "created", "duration")
GROUP_KEYS = ("recording", "pipeline", "variant", "commit")  # and config.KEY
CHART_X = ("seed", "created", "commit", "parallel")  # and config.KEY; parallel: parallel coordinates
MAX_GROUP_KEYS = 4
TIME_SORTS = ("created", "started", "finished", "duration")


@functools.cache
def metric_specs() -> dict[str, MetricSpec]:
    """Every metric any installed pipeline reports, by name (its unit, direction and meaning)."""
    from slamreplay.replay.engine.pipeline import all_pipelines
    from slamreplay.replay.evaluation.score import metric_specs as specs_of

    out: dict[str, MetricSpec] = {}
    for pipeline in all_pipelines().values():
        out.update(specs_of(pipeline))
    return dict(sorted(out.items()))


@functools.cache
def known_config_keys() -> frozenset[str]:
    """Every config key of an installed pipeline (its ``Config`` fields)."""
    import dataclasses

    from slamreplay.replay.engine.pipeline import all_pipelines

    keys: set[str] = set()
    for pipeline in all_pipelines().values():
        config = getattr(pipeline, "Config", None)
        if config is not None and dataclasses.is_dataclass(config):
            keys.update(f.name for f in dataclasses.fields(config))
    return frozenset(keys)


def best_first(metric: str) -> str:
    """The sort key listing the runs best first by ``metric``'s direction (lower, higher, or closest to its target;
    a metric that only describes the run: the largest first)."""
    spec = metric_specs().get(metric)
    better = getattr(spec, "better", "none")
    return f"m.{metric}" if better in ("lower", "target") else f"-m.{metric}"


@dataclass(frozen=True)
class RunsView:
    """What the runs table shows: filters, condition, columns, groups, sort and page; built by `parse_view`."""

    q: str = ""
    recording: str = ""
    pipeline: str = ""
    status: str = ""
    tag: str = ""
    where: str = ""
    since: str = ""  # YYYY-MM-DD: created on that UTC day or later
    until: str = ""  # YYYY-MM-DD: created on that UTC day or earlier
    cols: tuple[str, ...] = DEFAULT_COLS  # metric columns, in order
    show: tuple[str, ...] = DEFAULT_SHOW  # the other columns, in order (COLUMNS)
    group: tuple[str, ...] = ()  # GROUP_KEYS or config.KEY
    chart: str = ""  # a metric drawn per group (grouped) or against ``x`` (api/web/runs_charts.py)
    x: str = ""  # CHART_X or config.KEY: a scatter of ``chart`` against it
    sort: str = DEFAULT_SORT
    page: int = 1
    per: int = 50
    condition: Expr | None = None
    errors: tuple[str, ...] = field(default=(), compare=False)

    def params(self, **changes: Any) -> dict[str, str]:
        """The URL query of this view (with ``changes``), leaving out what is at its default."""
        v = replace(self, **changes)
        out = {k: getattr(v, k) for k in ("q", "recording", "pipeline", "status", "tag", "where", "since", "until",
                                          "chart", "x") if getattr(v, k)}
        if v.cols != DEFAULT_COLS:
            out["cols"] = ",".join(v.cols)
        if v.show != DEFAULT_SHOW:
            out["show"] = ",".join(v.show)
        if v.group:
            out["group"] = ",".join(v.group)
        if v.sort != DEFAULT_SORT:
            out["sort"] = v.sort
        if v.page != 1:
            out["page"] = str(v.page)
        if v.per != 50:
            out["per"] = str(v.per)
        return out

    def url(self, path: str = "/runs", **changes: Any) -> str:
        """A link to this view (with ``changes``) at ``path``."""
        query = urlencode(self.params(**changes))
        return path + ("?" + query if query else "")

    def sort_url(self, key: str) -> str:
        """The view sorted by ``key``: first best first for a metric (by its direction), newest or largest first for
        times and counts, ascending for text; again: flipped."""
        if self.sort.lstrip("-") == key:
            return self.url(sort=key if self.sort.startswith("-") else f"-{key}", page=1)
        if key.startswith("m."):
            return self.url(sort=best_first(key[2:]), page=1)
        return self.url(sort=f"-{key}" if key in (*TIME_SORTS, "n") else key, page=1)

    def sort_mark(self, key: str) -> str:
        """The arrow a column's heading shows when the view is sorted by it."""
        return "" if self.sort.lstrip("-") != key else (" ▼" if self.sort.startswith("-") else " ▲")

    def sort_title(self, key: str) -> str:
        """What a click on a metric's heading does (its tooltip)."""
        if not key.startswith("m."):
            return ""
        best = best_first(key[2:])
        if self.sort.lstrip("-") != key:
            return "sort best first"
        return "sorted best first: click for worst first" if self.sort == best else "sorted worst first"

    @property
    def filtered(self) -> bool:
        """Whether any filter or condition leaves runs out."""
        return bool(self.q or self.recording or self.pipeline or self.status or self.tag or self.condition
                    or self.since or self.until)


def _int(raw: str | None, default: int, what: str, errors: list[str]) -> int:
    if raw is None or raw == "":
        return default
    try:
        return int(raw)
    except ValueError:
        errors.append(f"{what} must be a whole number, not {raw!r}")
        return default


def _day(raw: str, what: str, errors: list[str]) -> str:
    try:
        dt.date.fromisoformat(raw)
        if len(raw) == 10:
            return raw
    except ValueError:
        pass
    errors.append(f"{what} must be a day YYYY-MM-DD, not {raw!r} (the date filter is not applied)")
    return ""


def _names(query: Mapping[str, list[str]], key: str) -> list[str]:
    return list(dict.fromkeys(c.strip() for raw in query[key] for c in raw.split(",") if c.strip()))


def parse_view(query: Mapping[str, list[str]], config_keys: frozenset[str] = frozenset()) -> RunsView:
    """The view a URL query asks for (``query``: each parameter's values); what does not parse is left out and
    said in ``errors``. ``cols`` and ``show`` may be one comma-separated value or repeated (the column menu's
    checkboxes, in the menu's order); ``config_keys``: config keys known besides the installed pipelines'."""
    known = metric_specs()
    keys = config_keys | known_config_keys()
    errors: list[str] = []

    def one(key: str) -> str:
        values = query.get(key) or [""]
        return values[-1].strip()[:500]

    status = one("status")
    if status and status not in JOB_STATUSES:
        errors.append(f"unknown status {status!r}: one of {', '.join(JOB_STATUSES)}")
        status = ""
    cols = tuple(c for c in DEFAULT_COLS if c in known)
    if "cols" in query:
        names = _names(query, "cols")
        errors += [f"column {unknown_metric(c, known)}" for c in names if c not in known]
        cols = tuple(c for c in names if c in known)
    show: tuple[str, ...] = DEFAULT_SHOW
    if "show" in query:
        names = _names(query, "show")
        errors += [f"unknown column {c!r}: one of {', '.join(COLUMNS)}" for c in names if c not in COLUMNS]
        show = tuple(c for c in names if c in COLUMNS)
    group: tuple[str, ...] = ()
    if "group" in query:
        for g in _names(query, "group"):
            key = g.removeprefix("config.")
            if g in GROUP_KEYS or (g.startswith("config.") and NAME_RE.fullmatch(key) and key in keys):
                group += (g,)
            else:
                errors.append(f"cannot group by {g!r}: by {', '.join(GROUP_KEYS)} or config.KEY (a pipeline's "
                              "config key)")
        if len(group) > MAX_GROUP_KEYS:
            errors.append(f"group by at most {MAX_GROUP_KEYS} keys")
            group = group[:MAX_GROUP_KEYS]
    chart, x = one("chart"), one("x")
    if chart and chart not in known:
        errors.append(f"chart: {unknown_metric(chart, known)}")
        chart = ""
    if x and not (x in CHART_X or (x.startswith("config.") and x.removeprefix("config.") in keys)):
        errors.append(f"cannot chart against {x!r}: against {', '.join(CHART_X)} or config.KEY (a pipeline's "
                      "config key)")
        x = ""
    where = one("where")
    condition: Expr | None = None
    if where:
        try:
            condition = parse_where(where, known, keys)
        except ValueError as err:
            errors.append(f"{err} (the condition is not applied)")
    since = _day(one("since"), "since", errors) if one("since") else ""
    until = _day(one("until"), "until", errors) if one("until") else ""
    sort = one("sort") or DEFAULT_SORT
    key = sort.lstrip("-")
    valid = key in SORTS or (key.startswith("m.") and key[2:] in known) or (
        key.startswith("c.") and NAME_RE.fullmatch(key[2:]) is not None) or (group and key in GROUP_SORTS)
    if not valid:
        errors.append(f"cannot sort by {key!r}: click a column's heading to sort by it")
        sort = DEFAULT_SORT
    per = _int(one("per"), 50, "per", errors)
    if per not in PAGE_SIZES:
        per = min(PAGE_SIZES, key=lambda p: abs(p - per))
    page = max(1, _int(one("page"), 1, "page", errors))
    return RunsView(q=one("q"), recording=one("recording"), pipeline=one("pipeline"), status=status, tag=one("tag"),
                    where=where, since=since, until=until, cols=cols, show=show, group=group, chart=chart, x=x,
                    sort=sort, page=page, per=per, condition=condition, errors=tuple(errors))


def strict_view(query: Mapping[str, list[str]]) -> RunsView:
    """`parse_view` for the API: a part that does not parse is a 422 saying what is wrong in one line
    (ReplayError), not a line above a table."""
    from slamreplay.replay.errors import ReplayError

    view = parse_view(query)
    if view.errors:
        first = view.errors[0].removesuffix(" (the condition is not applied)")
        raise ReplayError(first.removesuffix(" (the date filter is not applied)"))
    return view


def _like(text: str) -> str:
    return "%" + text.replace("\\", "\\\\").replace("%", "\\%").replace("_", "\\_") + "%"


def _metric(name: str) -> str:
    return metric_sql(name)


def day_start(day: str) -> float:
    """The first second (UTC, since the epoch) of the day ``YYYY-MM-DD``."""
    return float(calendar.timegm(dt.date.fromisoformat(day).timetuple()))


def where_sql(view: RunsView) -> tuple[str, list[Any]]:
    """The SQL condition of the view's filters and its arguments."""
    where: list[str] = ["1"]
    args: list[Any] = []
    if view.recording:
        where.append("(j.recording_id = ? OR r.filename = ? OR (length(?) >= 4 AND j.recording_id LIKE ? || '%'))")
        args += [view.recording, view.recording, view.recording, view.recording.lower()]
    for column, value in (("j.pipeline", view.pipeline), ("j.status", view.status)):
        if value:
            where.append(f"{column} = ?")
            args.append(value)
    if view.tag:
        where.append("EXISTS (SELECT 1 FROM job_tags t WHERE t.job_id = j.id AND t.tag = ?)")
        args.append(view.tag)
    for word in view.q.split():  # every word somewhere in the run
        where.append("(j.id LIKE ? ESCAPE '\\' OR j.name LIKE ? ESCAPE '\\' OR j.note LIKE ? ESCAPE '\\' "
                     "OR j.pipeline LIKE ? ESCAPE '\\' OR r.filename LIKE ? ESCAPE '\\' OR j.error LIKE ? ESCAPE '\\' "
                     "OR j.config LIKE ? ESCAPE '\\' OR v.variant LIKE ? ESCAPE '\\' "
                     "OR EXISTS (SELECT 1 FROM job_tags t WHERE t.job_id = j.id AND t.tag LIKE ? ESCAPE '\\'))")
        args += [_like(word)] * 9
    if view.since:
        where.append("j.created >= ?")
        args.append(day_start(view.since))
    if view.until:
        where.append("j.created < ?")
        args.append(day_start(view.until) + DAY_S)
    if view.condition is not None:
        sql, more = condition_sql(view.condition)
        where.append(sql)
        args += more
    return " AND ".join(where), args


def sort_expr(key: str) -> str:
    """The SQL value a sort key orders by (a metric with a target value: its distance from it, as a ratio >= 1)."""
    if key.startswith("m."):
        expr = _metric(key[2:])
        spec = metric_specs().get(key[2:])
        target = getattr(spec, "target", None)
        if target is not None and getattr(spec, "better", "") == "target":
            t = float(target)
            return f"(CASE WHEN {expr} > 0 THEN max({expr} / {t!r}, {t!r} / {expr}) END)"
        return expr
    if key.startswith("c."):
        return config_sql(key[2:])
    return SORTS[key]


def order_sql(view: RunsView) -> str:
    """ORDER BY of the view's sort: runs without a value last either way, then newest first."""
    key = view.sort.lstrip("-")
    if key in GROUP_SORTS:  # a grouped view's key, meaningless for runs: newest first
        return "j.seq DESC"
    expr = sort_expr(key)
    direction = "DESC" if view.sort.startswith("-") else "ASC"
    return f"({expr}) IS NULL, {expr} {direction}, j.seq DESC"


def metric_heading(name: str) -> dict[str, str]:
    """A metric column's heading: its name, unit (unless the name ends with it), direction arrow and meaning."""
    spec = metric_specs().get(name)
    if spec is None:
        return {"name": name, "unit": "", "arrow": "", "title": name}
    target = getattr(spec, "target", None)  # the consistent value of a NEES, closest is best
    arrow = {"lower": "↓", "higher": "↑"}.get(spec.better, f"≈{target:g}" if target is not None else "")
    better = {"lower": "lower is better", "higher": "higher is better"}.get(
        spec.better, f"closest to {target:g} is best" if target is not None else "describes the run")
    unit = spec.unit
    return {"name": name, "unit": "" if not unit or name.endswith(f"_{unit}") else unit, "arrow": arrow,
            "title": f"{spec.description}; {better}"}
