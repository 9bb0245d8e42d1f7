"""Environments of revisions shared by what they hold, and each revision's own code laid out as if installed.

An *environment* is a virtual environment with only a revision's dependencies, never the project itself, in
``<cache>/envs/<key>/``. Its key names what it holds (``DependencySpec``): the interpreter (implementation and
``major.minor.micro``), and the revision's pyproject.toml ``[project] dependencies`` and ``requires-python``,
plus the sha256 of each lock file the revision has (``LOCK_FILES``). No extras: ``pip install -e`` installed none.
Every commit with the same key runs in the same environment; a commit that changes its dependencies gets a new
one, built once (``python -m venv`` then ``pip install -r``, or ``uv`` when ``SLAMREPLAY_REV_INSTALLER=uv``
or ``uv`` is on PATH), under a lock, stamped ``ready``, removed when it fails.

A revision's own code is added per commit beside its worktree, in ``site/`` (``write_site``): what an install
would put in site-packages, made of links. A ``slamreplay-<version>.dist-info`` written from the revision's
pyproject.toml (its version, entry points: pipelines and importers are found through them, console script,
requirements), and for a revision with the package-dir mapping (``"slamreplay.api" = "api"``) a ``slamreplay``
namespace whose folders link into the worktree; an older revision, whose packages were top-level (``api``,
``replay``), gets its worktree on the path instead. ``site/`` goes first on ``PYTHONPATH`` so that it shadows an
install of slamreplay in the interpreter (``SLAMREPLAY_REV_PYTHON``): the revision's metadata, the revision's code.
"""

from __future__ import annotations

import hashlib
import importlib.metadata
import importlib.util
import json
import os
import platform
import shutil
import subprocess
import sys
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from slamreplay.replay.errors import ReplayError

if sys.version_info >= (3, 11):
    import tomllib
else:  # Python 3.10: the same parser, as the tomli package
    import tomli as tomllib

LOCK_FILES = ("requirements.lock", "pylock.toml", "uv.lock")  # requirements.lock is applied as pip constraints
INSTALLER_ENV = "SLAMREPLAY_REV_INSTALLER"  # pip or uv (default: uv when it is on PATH, else pip)
BUILD_TIMEOUT_S = 1800
FORMAT = 1  # of the key: a change to how environments are built makes new ones


def interpreter_id() -> str:
    """``cpython-3.11.7``: the implementation and version environments are built with (this interpreter's)."""
    return f"{sys.implementation.name}-{platform.python_version()}"


@dataclass(frozen=True, slots=True)
class DependencySpec:
    """What a revision's environment holds: the interpreter, the declared dependencies, the lock files' hashes."""

    python: str
    dependencies: tuple[str, ...]
    requires_python: str | None
    locks: tuple[tuple[str, str], ...]  # (file name, sha256)

    @property
    def key(self) -> str:
        """``<python>-<16 hex digits>``: the environment's folder name."""
        doc = {"format": FORMAT, "python": self.python, "dependencies": sorted(self.dependencies),
               "requires_python": self.requires_python, "locks": sorted(self.locks)}
        digest = hashlib.sha256(json.dumps(doc, sort_keys=True).encode()).hexdigest()
        return f"{self.python}-{digest[:16]}"

    def to_json(self) -> dict[str, Any]:
        return {"python": self.python, "dependencies": list(self.dependencies),
                "requires_python": self.requires_python, "locks": dict(self.locks)}


def read_project(src: Path) -> dict[str, Any]:
    """The parsed ``src/pyproject.toml``; ReplayError when it is missing or not TOML."""
    try:
        return tomllib.loads((src / "pyproject.toml").read_text())
    except (OSError, UnicodeDecodeError) as err:
        raise ReplayError(f"cannot read its pyproject.toml: {err}") from None
    except tomllib.TOMLDecodeError as err:
        raise ReplayError(f"its pyproject.toml is not valid TOML: {err}") from None


