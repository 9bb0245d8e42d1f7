"""The layer rules of docs/design.md, checked on the source: api -> replay -> {recorder, algorithms}."""

from __future__ import annotations

import ast
from collections.abc import Iterable
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
PACKAGES = ("recorder", "replay", "algorithms", "api")
# What each package may import among the project's packages and the heavy third-party ones.
ALLOWED_PROJECT = {"algorithms": {"algorithms"}, "recorder": {"recorder"},
                   "replay": {"replay", "recorder", "algorithms"}, "api": set(PACKAGES)}
# numeric libraries only; sksparse and cvxopt are bindings of CHOLMOD, qdldl an LDL' (the pose-graph Cholesky)
ALGORITHMS_THIRD_PARTY = {"numpy", "scipy", "cv2", "sksparse", "cvxopt", "qdldl"}


def _top(module: str) -> str:
    """The top-level name of ``module``; for the project's own, the package under ``slamreplay``."""
    parts = module.split(".")
    return parts[1] if parts[0] == "slamreplay" and len(parts) > 1 else parts[0]


def imports_of(path: Path) -> set[str]:
    """Top-level module names imported by a file (``slamreplay.replay.runs.run`` counts as ``replay``)."""
    tree = ast.parse(path.read_text(), filename=str(path))
    names = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names |= {_top(a.name) for a in node.names}
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            names.add(_top(node.module))
    return names


def bare_project_imports(path: Path) -> list[str]:
    """Imports of the project's packages by their bare names (``import replay``), which exist only in the
    repository, never in an installed slamreplay."""
    tree = ast.parse(path.read_text(), filename=str(path))
    bad = []
    for node in ast.walk(tree):
        names = ([a.name for a in node.names] if isinstance(node, ast.Import)
                 else [node.module] if isinstance(node, ast.ImportFrom) and node.level == 0 and node.module else [])
        bad += [f"line {node.lineno}: {n}" for n in names if n.split(".")[0] in PACKAGES]
    return bad


def test_project_is_imported_through_the_slamreplay_namespace() -> None:
    """Every Python file of the repository (packages, tests, benchmarks, examples, docs) imports the project as
    ``slamreplay.<package>``: the names an install provides."""
    skip = {".venv", ".git", "build", "node_modules"}
    offenders = {}
    for path in sorted(REPO.rglob("*.py")):
        rel = path.relative_to(REPO)
        if skip & set(rel.parts) or rel.parts[0].startswith(".venv"):
            continue
        if bad := bare_project_imports(path):
            offenders[str(rel)] = bad
    assert not offenders, offenders


def files(package: str) -> list[Path]:
    return sorted((REPO / package).rglob("*.py"))


@pytest.mark.parametrize("package", PACKAGES)
def test_project_imports_follow_layers(package: str) -> None:
    """No package imports a project package above or beside it."""
    for path in files(package):
        bad = (imports_of(path) & set(PACKAGES)) - ALLOWED_PROJECT[package]
        assert not bad, f"{path.relative_to(REPO)} imports {sorted(bad)}"


# replay/'s rooms (replay/__init__.py): which room may import which. The engine produces and never judges;
# evaluation scores what it produced; tools work beside a run; runs (run directories, suites, diff, compare,
# revisions) sit on top. errors and metric_registry are the shared vocabulary every room reads.
ROOMS_ALLOWED = {
    "engine": {"engine"},
    "evaluation": {"engine", "evaluation"},
    "tools": {"engine", "evaluation", "tools"},
    "pipelines": {"engine", "evaluation", "tools", "pipelines"},
    "runs": {"engine", "evaluation", "tools", "runs"},
}
SHARED = {"errors", "metric_registry"}
# the flat layout's paths that plugins import, kept as aliases of the moved modules (never used inside the project)
COMPAT = {"pipeline": "engine", "reader": "engine", "trajectory": "engine", "views": "engine",
          "metrics": "evaluation", "run": "runs"}


