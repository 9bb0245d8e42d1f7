"""The runs table's state, as it lives in the page's URL, and the SQL it selects.

Every part of a view (filters, metric condition, metric columns, sort, page) is a query
parameter, so a link shows the same view. Parsing never raises: a part that does not parse
is left out of the view and explained in ``RunsView.errors`` (one line each), which the page
shows above the table. Values reach SQL only as ``?`` arguments; what is spliced into the
SQL text (column expressions, JSON paths of metric names) comes from fixed tables or from
names that matched ``NAME_RE``.
"""

from __future__ import annotations

import difflib
import functools
import re
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING, Any
from urllib.parse import urlencode

from slamreplay.api.store import JOB_STATUSES

if TYPE_CHECKING:
    from slamreplay.replay.metric_registry import MetricSpec

NAME_RE = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")
CONDITION_RE = re.compile(r"\s*([A-Za-z_][A-Za-z0-9_]*)\s*(<=|>=|!=|<|>|=)\s*"
                          r"([-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?)\s*")
OPERATORS = ("<", "<=", ">", ">=", "=", "!=")
PAGE_SIZES = (25, 50, 100, 200)
DEFAULT_SORT = "-created"
DEFAULT_COLS = ("ape_rmse_m",)  # when the URL names none: the trajectory metric most pipelines have
# sort key -> SQL expression over j (jobs), r (recordings), v (variant)
SORTS = {
    "name": "j.name COLLATE NOCASE", "tags": "tags", "note": "j.note COLLATE NOCASE",
    "recording": "r.filename COLLATE NOCASE", "pipeline": "j.pipeline", "variant": "v.variant", "seed": "j.seed",
    "created": "j.seq", "started": "j.started", "finished": "j.finished", "duration": "(j.finished - j.started)",
    "status": "j.status",
}


@functools.cache
def metric_specs() -> dict[str, MetricSpec]:
    """Every metric any installed pipeline reports, by name (its unit, direction and meaning)."""
    from slamreplay.replay.engine.pipeline import all_pipelines
    from slamreplay.replay.evaluation.score import metric_specs as specs_of

    out: dict[str, MetricSpec] = {}
    for pipeline in all_pipelines().values():
        out.update(specs_of(pipeline))
    return dict(sorted(out.items()))


@dataclass(frozen=True)
class Condition:
    """``metric op value``: keeps the runs whose value of ``metric`` satisfies it (runs without it never do)."""

    metric: str
    op: str
    value: float

    def __str__(self) -> str:
        return f"{self.metric} {self.op} {self.value:g}"


def _unknown_metric(name: str, known: Mapping[str, Any]) -> str:
    close = difflib.get_close_matches(name, list(known), n=3)
    hint = f"did you mean {' or '.join(close)}?" if close else "the metric names are listed under Columns"
    return f"unknown metric {name!r}: {hint}"


def parse_conditions(text: str, known: Mapping[str, Any]) -> list[Condition]:
    """``landmark_rmse_m < 0.1`` (several joined by ``and``): metric name, one of < <= > >= = !=, a number.

    Raises
    ------
    ValueError
        One line saying which part is wrong and what is expected.
    """
    out = []
    for part in re.split(r"\s+and\s+", text.strip(), flags=re.IGNORECASE):
        m = CONDITION_RE.fullmatch(part)
        if m is None:
            raise ValueError(f"cannot read the condition {part.strip()!r}: write a metric name, one of "
                             f"{' '.join(OPERATORS)}, and a number, e.g. landmark_rmse_m < 0.1")
        name, op, number = m.groups()
        if name not in known:
            raise ValueError(f"in the condition {part.strip()!r}: {_unknown_metric(name, known)}")
        out.append(Condition(name, op, float(number)))
    return out


