"""Every change named: an external program edited under the same version string is a change in every output."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from conftest import write_tiny_recording

from slamreplay.api.cli.command import main
from slamreplay.replay.runs.compare import compare, format_table, load_side
from slamreplay.replay.runs.diff import describe_origin, diff_runs, origin_changes
from slamreplay.replay.runs.diff import format_table as diff_table
from slamreplay.replay.runs.report import render_html, render_markdown
from slamreplay.replay.runs.run import run_recording
from tests.replay.test_external import DEAD_RECKONING, declare

# the same program with its heading drifting: same version string (the Python's), another script
EDITED = DEAD_RECKONING.replace("th = th + oth - pth", "th = th + 1.02 * (oth - pth)")


def test_origin_changes_name_each_field() -> None:
    """Version, command, build and every hash are compared one by one; paths are not; old runs give nothing."""
    a = {"distribution": "external", "version": "v1", "executable": "/a/bin/prog", "executable_sha256": "1" * 64,
         "files_sha256": {"run.py": "2" * 64, "lib.py": "3" * 64}, "declaration_sha256": "4" * 64,
         "build": ["make"], "command": ["prog", "{out}"]}
    b = {**a, "executable": "/b/bin/prog", "files_sha256": {"run.py": "5" * 64}, "build": ["make", "-j2"]}
    fields = [c["field"] for c in origin_changes(a, b)]
    assert fields == ["pipeline_origin.build", "pipeline_origin.files_sha256.lib.py",
                      "pipeline_origin.files_sha256.run.py"]
    assert origin_changes(a, dict(a)) == [] and origin_changes(None, a) == []
    text = describe_origin(a)
    assert text.startswith("external: version v1") and "executable 111111111111" in text and "build make" in text
    assert "file run.py 222222222222" in text and describe_origin({"distribution": "slamreplay", "version": "1"}) == ""


def test_an_edited_program_is_never_nothing_changed(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                    capsys: pytest.CaptureFixture[str]) -> None:
    """The script edited, version string unchanged: diff names the file's hash and the worse metrics, exit 1;
    compare shows both programs in the terminal, markdown, HTML and JSON; the same script twice: nothing
    changed, same program."""
    rec = write_tiny_recording(tmp_path / "tiny.mcap")
    (tmp_path / "v1").mkdir()
    (tmp_path / "v2").mkdir()
    declare(tmp_path / "v1", monkeypatch, DEAD_RECKONING)
    a = run_recording(rec, "ext", tmp_path / "a").run_dir
    again = run_recording(rec, "ext", tmp_path / "again").run_dir
    declare(tmp_path / "v2", monkeypatch, EDITED)
    b = run_recording(rec, "ext", tmp_path / "b").run_dir

    same = diff_runs(a, again, compare_rrd=False)
    assert same.changes == [] and set(same.programs) == {"A", "B"}
    assert "What changed: nothing (same recording, pipeline, config, seed and code, same program)" in diff_table(same)

    d = diff_runs(a, b, compare_rrd=False)
    fields = {c["field"] for c in d.changes}
    assert fields == {"pipeline_origin.files_sha256.prog.py"}  # same declaration text, same version string
    assert "ape_rmse_m" in d.worse
    assert main(["diff", str(a), str(b)]) == 1
    out = capsys.readouterr().out
    assert "pipeline_origin.files_sha256.prog.py" in out and "program B: external: version Python" in out

    c = compare(load_side(a), load_side(b))
    changed = [ch["field"] for ch in c.changes]
    assert any(f.endswith("pipeline_origin.files_sha256.prog.py") for f in changed)
    assert len(c.programs) == 1 and c.programs[0]["A"] != c.programs[0]["B"]
    prog_b = c.programs[0]["B"]
    assert prog_b in format_table(c) and prog_b in render_markdown(c, tmp_path)
    assert prog_b.replace("'", "&#x27;") in render_html(c, tmp_path)
    assert json.loads(json.dumps(c.to_json()))["programs"][0]["B"] == prog_b
