"""The runs table's condition (``where``): comparisons joined by ``and`` and ``or``, grouped by parentheses.

::

    condition  := conjunct ("or" conjunct)*        "and" binds tighter than "or"
    conjunct   := atom ("and" atom)*
    atom       := "(" condition ")" | comparison
    comparison := FIELD OP VALUE                     OP: one of < <= > >= = !=

========================================  ===========================================================
FIELD                                     VALUE
========================================  ===========================================================
a metric name (``landmark_rmse_m``)       a number: ``landmark_rmse_m < 0.1``
``config.KEY`` (a pipeline's config key)  a number, ``true``/``false``, a word or quoted text (= and !=),
                                          or ``default``: the key was not submitted (its default ran)
``seed``                                  a whole number
``commit``                                a prefix of the code's commit sha (4-40 hex digits), = and !=;
                                          ``none``: not known
``created``, ``started``, ``finished``    a UTC day ``YYYY-MM-DD``: ``created >= 2024-05-01`` (``=``: that day)
``pipeline``, ``recording``, ``variant``,  a word or quoted text, = and != (``recording``: its file name
``status``, ``made_by``                   or id); ``none``: no value (no variant, nobody known)
========================================  ===========================================================

A run without the value compared (a metric it did not report, a config key left at its default, an unknown
commit) satisfies no comparison but ``= default`` / ``= none``. Parsing is strict: anything else is a
``ValueError`` of one line saying which part is wrong and what is expected. Values reach SQL only as ``?``
arguments; names spliced into JSON paths matched ``NAME_RE``.
"""

from __future__ import annotations

import calendar
import datetime as dt
import difflib
import re
from collections.abc import Collection, Mapping
from dataclasses import dataclass
from typing import Any, Literal

NAME_RE = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")
OPERATORS = ("<", "<=", ">", ">=", "=", "!=")
NUMBER_RE = re.compile(r"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?")
COMPARISON_RE = re.compile(r"\s*([A-Za-z_][A-Za-z0-9_]*(?:\.[A-Za-z_][A-Za-z0-9_]*)?)\s*(<=|>=|!=|<|>|=)\s*"
                           r"('[^']*'|\"[^\"]*\"|[^\s'\"()]+)\s*")
WORD_RE = re.compile(r"[\w.:/+@-]+")  # a value that needs no quotes
DATE_RE = re.compile(r"\d{4}-\d{2}-\d{2}")
COMMIT_RE = re.compile(r"[0-9a-fA-F]{4,40}(?:-dirty)?")
DATE_FIELDS = {"created": "j.created", "started": "j.started", "finished": "j.finished"}
TEXT_FIELDS = {"pipeline": "j.pipeline", "status": "j.status", "variant": "v.variant", "made_by": "j.made_by",
               "recording": "r.filename"}
OTHER_FIELDS = ("seed", "commit", *DATE_FIELDS, *TEXT_FIELDS)
EXAMPLE = "landmark_rmse_m < 0.1"
HELP = (f"write a metric name, one of {' '.join(OPERATORS)}, and a number, e.g. {EXAMPLE} "
        "(also config.KEY, seed, commit, created, started, finished, pipeline, recording, variant, status, made_by)")
DAY_S = 86_400


@dataclass(frozen=True)
class Condition:
    """``field op value``: keeps the runs whose ``field`` satisfies it (runs without a value never do, but for
    ``= default`` and ``= none``, whose ``value`` is None)."""

    field: str  # a metric name, "config.KEY", or one of OTHER_FIELDS
    op: str
    value: float | int | str | bool | None

    @property
    def metric(self) -> str:
        """The field (a metric's name for a metric condition): the name the first grammar had."""
        return self.field

    def __str__(self) -> str:
        if self.field in DATE_FIELDS and isinstance(self.value, float):
            day = dt.datetime.fromtimestamp(self.value, dt.timezone.utc).date().isoformat()
            return f"{self.field} {self.op} {day}"
        return f"{self.field} {self.op} {value_text(self.value, self.field)}"