@dataclass(frozen=True)
class RunsView:
    """What the runs table shows: filters, condition, metric columns, sort and page; built by `parse_view`."""

    q: str = ""
    recording: str = ""
    pipeline: str = ""
    status: str = ""
    tag: str = ""
    where: str = ""
    cols: tuple[str, ...] = DEFAULT_COLS
    sort: str = DEFAULT_SORT
    page: int = 1
    per: int = 50
    conditions: tuple[Condition, ...] = ()
    errors: tuple[str, ...] = field(default=(), compare=False)

    def params(self, **changes: Any) -> dict[str, str]:
        """The URL query of this view (with ``changes``), leaving out what is at its default."""
        v = replace(self, **changes)
        out = {k: getattr(v, k) for k in ("q", "recording", "pipeline", "status", "tag", "where") if getattr(v, k)}
        if v.cols != DEFAULT_COLS:
            out["cols"] = ",".join(v.cols)
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
        """The view sorted by ``key``: descending first for times and metrics, ascending for text; again: flipped."""
        if self.sort.lstrip("-") == key:
            return self.url(sort=key if self.sort.startswith("-") else f"-{key}", page=1)
        first_desc = key in ("created", "started", "finished", "duration") or key.startswith("m.")
        return self.url(sort=f"-{key}" if first_desc else key, page=1)

    def sort_mark(self, key: str) -> str:
        """The arrow a column's heading shows when the view is sorted by it."""
        return "" if self.sort.lstrip("-") != key else (" ▼" if self.sort.startswith("-") else " ▲")


def _int(raw: str | None, default: int, what: str, errors: list[str]) -> int:
    if raw is None or raw == "":
        return default
    try:
        return int(raw)
    except ValueError:
        errors.append(f"{what} must be a whole number, not {raw!r}")
        return default


def parse_view(query: Mapping[str, list[str]], config_keys: frozenset[str] = frozenset()) -> RunsView:
    """The view a URL query asks for (``query``: each parameter's values); what does not parse is left out and
    said in ``errors``. ``cols`` may be one comma-separated value or repeated (the form's checkboxes)."""
    known = metric_specs()
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
        names = [c.strip() for raw in query["cols"] for c in raw.split(",") if c.strip()]
        bad = [c for c in names if c not in known]
        errors += [f"column {_unknown_metric(c, known)}" for c in bad]
        cols = tuple(dict.fromkeys(c for c in names if c in known))
    where = one("where")
    conditions: tuple[Condition, ...] = ()
    if where:
        try:
            conditions = tuple(parse_conditions(where, known))
        except ValueError as err:
            errors.append(f"{err} (the condition is not applied)")
    sort = one("sort") or DEFAULT_SORT
    key = sort.lstrip("-")
    valid = key in SORTS or (key.startswith("m.") and key[2:] in known) or (
        key.startswith("c.") and NAME_RE.fullmatch(key[2:]) is not None)
    if not valid:
        errors.append(f"cannot sort by {key!r}: click a column's heading to sort by it")
        sort = DEFAULT_SORT
    per = _int(one("per"), 50, "per", errors)
    if per not in PAGE_SIZES:
        per = min(PAGE_SIZES, key=lambda p: abs(p - per))
    page = max(1, _int(one("page"), 1, "page", errors))
    return RunsView(q=one("q"), recording=one("recording"), pipeline=one("pipeline"), status=status, tag=one("tag"),
                    where=where, cols=cols, sort=sort, page=page, per=per, conditions=conditions,
                    errors=tuple(errors))


def strict_view(query: Mapping[str, list[str]]) -> RunsView:
    """`parse_view` for the API: a part that does not parse is a 422 saying what is wrong (ReplayError), not a
    line above a table."""
    from slamreplay.replay.errors import ReplayError

    view = parse_view(query)
    if view.errors:
        raise ReplayError(view.errors[0].removesuffix(" (the condition is not applied)"))
    return view


def _like(text: str) -> str:
    return "%" + text.replace("\\", "\\\\").replace("%", "\\%").replace("_", "\\_") + "%"


def _metric(name: str) -> str:
    return f"json_extract(j.metrics, '$.\"{name}\"')"  # name matched NAME_RE: no quote can end the path


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
    for c in view.conditions:
        where.append(f"{_metric(c.metric)} {'<>' if c.op == '!=' else c.op} ?")
        args.append(c.value)
    return " AND ".join(where), args


def order_sql(view: RunsView) -> str:
    """ORDER BY of the view's sort: runs without a value last either way, then newest first."""
    key = view.sort.lstrip("-")
    if key.startswith("m."):
        expr = _metric(key[2:])
    elif key.startswith("c."):
        expr = f"json_extract(j.config, '$.\"{key[2:]}\"')"
    else:
        expr = SORTS[key]
    direction = "DESC" if view.sort.startswith("-") else "ASC"
    return f"({expr}) IS NULL, {expr} {direction}, j.seq DESC"
