"""Suite files: parsing, errors that name file, line and key, and cell expansion."""

from __future__ import annotations

from pathlib import Path

import pytest

from slamreplay.replay.errors import ReplayError
from slamreplay.replay.runs.suite import key_line, load_suite, parse_suite

GOOD = """\
seeds = [1, 2]                                # run seeds
[recordings.landmarks]
sim = "sim-landmarks"
args = { duration-s = 20 }
seeds = [1, 2, 3]
[recordings.file]
path = "tiny.mcap"
[pipelines.odometry]
[pipelines.dslam.variants]
default = {}
tight = { range_gate_sigma = 2.0 }
"""


def write(tmp_path: Path, text: str) -> Path:
    (tmp_path / "tiny.mcap").write_bytes(b"")
    p = tmp_path / "suite.toml"
    p.write_text(text)
    return p


def test_parse_and_expand(tmp_path: Path) -> None:
    """The issue's form parses; cells are recordings x recording seeds x pipelines x variants x seeds."""
    text = GOOD.replace("range_gate_sigma", _a_dslam_float_key())
    suite = load_suite(write(tmp_path, text))
    assert suite.seeds == (1, 2)
    assert suite.recordings["landmarks"].seeds == (1, 2, 3)
    assert suite.recordings["file"].path == tmp_path / "tiny.mcap"
    assert list(suite.pipelines["odometry"]) == ["default"]
    assert list(suite.pipelines["dslam"]) == ["default", "tight"]
    cells = suite.cells()
    # (3 sim recordings + 1 file) x (1 + 2 variants) x 2 seeds
    assert len(cells) == 4 * 3 * 2
    assert len({c.label for c in cells}) == len(cells)
    assert {c.recording_seed for c in cells if c.recording == "file"} == {None}
    groups = {c.group for c in cells}
    assert ("landmarks", "dslam", "tight") in groups and len(groups) == 2 * 3


def test_a_variant_names_a_preset(tmp_path: Path) -> None:
    """``preset`` writes the pipeline's preset into the variant's config; the variant's own keys win over it;
    a pipeline-level preset applies to the variants that name none."""
    from slamreplay.replay.engine.pipeline import get_pipeline

    paper = get_pipeline("dslam").presets["paper"]
    key = next(iter(paper))
    text = GOOD.replace("tight = { range_gate_sigma = 2.0 }",
                        f'paper = {{ preset = "paper" }}\nmixed = {{ preset = "paper", {key} = {paper[key] + 1} }}')
    suite = load_suite(write(tmp_path, text))
    variants = suite.pipelines["dslam"]
    assert variants["default"] == {} and variants["paper"] == paper
    assert variants["mixed"] == {**paper, key: paper[key] + 1}
    assert "preset" not in variants["paper"]
    text = GOOD.replace("[pipelines.dslam.variants]", '[pipelines.dslam]\npreset = "paper"\n[pipelines.dslam.variants]')
    suite = load_suite(write(tmp_path, text.replace("range_gate_sigma", _a_dslam_float_key())))
    assert suite.pipelines["dslam"]["default"] == paper


def _a_dslam_float_key() -> str:
    from slamreplay.replay.engine.pipeline import config_schema, get_pipeline

    return next(r["key"] for r in config_schema(get_pipeline("dslam").Config) if r["type"] == "float")


