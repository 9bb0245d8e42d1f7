"""Config dataclasses as options: one typed parser for every place a user sets a field by name.

``slamreplay record SIM --field-name VALUE`` and ``record ros2 --pole-...`` (:func:`add_dataclass_options`),
a suite's ``args = { field-name = value }`` and a pipeline's ``--set key=value`` / ``--config`` (through
``slamreplay.replay.engine.pipeline``) all convert a value with :func:`parse_value`, so a field takes the same
spellings everywhere and a value that is not of its type is an error, never a silent default.
"""

from __future__ import annotations

import argparse
import dataclasses
import difflib
import types
import typing
from collections.abc import Iterable, Mapping
from typing import Any, Literal

from slamreplay.recorder.errors import RecorderError

TRUE, FALSE = ("1", "true", "yes", "on"), ("0", "false", "no", "off")


def did_you_mean(word: str, known: Iterable[str], quote: bool = False) -> str:
    """``" (did you mean X?)"`` (or ``X or Y``) naming the known words closest to a mistyped ``word``, else ``""``:
    what follows the name in every "unknown NAME" error (config keys, pipelines, metrics, options), as git says it."""
    close = difflib.get_close_matches(word, list(known), n=2, cutoff=0.6)
    if not close:
        return ""
    ratios = [difflib.SequenceMatcher(None, word, c).ratio() for c in close]
    close = [c for c, r in zip(close, ratios, strict=True) if r >= ratios[0] - 0.05]  # a second only if as close
    return " (did you mean " + " or ".join(repr(c) if quote else c for c in close) + "?)"


def parse_pairs(items: Iterable[str], what: str = "--topic-map") -> dict[str, str]:
    """``["A=B", ...]`` as a dict; a ``RecorderError`` naming the option (``what``) for an item that is not A=B."""
    out = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or not key or not value:
            raise RecorderError(f"{what} expects A=B, got {item!r}")
        out[key] = value
    return out


def seed_value(text: str) -> int:
    """An argparse type for a seed: a whole number from 0 to 2**63 - 1 (numpy's generators refuse others)."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a whole number") from None
    if not 0 <= value < 2**63:
        raise argparse.ArgumentTypeError(f"a seed is a whole number from 0 to 2**63 - 1, got {value}")
    return value


def type_name(tp: Any) -> str:
    """How a field's type reads in help and errors: ``float``, ``a|b|c`` for a Literal."""
    if typing.get_origin(tp) is Literal:
        return "|".join(str(a) for a in typing.get_args(tp))
    return getattr(tp, "__name__", str(tp))


def field_types(config_cls: type) -> dict[str, Any]:
    """Field name -> its resolved type (``X | None`` as ``X``), for a config dataclass."""
    hints = typing.get_type_hints(config_cls)
    out = {}
    for f in dataclasses.fields(config_cls):
        tp = hints[f.name]
        args = [a for a in typing.get_args(tp) if a is not type(None)]
        optional = typing.get_origin(tp) in (typing.Union, types.UnionType) and len(args) == 1
        out[f.name] = args[0] if optional else tp
    return out


def parse_value(tp: Any, value: Any) -> Any:
    """``value`` (a command-line string, or a TOML/JSON value) as type ``tp``; ValueError saying what was expected.

    bool: true/false, 1/0, yes/no, on/off; int: a whole number (1.0 is 1, 1.5 is an error); float; str;
    ``Literal[...]``: one of its values."""
    if typing.get_origin(tp) is Literal:
        allowed = typing.get_args(tp)
        if value not in allowed:
            raise ValueError(f"must be one of {', '.join(map(str, allowed))}, got {value!r}")
        return value
    try:
        if tp is bool:
            if isinstance(value, bool):
                return value
            if str(value).lower() in TRUE:
                return True
            if str(value).lower() in FALSE:
                return False
            raise ValueError(value)
        if tp is int:
            if isinstance(value, bool) or (isinstance(value, float) and not value.is_integer()):
                raise ValueError(value)
            return int(value)
        if tp is float:
            if isinstance(value, bool):
                raise ValueError(value)
            return float(value)
        if tp is str:
            return str(value)
    except (TypeError, ValueError):
        name = type_name(tp)
        raise ValueError(f"must be {'an' if name[0] in 'aeiou' else 'a'} {name}, got {value!r}") from None
    raise ValueError(f"has an unsupported type {tp!r}")


def _argparse_type(tp: Any) -> Any:
    def convert(text: str) -> Any:
        try:
            return parse_value(tp, text)
        except ValueError as err:
            raise argparse.ArgumentTypeError(str(err)) from None

    convert.__name__ = type_name(tp)
    return convert


def add_dataclass_options(parser: argparse.ArgumentParser, config_cls: type, prefix: str = "cfg_",
                          option_prefix: str = "", help_prefix: str = "") -> None:
    """One ``--<option_prefix>field-name`` option per field of a config dataclass (stored as ``<prefix>field``),
    typed by :func:`parse_value`, its help from the field's metadata and its default."""
    kinds = field_types(config_cls)
    for f in dataclasses.fields(config_cls):
        name = type_name(kinds[f.name])
        parser.add_argument(f"--{option_prefix}{f.name.replace('_', '-')}", dest=f"{prefix}{f.name}", default=None,
                            type=_argparse_type(kinds[f.name]), metavar=name.upper() if "|" not in name else name,
                            help=help_prefix + field_help(f).replace("%", "%%"))  # argparse %-formats help


def field_help(f: dataclasses.Field[Any]) -> str:
    """The help line of a config field: its ``help`` metadata and its default (a ``None`` default is
    explained by the help itself); the bare field name when the field has no help."""
    text = f.metadata.get("help", "") or f.name.replace("_", " ")
    if f.default is dataclasses.MISSING or f.default is None:
        return text
    default = f.default if not isinstance(f.default, str) else (repr(f.default) if not f.default else f.default)
    return f"{text} (default: {default})"


def dataclass_from_options(options: Mapping[str, Any], config_cls: type, prefix: str = "cfg_",
                           what: str = "simulator option") -> Any:
    """The config dataclass from the options given (others keep their defaults); RecorderError when invalid."""
    values = {k[len(prefix):]: v for k, v in options.items() if k.startswith(prefix) and v is not None}
    try:
        return config_cls(**values)
    except (TypeError, ValueError) as err:
        raise RecorderError(f"invalid {what}: {err}") from err


def typed_fields(config_cls: type, values: Mapping[str, Any]) -> dict[str, Any]:
    """``values`` keyed by field name, each converted by :func:`parse_value`; ValueError naming an unknown field
    or a value of the wrong type."""
    kinds = field_types(config_cls)
    out = {}
    for key, value in values.items():
        if key not in kinds:
            raise ValueError(f"unknown field {key!r}")
        try:
            out[key] = parse_value(kinds[key], value)
        except ValueError as err:
            raise ValueError(f"{key} {err}") from None
    return out
