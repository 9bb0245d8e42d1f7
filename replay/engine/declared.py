"""Pipelines declared in TOML files (docs/external.md), beside those of entry points.

A declaration file holds a table ``[pipelines.NAME]`` per pipeline. Each is made into a ``Pipeline`` class by
an adapter named like an entry point (``adapter = "module:function"``, by default the external-program
adapter ``slamreplay.replay.pipelines.external``), loaded on first use as plugins are: the engine imports
no pipeline here either. Files are found through ``$SLAMREPLAY_PIPELINES`` and ``[tool.slamreplay]`` of
``./pyproject.toml`` (:func:`declaration_files`); a suite file adds its own (:func:`use_declarations`).
"""

from __future__ import annotations

import importlib
import os
import sys
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

if sys.version_info >= (3, 11):
    import tomllib
else:  # Python 3.10: the same parser, as the tomli package
    import tomli as tomllib

from slamreplay.recorder.plugins import Plugin
from slamreplay.replay.errors import ReplayError

Check = Callable[[str, Any], "str | None"]


DECLARATIONS_ENV = "SLAMREPLAY_PIPELINES"
DEFAULT_ADAPTER = "slamreplay.replay.pipelines.external:pipeline_from_declaration"
DECLARED = "declared"  # Plugin.distribution of a declared pipeline


class DeclaredPlugin(Plugin):
    """A pipeline declared by table ``[pipelines.NAME]`` of a TOML file, built on first use by its adapter."""

    def __init__(self, group: str, name: str, table: Mapping[str, Any], path: Path, check: Check,
                 error: str | None = None) -> None:
        adapter = table.get("adapter", DEFAULT_ADAPTER) if isinstance(table, Mapping) else DEFAULT_ADAPTER
        super().__init__(group, name, str(adapter), DECLARED, "", check)
        self.table, self.path = table, path
        if error is not None:
            self.refuse(error)

    def refuse(self, error: str) -> None:
        """Mark the declaration broken with ``error``."""
        self._loaded, self._error, self._obj = True, error, None

    @property
    def builtin(self) -> bool:
        return False

    @property
    def origin(self) -> str:
        return f"declared in {self.path}"

    def describe(self) -> str:
        return f"pipeline {self.name!r} (declared in {self.path})"

    def _load(self) -> None:
        if self._loaded:
            return
        self._loaded = True
        module, _, attr = self.value.partition(":")
        try:
            factory = getattr(importlib.import_module(module), attr)
            obj = factory(self.name, self.table, self.path)
        except (ReplayError, ValueError, TypeError) as err:
            self._error = str(err)
            return
        except Exception as err:  # noqa: BLE001 -- an adapter's failure is this declaration's, never fatal
            self._error = f"adapter {self.value} failed: {type(err).__name__}: {err}"
            return
        self._accept(obj)

    def load(self) -> Any:
        self._load()
        if self._error is not None:
            raise ReplayError(f"{self.describe()} {self._error}")
        return self._obj


def declaration_files() -> list[Path]:
    """The TOML files declaring pipelines: each entry of ``$SLAMREPLAY_PIPELINES`` (``os.pathsep``-separated files,
    or folders whose ``*.toml`` are read), then ``[tool.slamreplay] pipelines = [...]`` of ``./pyproject.toml``
    (paths relative to it)."""
    paths: list[Path] = []
    for entry in filter(None, os.environ.get(DECLARATIONS_ENV, "").split(os.pathsep)):
        p = Path(entry)
        paths += sorted(p.glob("*.toml")) if p.is_dir() else [p]
    project = Path("pyproject.toml")
    if project.is_file():
        try:
            listed = tomllib.loads(project.read_text()).get("tool", {}).get("slamreplay", {}).get("pipelines", [])
        except (OSError, ValueError):
            listed = []
        paths += [project.parent / str(p) for p in listed] if isinstance(listed, list) else []
    return list(dict.fromkeys(p.resolve() for p in paths))


def use_declarations(paths: Sequence[Path]) -> None:
    """Add declaration files for this process and the processes it starts (suite workers, ``--rev`` runs)."""
    have = [e for e in os.environ.get(DECLARATIONS_ENV, "").split(os.pathsep) if e]
    new = [str(Path(p).resolve()) for p in paths if str(Path(p).resolve()) not in have]
    if new:
        os.environ[DECLARATIONS_ENV] = os.pathsep.join([*have, *new])


_DECLARED_CACHE: dict[tuple[tuple[str, int], ...], dict[str, Plugin]] = {}


def declared_pipelines(group: str, check: Check) -> dict[str, Plugin]:
    """The pipelines of :func:`declaration_files`, by name, not yet built (cached while the files are unchanged).
    A file that is missing or not TOML, or two files declaring one name, is a broken pipeline naming the file."""
    files = declaration_files()
    key = tuple((str(p), p.stat().st_mtime_ns if p.is_file() else -1) for p in files)
    if key in _DECLARED_CACHE:
        return _DECLARED_CACHE[key]
    out: dict[str, Plugin] = {}
    for path in files:
        try:
            doc = tomllib.loads(path.read_text())
        except OSError as err:
            out[path.name] = DeclaredPlugin(group, path.name, {}, path, check, f"cannot be read: {err.strerror}")
            continue
        except ValueError as err:
            out[path.name] = DeclaredPlugin(group, path.name, {}, path, check, f"is not valid TOML: {err}")
            continue
        tables = doc.get("pipelines")
        if not isinstance(tables, dict) or not tables:
            out[path.name] = DeclaredPlugin(group, path.name, {}, path, check, "declares no [pipelines.NAME] table")
            continue
        for name, table in tables.items():
            if name in out:
                other = getattr(out[name], "path", "?")
                out[name] = DeclaredPlugin(group, name, {}, path, check, f"is declared twice (also in {other})")
                continue
            error = None if isinstance(table, dict) else "is not a table"
            out[name] = DeclaredPlugin(group, name, table if isinstance(table, dict) else {}, path, check, error)
    _DECLARED_CACHE.clear()
    _DECLARED_CACHE[key] = dict(sorted(out.items()))
    return _DECLARED_CACHE[key]