@dataclass(frozen=True)
class Clause:
    """Conditions joined by ``and`` (all hold) or ``or`` (one holds)."""

    join: Literal["and", "or"]
    parts: tuple[Expr, ...]

    def __str__(self) -> str:
        return f" {self.join} ".join(f"({p})" if isinstance(p, Clause) else str(p) for p in self.parts)


Expr = Condition | Clause


def value_text(value: Any, field: str = "") -> str:
    """``value`` as the grammar writes it (quoted when it is not one word); ``default``/``none`` for None."""
    if value is None:
        return "default" if field.startswith("config.") else "none"
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (int, float)):
        return f"{value:g}" if isinstance(value, float) and float(f"{value:g}") == value else repr(value)
    text = str(value)
    if WORD_RE.fullmatch(text) and text.lower() not in ("and", "or", "true", "false", "default", "none") \
            and not NUMBER_RE.fullmatch(text):
        return text
    if '"' not in text:
        return f'"{text}"'
    if "'" not in text:
        return f"'{text}'"
    raise ValueError(f"{text[:60]!r} holds both kinds of quote: the grammar cannot write it")


def _close(name: str, known: Collection[str], what: str, where_listed: str) -> str:
    close = difflib.get_close_matches(name, list(known), n=3)
    hint = f"did you mean {' or '.join(close)}?" if close else f"the {what} names are listed {where_listed}"
    return f"unknown {what} {name!r}: {hint}"


def unknown_metric(name: str, known: Collection[str]) -> str:
    """One line: ``name`` is no metric, and the closest ones."""
    return _close(name, known, "metric", "under Columns")


def _tokens(text: str) -> list[str | tuple[str]]:
    """Parentheses, ``and``/``or`` (as str) and the comparisons between them (as 1-tuples), quotes kept whole."""
    out: list[str | tuple[str]] = []
    chunk: list[str] = []

    def flush() -> None:
        part = "".join(chunk).strip()
        if part:
            out.append((part,))
        chunk.clear()

    i = 0
    while i < len(text):
        ch = text[i]
        if ch in "'\"":
            end = text.find(ch, i + 1)
            if end < 0:
                raise ValueError(f"cannot read the condition {text!r}: the quote {ch} at {i + 1} is not closed")
            chunk.append(text[i:end + 1])
            i = end + 1
            continue
        if ch in "()":
            flush()
            out.append(ch)
            i += 1
            continue
        m = re.compile(r"(and|or)(?=[\s()]|$)", re.IGNORECASE).match(text, i)
        if m is not None and (i == 0 or text[i - 1] in " \t\r\n()"):
            flush()
            out.append(m.group(1).lower())
            i = m.end()
            continue
        chunk.append(ch)
        i += 1
    flush()
    return out


def parse_where(text: str, metrics: Mapping[str, Any], config_keys: Collection[str] = ()) -> Expr | None:
    """The condition ``text`` (None when it is blank), its metric names checked against ``metrics`` and its
    ``config.KEY`` against ``config_keys`` (none given: any key).

    Raises
    ------
    ValueError
        One line saying which part is wrong and what is expected.
    """
    tokens = _tokens(text.strip())
    if not tokens:
        return None
    pos = 0

    def peek() -> str | tuple[str] | None:
        return tokens[pos] if pos < len(tokens) else None

    def atom() -> Expr:
        nonlocal pos
        tok = peek()
        before = tokens[pos - 1] if pos else None
        if tok is None or tok in ("and", "or", ")"):
            after = f"after {before!r}" if isinstance(before, str) else "at the start"
            raise ValueError(f"cannot read the condition {text!r}: a comparison is missing {after}, e.g. {EXAMPLE}")
        pos += 1
        if tok == "(":
            inner = either()
            if peek() != ")":
                raise ValueError(f"cannot read the condition {text!r}: a ( without its )")
            pos += 1
            return inner
        assert isinstance(tok, tuple)
        return comparison(tok[0], metrics, config_keys)

    def joined(join: Literal["and", "or"], part: Any) -> Expr:
        nonlocal pos
        parts = [part()]
        while peek() == join:
            pos += 1
            parts.append(part())
        return parts[0] if len(parts) == 1 else Clause(join, tuple(parts))

    def either() -> Expr:
        return joined("or", lambda: joined("and", atom))

    expr = either()
    if pos < len(tokens):
        tok = tokens[pos]
        if tok == ")":
            raise ValueError(f"cannot read the condition {text!r}: a ) without its (")
        raise ValueError(f"cannot read the condition {text!r}: join comparisons with and or or")  # e.g. ") ("
    return expr