def imported_from(path: Path, package: str, depth: int) -> set[str]:
    """What a file imports of ``slamreplay.<package>``, as the first ``depth`` names below it: for replay/ (depth 1)
    a room (``engine``), shared module (``errors``) or compat path; for api/ (depth 2) ``room.module``
    (``service.store``), a room (``cli``) or ``app``. ``from PKG import name`` counts as an import of ``PKG.name``
    while ``PKG`` is above that depth."""
    targets = set()
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        if isinstance(node, ast.Import):
            modules = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            modules = ([f"{node.module}.{a.name}" for a in node.names] if len(node.module.split(".")) < depth + 2
                       else [node.module])
        else:
            continue
        targets |= {".".join(m.split(".")[2:2 + depth]) for m in modules if m.startswith(f"slamreplay.{package}.")}
    return targets


def replay_targets(path: Path) -> set[str]:
    return imported_from(path, "replay", 1)


def assert_rooms(package: str, top: set[str], rooms: Iterable[str]) -> None:
    """``package/`` holds the modules ``top`` and the sub-packages ``rooms``, each of whose __init__ says what it
    owns."""
    assert {p.stem for p in (REPO / package).glob("*.py")} - {"__init__"} == top
    assert {p.name for p in (REPO / package).iterdir() if p.is_dir() and p.name != "__pycache__"} == set(rooms)
    for room in rooms:
        doc = ast.get_docstring(ast.parse((REPO / package / room / "__init__.py").read_text()))
        assert doc and len(doc) > 100, f"{package}/{room}/__init__.py does not say what the room owns"


def test_replay_is_four_rooms_and_the_pipelines() -> None:
    """replay/ holds only its rooms, the pipelines, the shared vocabulary and the compat paths; each room's
    __init__ says what it owns."""
    assert_rooms("replay", SHARED | set(COMPAT), ROOMS_ALLOWED)


@pytest.mark.parametrize("room", sorted(ROOMS_ALLOWED))
def test_replay_rooms_import_downwards(room: str) -> None:
    """No import runs from the engine into evaluation, tools or runs, nor from evaluation or tools into runs;
    nothing inside the project imports a compat path, and the shared modules import no room."""
    for path in files(f"replay/{room}"):
        got = replay_targets(path)
        bad = got - ROOMS_ALLOWED[room] - SHARED
        assert not bad, f"{path.relative_to(REPO)} imports replay's {sorted(bad)}"
    for name in SHARED:
        assert replay_targets(REPO / "replay" / f"{name}.py") <= SHARED


def test_nothing_in_the_project_uses_the_compat_paths() -> None:
    """The flat paths are for plugins outside; the project's own code, tests, benchmarks and docs use the rooms."""
    offenders = []
    for package in (*PACKAGES, "tests", "benchmarks", "examples", "docs"):
        for path in files(package):
            if (path.parent == REPO / "replay" and path.stem in COMPAT) or path == Path(__file__).resolve():
                continue  # the compat modules themselves, and the test below that imports them
            if used := replay_targets(path) & set(COMPAT):
                offenders.append(f"{path.relative_to(REPO)}: {sorted(used)}")
    assert not offenders, offenders


def test_compat_paths_are_the_moved_modules() -> None:
    """A plugin importing ``slamreplay.replay.pipeline`` gets the module itself, not a copy: ``MetricSpec`` and
    ``Pipeline`` are the same objects, and patching one path patches the other."""
    import importlib

    for old, room in COMPAT.items():
        assert importlib.import_module(f"slamreplay.replay.{old}") is importlib.import_module(
            f"slamreplay.replay.{room}.{old}")
    from slamreplay.replay.engine.pipeline import Pipeline
    from slamreplay.replay.metric_registry import MetricSpec
    from slamreplay.replay.pipeline import MetricSpec as OldSpec
    from slamreplay.replay.pipeline import Pipeline as OldPipeline

    assert OldSpec is MetricSpec and OldPipeline is Pipeline


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


