"""The layer rules of docs/design.md, checked on the source: api -> replay -> {recorder, algorithms}."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
PACKAGES = ("recorder", "replay", "algorithms", "api")
# What each package may import among the project's packages and the heavy third-party ones.
ALLOWED_PROJECT = {"algorithms": {"algorithms"}, "recorder": {"recorder"},
                   "replay": {"replay", "recorder", "algorithms"}, "api": set(PACKAGES)}
# numeric libraries only; sksparse and cvxopt are bindings of CHOLMOD (the pose-graph Cholesky)
ALGORITHMS_THIRD_PARTY = {"numpy", "scipy", "cv2", "sksparse", "cvxopt"}


def imports_of(path: Path) -> set[str]:
    """Top-level module names imported by a file."""
    tree = ast.parse(path.read_text(), filename=str(path))
    names = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names |= {a.name.split(".")[0] for a in node.names}
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            names.add(node.module.split(".")[0])
    return names


def files(package: str) -> list[Path]:
    return sorted((REPO / package).rglob("*.py"))


@pytest.mark.parametrize("package", PACKAGES)
def test_project_imports_follow_layers(package: str) -> None:
    """No package imports a project package above or beside it."""
    for path in files(package):
        bad = (imports_of(path) & set(PACKAGES)) - ALLOWED_PROJECT[package]
        assert not bad, f"{path.relative_to(REPO)} imports {sorted(bad)}"


def test_algorithms_are_pure_math() -> None:
    """algorithms/ imports only the standard library, numpy, scipy and cv2."""
    import sys

    stdlib = set(sys.stdlib_module_names)
    for path in files("algorithms"):
        third = imports_of(path) - stdlib - {"algorithms", "__future__"}
        assert third <= ALGORITHMS_THIRD_PARTY, f"{path.relative_to(REPO)} imports {sorted(third)}"


def test_only_api_uses_web_stack_and_only_replay_uses_rerun() -> None:
    """fastapi/pydantic/uvicorn live in api/; rerun never in recorder/ or algorithms/."""
    for package in ("recorder", "replay", "algorithms"):
        for path in files(package):
            web = imports_of(path) & {"fastapi", "pydantic", "uvicorn", "starlette"}
            assert not web, f"{path.relative_to(REPO)} imports {sorted(web)}"
    for package in ("recorder", "algorithms"):
        for path in files(package):
            assert "rerun" not in imports_of(path), f"{path.relative_to(REPO)} imports rerun"
