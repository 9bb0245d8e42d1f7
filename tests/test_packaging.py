"""pyproject.toml: a PEP 639 licence, typed packages, bounded dependencies, entry points that resolve."""

from __future__ import annotations

import importlib
import re
import sys
from pathlib import Path

import pytest

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

REPO = Path(__file__).resolve().parents[1]
PYPROJECT = tomllib.loads((REPO / "pyproject.toml").read_text())
PACKAGES = ("recorder", "replay", "algorithms", "api")


def test_licence_is_a_pep639_expression() -> None:
    """`license` is an SPDX string with its file (no TOML table: setuptools' deprecation banner)."""
    project = PYPROJECT["project"]
    assert project["license"] == "MIT" and project["license-files"] == ["LICENSE"]
    assert (REPO / "LICENSE").read_text().startswith("MIT License")


@pytest.mark.parametrize("package", PACKAGES)
def test_packages_ship_py_typed(package: str) -> None:
    """Each package carries a PEP 561 marker, and package-data ships it."""
    assert (REPO / package / "py.typed").exists()
    assert "py.typed" in PYPROJECT["tool"]["setuptools"]["package-data"]["*"]


def test_runtime_dependencies_have_upper_bounds() -> None:
    """Every run-time dependency is bounded above (<N or ~=), so a breaking release is taken on purpose."""
    unbounded = [d for d in PYPROJECT["project"]["dependencies"]
                 if not re.search(r"<|~=", d.split(";")[0])]
    assert not unbounded, unbounded


@pytest.mark.parametrize("group", ["slamreplay.pipelines", "slamreplay.importers"])
def test_declared_entry_points_resolve(group: str) -> None:
    """Each built-in entry point names an existing attribute whose `name` is the entry point's."""
    for name, value in PYPROJECT["project"]["entry-points"][group].items():
        module, _, attr = value.partition(":")
        obj = getattr(importlib.import_module(module), attr)
        assert obj.name == name, value


def test_every_package_folder_is_listed_under_the_namespace() -> None:
    """[tool.setuptools] packages lists every folder of the four packages (data folders too) as
    ``slamreplay.<package>...``, and package-dir maps each package to its repository folder."""
    setup = PYPROJECT["tool"]["setuptools"]
    assert setup["package-dir"] == {f"slamreplay.{p}": p for p in PACKAGES}
    folders = {"slamreplay." + ".".join(d.relative_to(REPO).parts)
               for p in PACKAGES for d in [REPO / p, *(REPO / p).rglob("*")]
               if d.is_dir() and d.name != "__pycache__" and any(f.is_file() for f in d.iterdir())}
    assert set(setup["packages"]) == folders


def test_installed_names_are_under_slamreplay() -> None:
    """The project imports as slamreplay.<package>, from this repository's folders."""
    import slamreplay.api.cli.command
    import slamreplay.replay.runs.run

    assert Path(slamreplay.api.cli.command.__file__).resolve() == REPO / "api" / "cli" / "command.py"
    assert Path(slamreplay.replay.runs.run.__file__).resolve() == REPO / "replay" / "runs" / "run.py"