def _module_name(path: Path) -> str:
    parts = path.relative_to(REPO).with_suffix("").parts
    return "slamreplay." + ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def test_no_import_circles() -> None:
    """No two modules import each other, directly or round a longer loop (imports inside functions and under
    TYPE_CHECKING count too: a loop hidden there is still one). ``from pkg import name`` counts as an import of
    ``pkg.name`` when that is a module, else of ``pkg``; a package's ``__init__`` re-exporting its own modules
    is not a loop."""
    paths = {_module_name(p): p for package in PACKAGES for p in files(package)}
    edges: dict[str, set[str]] = {m: set() for m in paths}
    for mod, path in paths.items():
        for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
            if isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                targets = [f"{node.module}.{a.name}" if f"{node.module}.{a.name}" in paths else node.module
                           for a in node.names]
            else:
                continue
            edges[mod] |= {t for t in targets if t in paths and t != mod and not mod.startswith(t + ".")}
    loops = []
    for start in sorted(edges):  # a loop through ``start`` is a path from one of its imports back to it
        seen, stack = set(), [(n, [start, n]) for n in sorted(edges[start])]
        while stack:
            node, trail = stack.pop()
            if node == start:
                loops.append(" -> ".join(trail))
                break
            if node not in seen:
                seen.add(node)
                stack += [(n, [*trail, n]) for n in sorted(edges[node])]
    assert not loops, loops


def test_the_two_wrap_angles_agree() -> None:
    """recorder and algorithms may not share code, so each has a wrap_angle: the same values, [-pi, pi), on
    ordinary angles, multiples of pi and the values just below -pi where a bare modulo gives +pi."""
    import numpy as np

    from slamreplay.algorithms.common.se2 import wrap_angle as algorithms_wrap
    from slamreplay.recorder.sim.unicycle import wrap_angle as recorder_wrap

    rng = np.random.default_rng(0)
    edge = -np.pi - np.array([0.0, 1e-17, 1e-16, 4e-16, 1e-15])
    theta = np.concatenate([rng.uniform(-50, 50, 10_000), np.arange(-9, 10) * np.pi, edge, -edge])
    a, r = algorithms_wrap(theta), recorder_wrap(theta)
    assert np.array_equal(a, r)
    assert np.all((r >= -np.pi) & (r < np.pi))


# api/'s rooms (api/__init__.py): the service imports neither the web page nor the command line; the web page may
# import the service; the command line imports the service only for what it starts or shares with it (below) and
# the client; ``api/app.py``, above the rooms, composes the service and the pages.
API_ROOMS_ALLOWED = {
    "service": {"service"},
    "web": {"service", "web"},
    "client": {"client"},
    "cli": {"cli", "client", "service", "app"},
}
# What the command line may use of the service: `serve` (settings, the data directory's lock, the site guard's
# host names, the server's timeouts, create_app above the rooms), `users` (people in the store), and the executors
# a local `suite run` shares with the service (and their limits).
CLI_USES_OF_SERVICE = {"settings", "datalock", "siteguard", "timeouts", "store", "people", "executor",
                       "ray_executor", "limits"}
MAX_API_MODULE_LINES = 400


def test_api_is_rooms_under_the_app() -> None:
    """api/ holds its four rooms and, above them, only ``app``; each room's __init__ says what it owns."""
    assert_rooms("api", {"app"}, API_ROOMS_ALLOWED)


@pytest.mark.parametrize("room", sorted(API_ROOMS_ALLOWED))
def test_api_rooms_import_by_the_rules(room: str) -> None:
    """The service imports neither the web page nor the command line, the web page never the command line, and the
    command line of the service only what it starts or shares (CLI_USES_OF_SERVICE)."""
    for path in files(f"api/{room}"):
        got = imported_from(path, "api", 2)
        bad = {t for t in got if t.split(".")[0] not in API_ROOMS_ALLOWED[room]}
        if room == "cli":
            bad |= {t for t in got if t.startswith("service.") and t.split(".")[1] not in CLI_USES_OF_SERVICE}
        assert not bad, f"{path.relative_to(REPO)} imports {sorted(bad)}"
    assert imported_from(REPO / "api" / "app.py", "api", 2) <= {f"service.{m}" for m in ("app", "datalock", "executor",
                                                                            "settings")} | {"web.pages", "web.web"}


def test_no_api_module_is_over_400_lines() -> None:
    """A module a reader can hold in their head: none of api/ over MAX_API_MODULE_LINES lines."""
    long = {str(p.relative_to(REPO)): n for p in files("api") if (n := len(p.read_text().splitlines()))
            > MAX_API_MODULE_LINES}
    assert not long, long
