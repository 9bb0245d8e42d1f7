"""Pipelines found through the entry-point group slamreplay.pipelines: built-ins, a user's, broken ones."""

from __future__ import annotations

import json
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest
from conftest import make_distribution, write_tiny_recording

from slamreplay.api.cli.command import main
from slamreplay.recorder.plugins import refresh
from slamreplay.replay.engine.pipeline import all_pipelines, get_pipeline, pipeline_plugins
from slamreplay.replay.errors import ReplayError

BUILTINS = {"dslam", "ekfslam", "ifmi", "odometry", "topometric", "topometric-nav"}

GOOD = '''
from slamreplay.replay.pipelines.odometry import OdometryPipeline


class Good(OdometryPipeline):
    name = "good"
    summary = "dead reckoning under another name"


class Misnamed(OdometryPipeline):
    name = "something-else"


def helper():
    return 1
'''


@pytest.fixture
def plugins(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[Path]:
    """A fake distribution `fake-plugins 1.2` with one good and four broken pipeline entry points."""
    root = tmp_path / "site"
    make_distribution(root, "fake-plugins", "1.2", {
        "good": "fakeplug.good:Good",
        "no-module": "fakeplug.missing:Cls",
        "raises": "fakeplug.raises:Cls",
        "not-a-class": "fakeplug.good:helper",
        "misnamed": "fakeplug.good:Misnamed",
    }, {"fakeplug.__init__": "", "fakeplug.good": GOOD, "fakeplug.raises": "raise RuntimeError('boom at import')\n"})
    monkeypatch.syspath_prepend(str(root))
    refresh()
    yield root
    refresh()
    for mod in [m for m in sys.modules if m == "fakeplug" or m.startswith("fakeplug.")]:
        del sys.modules[mod]


def test_builtins_come_from_entry_points() -> None:
    """The six built-in pipelines are entry points of the slamreplay distribution itself."""
    found = pipeline_plugins()
    assert set(found) >= BUILTINS
    assert all(found[n].origin == "built-in" and found[n].error is None for n in BUILTINS)
    assert get_pipeline("odometry").__name__ == "OdometryPipeline"


def test_user_plugin_is_found_and_runs(plugins: Path, tmp_path: Path) -> None:
    """A third-party entry point is listed with its distribution and runs like a built-in."""
    found = pipeline_plugins()
    assert found["good"].origin == "fake-plugins 1.2" and found["good"].error is None
    assert "good" in all_pipelines() and set(all_pipelines()) >= BUILTINS
    assert not {"no-module", "raises", "not-a-class", "misnamed"} & set(all_pipelines())
    rec = write_tiny_recording(tmp_path / "tiny.mcap")
    assert main(["run", str(rec), "--pipeline", "good", "--out", str(tmp_path / "g"), "-q"]) == 0
    assert main(["run", str(rec), "--pipeline", "odometry", "--out", str(tmp_path / "o"), "-q"]) == 0
    manifest = json.loads((tmp_path / "g" / "manifest.json").read_text())
    assert manifest["pipeline_origin"] == {"distribution": "fake-plugins", "version": "1.2",
                                           "entry_point": "fakeplug.good:Good"}
    good = json.loads((tmp_path / "g" / "metrics.json").read_text())["metrics"]
    odom = json.loads((tmp_path / "o" / "metrics.json").read_text())["metrics"]
    assert good["ape_rmse_m"] == odom["ape_rmse_m"]


@pytest.mark.parametrize(("name", "reason"), [
    ("no-module", r"failed to import: ModuleNotFoundError: No module named 'fakeplug\.missing'"),
    ("raises", r"failed to import: RuntimeError: boom at import"),
    ("not-a-class", r"is not a Pipeline subclass \(it is function 'helper'\)"),
    ("misnamed", r"registered as 'misnamed' but its class says name = 'something-else'"),
])
def test_broken_plugin_is_one_line_when_used(plugins: Path, tmp_path: Path, name: str, reason: str,
                                             capsys: pytest.CaptureFixture[str]) -> None:
    """Running a broken plugin: exit 2, one line naming the plugin, its distribution and what is wrong."""
    rec = write_tiny_recording(tmp_path / "tiny.mcap")
    code = main(["run", str(rec), "--pipeline", name, "--out", str(tmp_path / "r")])
    err = capsys.readouterr().err
    lines = err.strip().splitlines()
    assert code == 2 and len(lines) == 1 and "Traceback" not in err, err
    assert f"pipeline plugin '{name}'" in lines[0] and "distribution fake-plugins 1.2" in lines[0]
    assert pytest.importorskip("re").search(reason, lines[0]), lines[0]
    assert not (tmp_path / "r").exists()
    with pytest.raises(ReplayError, match=reason):
        get_pipeline(name)


def test_pipelines_lists_broken_plugins(plugins: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """`slamreplay pipelines` lists every pipeline with its origin, the broken ones with why, and exits 2."""
    code = main(["pipelines"])
    out, err = capsys.readouterr()
    assert code == 2
    assert "good: dead reckoning under another name\n  from:     fake-plugins 1.2 (fakeplug.good:Good)" in out
    assert "odometry: dead reckoning" in out and "  from:     built-in" in out
    assert "raises: BROKEN (fake-plugins 1.2, fakeplug.raises:Cls): failed to import: RuntimeError" in out
    assert len(err.strip().splitlines()) == 4 and all("fake-plugins" in ln for ln in err.strip().splitlines())
    code = main(["pipelines", "--json"])
    rows = {r["name"]: r for r in json.loads(capsys.readouterr().out)}
    assert code == 2 and rows["good"]["origin"] == "fake-plugins 1.2" and rows["good"]["error"] is None
    assert rows["odometry"]["origin"] == "built-in" and "boom" in rows["raises"]["error"]


def test_same_name_from_two_distributions(plugins: Path, tmp_path: Path) -> None:
    """Two distributions claiming one name: neither is used, the error names both."""
    other = tmp_path / "other"
    make_distribution(other, "other-plugins", "3.0", {"good": "fakeplug.good:Good"}, {})
    sys.path.insert(0, str(other))
    try:
        refresh()
        with pytest.raises(ReplayError, match=r"several distributions \(.*fake-plugins 1\.2.*other-plugins 3\.0"):
            get_pipeline("good")
    finally:
        sys.path.remove(str(other))
        refresh()


def test_unknown_pipeline_names_the_known_ones() -> None:
    """An unknown name lists the known pipelines."""
    with pytest.raises(ReplayError, match=r"unknown pipeline 'nope'; known pipelines: dslam, dslam-multi, ekfslam"):
        get_pipeline("nope")


def test_uninstalled_source_tree_says_to_install(monkeypatch: pytest.MonkeyPatch,
                                                 capsys: pytest.CaptureFixture[str]) -> None:
    """With no entry points at all (a source tree that was never installed): one line saying to install it."""
    import slamreplay.recorder.plugins as plugins

    monkeypatch.setattr(plugins.md, "entry_points", lambda group: [])
    refresh()
    try:
        with pytest.raises(ReplayError, match=r"only seen once it is installed \(`pip install -e \.`"):
            get_pipeline("odometry")
        assert main(["pipelines"]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and "no entry points in group 'slamreplay.pipelines'" in err[0]
    finally:
        refresh()
