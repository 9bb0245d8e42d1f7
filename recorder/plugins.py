"""Plugins found through entry points: pipelines (``slamreplay.pipelines``) and importers (``slamreplay.importers``).

slamreplay's own pipelines and importers register the same way, in its pyproject.toml, so a
user's package that declares an entry point in one of these groups is found with no change
to slamreplay. Loading is lazy and per plugin: a plugin that fails to import, or that is not
the kind of object its group expects, is reported (naming the plugin and the distribution
that provides it) only when it is used or listed; every other plugin keeps working.
"""

from __future__ import annotations

import importlib
import importlib.metadata as md
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from slamreplay.recorder.errors import RecorderError

BUILTIN_DISTRIBUTION = "slamreplay"


class PluginError(RecorderError):
    """A plugin that cannot be used: it failed to import, or it is not what its group expects."""


@dataclass(eq=False)
class Plugin:
    """One entry point of a plugin group, loaded on first use.

    ``check(obj)`` returns None when the loaded object is acceptable, else what is wrong with it.
    """

    group: str
    name: str
    value: str  # "module:attribute"
    distribution: str
    version: str
    check: Callable[[str, Any], str | None] = field(repr=False)
    _obj: Any = field(default=None, repr=False)
    _error: str | None = field(default=None, repr=False)
    _loaded: bool = field(default=False, repr=False)
    _clash: bool = field(default=False, repr=False)

    @property
    def builtin(self) -> bool:
        return self.distribution == BUILTIN_DISTRIBUTION

    @property
    def origin(self) -> str:
        """``built-in`` or the providing distribution and its version: ``my-pipeline 0.1.0``."""
        return "built-in" if self.builtin else f"{self.distribution} {self.version}"

    def describe(self) -> str:
        """How an error names the plugin: ``pipeline plugin 'x' (x = mod:Cls from distribution d 1.0)``."""
        kind = self.group.rpartition(".")[2].rstrip("s")
        if self._clash:
            return f"{kind} plugin {self.name!r}"
        return f"{kind} plugin {self.name!r} ({self.name} = {self.value} from distribution {self.distribution} " \
               f"{self.version})"

    def _load(self) -> None:
        if self._loaded:
            return
        self._loaded = True
        module, _, attr = self.value.partition(":")
        try:
            obj: Any = importlib.import_module(module)
            for part in attr.split(".") if attr else ():
                obj = getattr(obj, part)
        except Exception as err:  # noqa: BLE001 -- whatever a plugin raises on import, it is reported, never fatal
            first = str(err).splitlines()[0] if str(err) else ""
            self._error = f"failed to import: {type(err).__name__}: {first}".rstrip(": ")
            return
        self._accept(obj)

    def _accept(self, obj: Any) -> None:
        """Keep the loaded ``obj``, or the error the group's check finds in it."""
        problem = self.check(self.name, obj)
        if problem is not None:
            self._error = problem
            return
        self._obj = obj

    @property
    def error(self) -> str | None:
        """What is wrong with the plugin (None when it loads and passes its group's check)."""
        self._load()
        return self._error

    def load(self) -> Any:
        """The plugin's object; PluginError, one line naming the plugin and its distribution, when broken."""
        self._load()
        if self._error is not None:
            fix = "" if self._clash else f"; fix or uninstall `{self.distribution}`"
            raise PluginError(f"{self.describe()} {self._error}{fix}")
        return self._obj


_CACHE: dict[str, dict[str, Plugin]] = {}


def discover(group: str, check: Callable[[str, Any], str | None]) -> dict[str, Plugin]:
    """The entry points of ``group`` by name, sorted, not yet loaded (cached: see :func:`refresh`).

    A name that two distributions both provide is kept once and marked broken, naming both:
    which of the two a run used would otherwise depend on the order of sys.path.
    """
    if group in _CACHE:
        return _CACHE[group]
    found: dict[str, Plugin] = {}
    clashes: dict[str, list[str]] = {}
    for ep in md.entry_points(group=group):
        dist = ep.dist
        name, version = (dist.metadata["Name"], dist.version) if dist is not None else ("(unknown)", "?")
        plugin = Plugin(group, ep.name, ep.value, name, version, check)
        previous = found.get(ep.name)
        if previous is not None and (previous.distribution, previous.value) != (name, ep.value):
            clashes.setdefault(ep.name, [f"{previous.distribution} {previous.version}"]).append(f"{name} {version}")
            continue
        found.setdefault(ep.name, plugin)
    for name, dists in clashes.items():
        p = found[name]
        p._loaded, p._clash = True, True
        p._error = f"is provided by several distributions ({', '.join(sorted(dists))}): uninstall all but one"
    _CACHE[group] = dict(sorted(found.items()))
    return _CACHE[group]


def refresh() -> None:
    """Forget what was discovered (after installing a plugin into a running interpreter, and in tests)."""
    _CACHE.clear()


def missing_builtins_hint(group: str) -> str:
    """Why a group has no entry points at all: slamreplay runs from a source tree that is not installed."""
    return (f"no entry points in group {group!r}: slamreplay's own are declared in its pyproject.toml and are "
            f"only seen once it is installed (`pip install -e .`, or `make venv`)")