def parse_conditions(text: str, known: Mapping[str, Any], config_keys: Collection[str] = ()) -> list[Expr]:
    """The conditions that ``text`` joins by a top-level ``and`` (one when it is an ``or`` or a single comparison;
    none when blank); see `parse_where`."""
    expr = parse_where(text, known, config_keys)
    if expr is None:
        return []
    return list(expr.parts) if isinstance(expr, Clause) and expr.join == "and" else [expr]


def _day(text: str, part: str, field: str) -> float:
    try:
        day = dt.date.fromisoformat(text) if DATE_RE.fullmatch(text) else None
    except ValueError:
        day = None
    if day is None:
        raise ValueError(f"in the condition {part!r}: {field} takes a day YYYY-MM-DD (UTC), e.g. "
                         f"{field} >= 2024-05-01")
    return float(calendar.timegm(day.timetuple()))


def _text(raw: str) -> str:
    return raw[1:-1] if raw[:1] in "'\"" else raw


def comparison(part: str, metrics: Mapping[str, Any], config_keys: Collection[str] = ()) -> Condition:
    """One ``FIELD OP VALUE`` (see the module's table); ValueError of one line otherwise."""
    m = COMPARISON_RE.fullmatch(part)
    if m is None:
        raise ValueError(f"cannot read the condition {part!r}: {HELP}")
    name, op, raw = m.groups()
    lowered = raw.lower()
    eq_only = f"in the condition {part!r}: {{what}} takes = or != only"
    if name.startswith("config."):
        key = name.removeprefix("config.")
        if config_keys and key not in config_keys:
            raise ValueError(f"in the condition {part!r}: {_close(key, config_keys, 'config key', 'on a job page')}")
        if lowered in ("default", "true", "false") or not NUMBER_RE.fullmatch(raw):
            if op not in ("=", "!="):
                raise ValueError(f"in the condition {part!r}: {name} takes a number with < <= > >=, and text, true, "
                                 "false or default with = or != only")
            if lowered not in ("default", "true", "false") and raw[:1] not in "'\"" and not WORD_RE.fullmatch(raw):
                raise ValueError(f"cannot read the condition {part!r}: quote text that is not one word")
            value: Any = {"default": None, "true": True, "false": False}.get(lowered, _text(raw))
            return Condition(name, op, value)
        return Condition(name, op, float(raw))
    if name == "seed":
        if not re.fullmatch(r"[-+]?\d+", raw):
            raise ValueError(f"in the condition {part!r}: seed takes a whole number, e.g. seed = 3")
        return Condition(name, op, int(raw))
    if name == "commit":
        if op not in ("=", "!="):
            raise ValueError(eq_only.format(what="commit") + " and a prefix of a sha, e.g. commit = 1a2b3c4")
        if lowered == "none":
            return Condition(name, op, None)
        if not COMMIT_RE.fullmatch(raw):
            raise ValueError(f"in the condition {part!r}: commit takes 4 to 40 hex digits of a sha (or none), "
                             "e.g. commit = 1a2b3c4")
        return Condition(name, op, lowered)
    if name in DATE_FIELDS:
        return Condition(name, op, _day(raw, part, name))
    if name in TEXT_FIELDS:
        if op not in ("=", "!="):
            raise ValueError(eq_only.format(what=name))
        if raw[:1] not in "'\"" and not WORD_RE.fullmatch(raw):
            raise ValueError(f"cannot read the condition {part!r}: quote text that is not one word")
        if name == "status" and lowered != "none":
            from slamreplay.api.service.store import JOB_STATUSES

            if raw not in JOB_STATUSES:
                raise ValueError(f"in the condition {part!r}: unknown status {raw!r}: one of {', '.join(JOB_STATUSES)}")
        return Condition(name, op, None if lowered == "none" and raw[:1] not in "'\"" else _text(raw))
    if name not in metrics:
        raise ValueError(f"in the condition {part!r}: {unknown_metric(name, [*metrics, *OTHER_FIELDS])}")
    if not NUMBER_RE.fullmatch(raw):
        raise ValueError(f"cannot read the condition {part!r}: {HELP}")
    return Condition(name, op, float(raw))


