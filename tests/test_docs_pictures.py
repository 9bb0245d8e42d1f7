"""The pictures README.md and docs/ show are the ones their records say (docs/pictures.py): made by the build at
a clean commit, unchanged since, showing metrics the registry still has. `make snapshots` writes the records;
the values a demo picture shows are checked against a fresh demo in tests/test_readme.py."""

from __future__ import annotations

import importlib.util
import json
import sys
from pathlib import Path

import pytest

from slamreplay.replay.metric_registry import spec
from slamreplay.replay.runs.diff import metric_tolerance
from slamreplay.replay.runs.diff_view import run_name

REPO = Path(__file__).resolve().parents[1]


def _pictures() -> object:
    loaded = importlib.util.spec_from_file_location("pictures", REPO / "docs" / "pictures.py")
    assert loaded is not None and loaded.loader is not None
    module = importlib.util.module_from_spec(loaded)
    sys.modules["pictures"] = module
    loaded.loader.exec_module(module)
    return module


pictures = _pictures()


def registered(name: str) -> bool:
    """Whether the metric registry knows ``name`` under its current name (a per-robot name included)."""
    try:
        spec(name)
    except KeyError:
        return False
    return True


@pytest.mark.docs
def test_every_picture_is_recorded_unchanged_and_current() -> None:
    """Each picture README.md or docs/*.md links has a record: its png's sha256, a clean commit, registered metrics."""
    found = pictures.problems(pictures.load(), pictures.IMAGES, pictures.linked(), registered)  # type: ignore[attr-defined]
    assert not found, "\n".join(found)


def _fake(tmp_path: Path, metrics: dict[str, float], commit: str = "a" * 40) -> tuple[dict, Path]:
    images = tmp_path / "images"
    images.mkdir()
    (images / "x.png").write_bytes(b"\x89PNG picture")
    rec = {"made_by": "make snapshots", "commit": commit, "sha256": pictures.sha256(images / "x.png"),  # type: ignore[attr-defined]
           "source": "demo", "metrics": metrics}
    return {"x.png": rec}, images


def test_a_picture_made_before_a_metric_rename_fails(tmp_path: Path) -> None:
    """A record naming robot_ate_rmse_m (renamed ape_rmse_m) is a problem; the current name is not."""
    records, images = _fake(tmp_path, {"demo-run/robot_ate_rmse_m": 0.2, "demo-run/ape_rmse_m": 0.2})
    found = pictures.problems(records, images, {"x.png": "README.md:1"}, registered)  # type: ignore[attr-defined]
    assert len(found) == 1 and "'robot_ate_rmse_m'" in found[0] and "registry" in found[0]


def test_a_dirty_unrecorded_or_replaced_picture_fails(tmp_path: Path) -> None:
    """A -dirty commit, a png replaced by hand and a linked picture without a record are each named."""
    records, images = _fake(tmp_path, {}, commit="a" * 40 + "-dirty")
    (images / "x.png").write_bytes(b"\x89PNG another picture")
    found = pictures.problems(records, images, {"x.png": "README.md:1", "y.png": "docs/a.md:3"}, registered)  # type: ignore[attr-defined]
    assert any("y.png, which has no record" in f for f in found)
    assert any("sha256 differs" in f for f in found)
    assert any("not a clean commit" in f for f in found)


def test_a_record_is_of_the_png_as_it_is_and_never_of_a_dirty_tree(tmp_path: Path) -> None:
    """pictures.record (what make snapshots and the report scripts write): the png's sha256, no problem found;
    a -dirty commit is refused when the picture is recorded, not only when it is checked."""
    png = tmp_path / "x.png"
    png.write_bytes(b"\x89PNG picture")
    rec = pictures.record(png, "make snapshots", "a" * 40, "demo", {"demo-run/ape_rmse_m": 0.2})  # type: ignore[attr-defined]
    assert rec["sha256"] == pictures.sha256(png) and rec["metrics"] == {"demo-run/ape_rmse_m": 0.2}  # type: ignore[attr-defined]
    assert pictures.problems({"x.png": rec}, tmp_path, {"x.png": "README.md:1"}, registered) == []  # type: ignore[attr-defined]
    with pytest.raises(ValueError, match="clean commit"):
        pictures.record(png, "make snapshots", "a" * 40 + "-dirty", "demo", {})  # type: ignore[attr-defined]


def test_a_value_a_fresh_demo_no_longer_gives_fails(tmp_path: Path) -> None:
    """A demo picture's value is compared with the demo's metrics.json within the metric's tolerance."""
    records, _ = _fake(tmp_path, {"demo-run/ape_rmse_m": 0.2, "demo-run/steps": 3001.0})
    (tmp_path / "demo" / "demo-run").mkdir(parents=True)
    entries = {"ape_rmse_m": {"value": 0.2000001, "tolerance": 1e-6, "rel_tolerance": 1e-3},
               "steps": {"value": 3002, "tolerance": 0}}
    (tmp_path / "demo" / "demo-run" / "metrics.json").write_text(json.dumps({"metrics": entries}))
    found = pictures.value_problems(records, tmp_path / "demo", metric_tolerance)  # type: ignore[attr-defined]
    assert found == ["x.png: shows demo-run/steps = 3001; a fresh demo gives 3002"]


def test_a_diff_names_its_runs_without_the_machines_paths(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Runs are named relative to the working directory, or by their last two folders outside it."""
    monkeypatch.chdir(tmp_path)
    assert run_name(tmp_path / "runs" / "a") == "runs/a"
    assert run_name("runs/b") == "runs/b"
    assert run_name("/elsewhere/home/me/demo/sim-landmarks--dslam") == "demo/sim-landmarks--dslam"


def test_snapshot_without_a_vulkan_driver_names_the_packages(monkeypatch: pytest.MonkeyPatch) -> None:
    """`slamreplay snapshot` on a headless machine without Vulkan says which Debian packages the README names."""
    import ctypes.util

    from slamreplay.replay.errors import ReplayError
    from slamreplay.replay.tools import snapshot

    monkeypatch.setattr(ctypes.util, "find_library", lambda name: None)
    with pytest.raises(ReplayError, match=r"apt-get install mesa-vulkan-drivers libvulkan1"):
        snapshot.check_graphics()
    readme = (REPO / "README.md").read_text()
    assert "mesa-vulkan-drivers libvulkan1" in readme
