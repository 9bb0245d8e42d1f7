"""recorder.options: one typed parser for record's options, suite args and pipeline config keys."""

from __future__ import annotations

import argparse
from dataclasses import dataclass, field
from typing import Literal

import pytest

from slamreplay.recorder.errors import RecorderError
from slamreplay.recorder.options import (
    add_dataclass_options,
    dataclass_from_options,
    did_you_mean,
    parse_value,
    typed_fields,
)


@dataclass(frozen=True)
class Cfg:
    rate_hz: float = field(default=5.0, metadata={"help": "images per second"})
    laps: int = 1
    circle_fit: bool = True
    mode: Literal["a", "b"] = "a"
    label: str | None = None


@pytest.mark.parametrize(("tp", "value", "want"), [
    (bool, "on", True), (bool, "No", False), (bool, True, True), (int, "3", 3), (int, 2.0, 2), (float, "0.5", 0.5),
    (float, 2, 2.0), (str, "x", "x"), (Literal["a", "b"], "b", "b")])
def test_parse_value_accepts_each_types_spellings(tp: object, value: object, want: object) -> None:
    got = parse_value(tp, value)
    assert got == want and type(got) is type(want)


@pytest.mark.parametrize(("tp", "value", "match"), [
    (bool, "maybe", "must be a bool, got 'maybe'"), (int, 1.5, "must be an int, got 1.5"), (int, True, "int"),
    (float, "fast", "must be a float"), (Literal["a", "b"], "c", "must be one of a, b, got 'c'")])
def test_parse_value_refuses_what_is_not_of_the_type(tp: object, value: object, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        parse_value(tp, value)


def test_options_parse_typed_values_and_keep_unset_fields_at_their_defaults() -> None:
    parser = argparse.ArgumentParser(exit_on_error=False)
    add_dataclass_options(parser, Cfg, prefix="p_", option_prefix="pole-")
    ns = vars(parser.parse_args(["--pole-rate-hz", "2.5", "--pole-circle-fit", "false", "--pole-label", "x"]))
    assert dataclass_from_options(ns, Cfg, prefix="p_") == Cfg(rate_hz=2.5, circle_fit=False, label="x")
    assert "images per second (default: 5.0)" in parser.format_help()


def test_a_bad_option_value_is_a_usage_error_not_a_silent_default(capsys: pytest.CaptureFixture[str]) -> None:
    """A flag that is not true/false used to read as False: now argparse refuses it (exit 2, one line)."""
    parser = argparse.ArgumentParser(prog="record ros2")
    add_dataclass_options(parser, Cfg, prefix="p_", option_prefix="pole-")
    with pytest.raises(SystemExit) as exc:
        parser.parse_args(["--pole-circle-fit", "maybe"])
    assert exc.value.code == 2
    assert "argument --pole-circle-fit: must be a bool, got 'maybe'" in capsys.readouterr().err


def test_invalid_combination_is_a_recorder_error() -> None:
    with pytest.raises(RecorderError, match="invalid simulator option"):
        dataclass_from_options({"cfg_nope": 1}, Cfg)


def test_typed_fields_names_the_field() -> None:
    assert typed_fields(Cfg, {"laps": "2", "rate_hz": 1}) == {"laps": 2, "rate_hz": 1.0}
    with pytest.raises(ValueError, match="laps must be an int, got 'two'"):
        typed_fields(Cfg, {"laps": "two"})
    with pytest.raises(ValueError, match="unknown field 'lap'"):
        typed_fields(Cfg, {"lap": 2})


def test_help_lines_give_the_default_and_survive_a_percent_sign() -> None:
    """A None default is left to the help text; a % in it does not break argparse's formatting."""

    @dataclass(frozen=True)
    class Pct:
        gain: float = field(default=0.01, metadata={"help": "scale error (0.01: 1 % fast)"})
        area_m: float | None = field(default=None, metadata={"help": "side, metres (default: from the grid)"})

    parser = argparse.ArgumentParser(prog="record x")
    add_dataclass_options(parser, Pct)
    text = " ".join(parser.format_help().split())
    assert "scale error (0.01: 1 % fast) (default: 0.01)" in text
    assert "side, metres (default: from the grid)" in text and "(default: None)" not in text


def test_did_you_mean_names_the_closest_or_nothing() -> None:
    assert did_you_mean("rang_sigma_m", ["range_sigma_m", "bearing_sigma_deg"], quote=True) == \
        " (did you mean 'range_sigma_m'?)"
    assert did_you_mean("--sed", ["--seed", "--out"]) == " (did you mean --seed?)"
    assert did_you_mean("zzz", ["range_sigma_m"]) == ""