@pytest.mark.parametrize(("text", "line", "pattern"), [
    (GOOD.replace("seeds = [1, 2, 3]", "seeds = [1, 1]"), 5, r"recordings\.landmarks\.seeds: lists a seed twice"),
    (GOOD.replace("duration-s = 20", "duraton-s = 20"), 4, r"recordings\.landmarks\.args\.duraton-s: .*no option"),
    (GOOD.replace("duration-s = 20", "duration-s = -1"), 4, r"recordings\.landmarks\.args: invalid sim-landmarks"),
    (GOOD.replace('sim = "sim-landmarks"', 'sim = "sim-moon"'), 3, r"unknown simulator 'sim-moon'"),
    (GOOD.replace("tight = { range_gate_sigma = 2.0 }", "tight = { no_such_key = 2.0 }"), 11,
     r"pipelines\.dslam\.variants\.tight\.no_such_key: unknown config key"),
    (GOOD.replace("[pipelines.odometry]", "[pipelines.odometri]"), 8, r"pipelines\.odometri: unknown pipeline"),
    (GOOD.replace('path = "tiny.mcap"', 'path = "missing.mcap"'), 7, r"recordings\.file\.path: .*does not exist"),
    (GOOD.replace('path = "tiny.mcap"', 'path = "tiny.mcap"\nsim = "sim-landmarks"'), 6,
     r"recordings\.file: needs exactly one of"),
    (GOOD.replace("seeds = [1, 2]  ", "sedes = [1, 2]  "), 1, r"sedes: unknown key"),
    (GOOD.replace("seeds = [1, 2]  ", "seeds = [-1]    "), 1, r"seeds: must be a non-empty list of integers"),
    (GOOD + "[pipelines.odometry.extra]\n", 12, r"pipelines\.odometry\.extra: unknown key"),
    (GOOD.replace("tight = { range_gate_sigma = 2.0 }", 'tight = { preset = "papr" }'), 11,
     r"pipelines\.dslam\.variants\.tight\.preset: pipeline dslam has no preset 'papr' \(did you mean 'paper'\?\); "
     r"its presets: paper"),
    (GOOD.replace("[pipelines.odometry]", '[pipelines.odometry]\npreset = "fast"'), 9,
     r"pipelines\.odometry\.preset: pipeline odometry has no preset 'fast'; its presets: "),
])
def test_errors_name_file_line_and_key(tmp_path: Path, text: str, line: int, pattern: str) -> None:
    """Each validation error starts with FILE:LINE and names the key."""
    path = write(tmp_path, text.replace("range_gate_sigma", _a_dslam_float_key()))
    with pytest.raises(ReplayError, match=pattern) as err:
        load_suite(path)
    assert str(err.value).startswith(f"{path}:{line}: "), str(err.value)


def test_errors_without_a_line(tmp_path: Path) -> None:
    """Broken TOML, no recordings, no pipelines, a missing file: one clear message each."""
    with pytest.raises(ReplayError, match=r"not valid TOML"):
        parse_suite("seeds = [1", tmp_path / "s.toml")
    with pytest.raises(ReplayError, match=r"names no recordings"):
        parse_suite("[pipelines.odometry]\n", tmp_path / "s.toml")
    with pytest.raises(ReplayError, match=r"names no pipelines"):
        parse_suite('[recordings.a]\nsim = "sim-landmarks"\n', tmp_path / "s.toml")
    with pytest.raises(ReplayError, match=r"suite file .* does not exist"):
        load_suite(tmp_path / "nope.toml")


def test_key_line_forms() -> None:
    """Headers, dotted keys, inline tables and quoted keys are found on their own line."""
    text = ('a = 1\n[x.y]\nb = { c = 2, "d e" = 3 }\n[x.y.z]\n# comment\n"q" = 4\nw.v = 5\n'
            '[[arr]]\nk = 1\n')
    assert key_line(text, ["a"]) == 1
    assert key_line(text, ["x", "y"]) == 2
    assert key_line(text, ["x", "y", "b"]) == 3
    assert key_line(text, ["x", "y", "b", "c"]) == 3
    assert key_line(text, ["x", "y", "b", "d e"]) == 3
    assert key_line(text, ["x", "y", "z"]) == 4
    assert key_line(text, ["x", "y", "z", "q"]) == 6
    assert key_line(text, ["x", "y", "z", "w", "v"]) == 7
    assert key_line(text, ["x"]) == 2  # a table only opened through a sub-table: its first header
    assert key_line(text, ["arr", "k"]) == 9
    assert key_line(text, ["nothing"]) is None