def _json_path(key: str) -> str:
    return f"'$.\"{key}\"'"  # key matched NAME_RE: no quote can end the path


def metric_sql(name: str) -> str:
    """The SQL value of metric ``name`` (matched NAME_RE) of job ``j``."""
    return f"json_extract(j.metrics, {_json_path(name)})"


def config_sql(key: str) -> str:
    """The SQL value of config key ``key`` (matched NAME_RE) of job ``j``, as submitted (NULL: its default ran)."""
    return f"json_extract(j.config, {_json_path(key)})"


def _sql_op(op: str) -> str:
    return "<>" if op == "!=" else op


def day_sql(column: str, op: str, day0: float) -> tuple[str, list[Any]]:
    """``column op DAY`` over times in seconds, a day being [day0, day0 + 1 day)."""
    day1 = day0 + DAY_S
    return {"<": (f"{column} < ?", [day0]), "<=": (f"{column} < ?", [day1]), ">": (f"{column} >= ?", [day1]),
            ">=": (f"{column} >= ?", [day0]), "=": (f"({column} >= ? AND {column} < ?)", [day0, day1]),
            "!=": (f"({column} < ? OR {column} >= ?)", [day0, day1])}[op]


def condition_sql(expr: Expr) -> tuple[str, list[Any]]:
    """The SQL of ``expr`` over ``j`` (jobs), ``r`` (recordings) and ``v.variant``, and its arguments."""
    if isinstance(expr, Clause):
        parts = [condition_sql(p) for p in expr.parts]
        return "(" + f" {expr.join.upper()} ".join(s for s, _ in parts) + ")", [a for _, args in parts for a in args]
    c = expr
    if c.field.startswith("config."):
        path = _json_path(c.field.removeprefix("config."))
        if c.value is None:
            return f"json_type(j.config, {path}) IS {'NOT ' if c.op == '!=' else ''}NULL", []
        if isinstance(c.value, bool):
            kind = "true" if c.value else "false"
            if c.op == "=":
                return f"json_type(j.config, {path}) = ?", [kind]
            return f"json_type(j.config, {path}) IN ('true', 'false') AND json_type(j.config, {path}) <> ?", [kind]
        return f"json_extract(j.config, {path}) {_sql_op(c.op)} ?", [c.value]
    if c.field == "seed":
        return f"j.seed {_sql_op(c.op)} ?", [c.value]
    if c.field == "commit":
        if c.value is None:
            return f"j.git_commit IS {'NOT ' if c.op == '!=' else ''}NULL", []
        return f"j.git_commit {'NOT ' if c.op == '!=' else ''}LIKE ?", [f"{c.value}%"]  # hex: no wildcard in it
    if c.field in DATE_FIELDS:
        assert isinstance(c.value, float)
        return day_sql(DATE_FIELDS[c.field], c.op, c.value)
    if c.field in TEXT_FIELDS:
        column = TEXT_FIELDS[c.field]
        if c.value is None:
            column = "j.recording_id" if c.field == "recording" else column
            return f"{column} IS {'NOT ' if c.op == '!=' else ''}NULL", []
        if c.field == "recording":
            same = "(r.filename = ? OR j.recording_id = ?)"
            return (same if c.op == "=" else f"NOT {same}"), [c.value, c.value]
        return f"{column} {_sql_op(c.op)} ?", [c.value]
    return f"{metric_sql(c.field)} {_sql_op(c.op)} ?", [c.value]