def dependency_spec(src: Path, project: dict[str, Any]) -> DependencySpec:
    """The dependency specification of the checkout ``src`` (``project``: its parsed pyproject.toml)."""
    meta = project.get("project")
    if not isinstance(meta, dict):
        raise ReplayError("its pyproject.toml has no [project] table")
    if "dependencies" in meta.get("dynamic", []):
        raise ReplayError("its pyproject.toml declares its dependencies dynamic: an environment is shared by "
                          "declared dependencies")
    deps = meta.get("dependencies", [])
    requires = meta.get("requires-python")
    if not isinstance(deps, list) or not all(isinstance(d, str) for d in deps):
        raise ReplayError("its pyproject.toml's [project] dependencies is not a list of strings")
    locks = tuple((name, hashlib.sha256((src / name).read_bytes()).hexdigest())
                  for name in LOCK_FILES if (src / name).is_file())
    return DependencySpec(interpreter_id(), tuple(deps), str(requires) if requires else None, locks)


def check_python(spec: DependencySpec) -> None:
    """ReplayError when this interpreter is outside the revision's ``requires-python``."""
    if not spec.requires_python:
        return
    try:
        from packaging.specifiers import InvalidSpecifier, SpecifierSet
    except ImportError:  # not a dependency: pip checked it when it installed the project itself
        return
    try:
        ok = platform.python_version() in SpecifierSet(spec.requires_python)
    except InvalidSpecifier:
        return
    if not ok:
        raise ReplayError(f"it requires Python {spec.requires_python}; this is {platform.python_version()}")


# ---------------------------------------------------------------------------------------
# The revision's own code, as installed


@dataclass(frozen=True, slots=True)
class Site:
    """How to run a revision's code: what goes on ``PYTHONPATH`` and the ``python -c`` program of its CLI."""

    path: tuple[str, ...]
    program: str


def _entry_points(meta: dict[str, Any]) -> str:
    groups: dict[str, dict[str, str]] = {}
    for table, group in (("scripts", "console_scripts"), ("gui-scripts", "gui_scripts")):
        if isinstance(meta.get(table), dict):
            groups[group] = meta[table]
    for group, eps in (meta.get("entry-points") or {}).items():
        if isinstance(eps, dict):
            groups[group] = eps
    return "".join(f"[{g}]\n" + "".join(f"{k} = {v}\n" for k, v in eps.items()) + "\n" for g, eps in groups.items())


def write_site(src: Path, site: Path, project: dict[str, Any]) -> Site:
    """Lay out ``site/`` for the checkout ``src`` (see the module docstring); how to run its CLI."""
    meta = project.get("project") or {}
    name = str(meta.get("name", "slamreplay"))
    version = str(meta.get("version", "0+unknown"))
    if site.exists():
        shutil.rmtree(site)
    dist = site / f"{name.replace('-', '_')}-{version}.dist-info"
    dist.mkdir(parents=True)
    lines = ["Metadata-Version: 2.1", f"Name: {name}", f"Version: {version}"]
    if meta.get("requires-python"):
        lines.append(f"Requires-Python: {meta['requires-python']}")
    lines += [f"Requires-Dist: {d}" for d in meta.get("dependencies", []) if isinstance(d, str)]
    (dist / "METADATA").write_text("\n".join(lines) + "\n")
    (dist / "entry_points.txt").write_text(_entry_points(meta))
    (dist / "INSTALLER").write_text("slamreplay revision cache\n")
    (dist / "RECORD").write_text("")
    mapping = (project.get("tool", {}).get("setuptools", {}) or {}).get("package-dir") or {}
    path = [str(site)]
    for package, folder in sorted(mapping.items()):
        if not package:  # "" = "dir": top-level packages live in that folder
            path.append(str((src / folder).resolve()))
            continue
        link = site.joinpath(*package.split("."))
        link.parent.mkdir(parents=True, exist_ok=True)
        link.symlink_to((src / folder).resolve(), target_is_directory=True)
    if not mapping:  # top-level packages at the root of the checkout (before the slamreplay namespace)
        path.append(str(src.resolve()))
    script = (meta.get("scripts") or {}).get("slamreplay", "slamreplay.api.cli:main")
    module, _, func = str(script).partition(":")
    program = f"import sys; from {module} import {func} as main; sys.argv[0] = 'slamreplay'; sys.exit(main())"
    return Site(tuple(path), program)


# ---------------------------------------------------------------------------------------
# Environments


def installer() -> str:
    """``uv`` or ``pip``: ``$SLAMREPLAY_REV_INSTALLER``, else uv when it is on PATH (faster), else pip."""
    chosen = os.environ.get(INSTALLER_ENV, "").strip().lower()
    if chosen and chosen not in ("pip", "uv"):
        raise ReplayError(f"${INSTALLER_ENV}={chosen!r}: give pip or uv")
    if chosen == "uv" and not shutil.which("uv"):
        raise ReplayError(f"${INSTALLER_ENV}=uv but uv is not on PATH: install it (pip install uv) or unset it")
    return chosen or ("uv" if shutil.which("uv") else "pip")


def env_python(env: Path) -> Path:
    return env / "bin" / "python"


# What each build step is, for the note printed before it (a build is minutes of silence otherwise).
ENV_STEP_NOTES = {"python -m venv": "python -m venv (an environment for its dependencies, shared by every commit "
                                    "that declares the same)",
                  "pip install": "pip install (its dependencies, not itself: a minute or more, once per set of "
                                 "dependencies)"}


def _pip_with_python_option() -> bool:
    """Whether this interpreter has a pip that installs into another one (``--python``: pip 22.3)."""
    if importlib.util.find_spec("pip") is None:
        return False
    try:
        major, minor = (int(x) for x in importlib.metadata.version("pip").split(".")[:2])
    except (importlib.metadata.PackageNotFoundError, ValueError):
        return False
    return (major, minor) >= (22, 3)


def env_steps(spec: DependencySpec, env: Path, src: Path) -> list[tuple[str, list[str]]]:
    """The commands that build the environment ``env`` for ``spec`` (``src``: the checkout, for a lock file)."""
    requirements = env / "requirements.txt"
    constraints = [a for name, _ in spec.locks if name == "requirements.lock"
                   for a in ("-c", str(src / name))]
    if installer() == "uv":
        steps = [("python -m venv", ["uv", "venv", "--quiet", "--python", sys.executable, str(env)])]
        install = ["uv", "pip", "install", "--quiet", "--python", str(env_python(env))]
    elif _pip_with_python_option():  # this pip installs into it: no pip inside (5 s and 15 MB less)
        steps = [("python -m venv", [sys.executable, "-m", "venv", "--without-pip", str(env)])]
        install = [sys.executable, "-m", "pip", "--python", str(env_python(env)), "install", "--quiet",
                   "--disable-pip-version-check"]
    else:
        steps = [("python -m venv", [sys.executable, "-m", "venv", str(env)])]
        install = [str(env_python(env)), "-m", "pip", "install", "--quiet", "--disable-pip-version-check"]
    if spec.dependencies:
        steps.append(("pip install", [*install, "-r", str(requirements), *constraints]))
    return steps


def build_env(spec: DependencySpec, env: Path, src: Path, step: Callable[[str, list[str]], None]) -> None:
    """Build ``env`` for ``spec``: each command through ``step(name, argv)`` (which raises on failure);
    ``spec.json`` and ``requirements.txt`` beside it, ``ready`` last."""
    if env.exists():
        shutil.rmtree(env)
    env.parent.mkdir(parents=True, exist_ok=True)
    steps = env_steps(spec, env, src)
    for name, argv in steps:
        step(name, argv)
        if name == "python -m venv":  # the venv exists now: what it is for goes inside it
            (env / "requirements.txt").write_text("".join(f"{d}\n" for d in spec.dependencies))
            (env / "spec.json").write_text(json.dumps({"key": spec.key, **spec.to_json()}, indent=2) + "\n")
    (env / "ready").write_text(spec.key + "\n")


def run_step(name: str, argv: list[str], cwd: Path, out: Any) -> None:
    """Run one build command, its output into ``out``; ReplayError naming the step when it fails."""
    out.write(f"$ {' '.join(argv)}\n")
    out.flush()
    try:
        done = subprocess.run(argv, cwd=cwd, stdout=out, stderr=subprocess.STDOUT, timeout=BUILD_TIMEOUT_S)
        code = done.returncode
    except (OSError, subprocess.SubprocessError) as err:
        out.write(f"{err}\n")
        code = 1
    if code != 0:
        raise ReplayError(f"`{name}` failed")
