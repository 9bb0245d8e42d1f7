"""A fingerprint of the code a process has *loaded*, to tell "same code" from "same commit".

A replay reproduces a run only with the same code. The git commit does not say it: a checkout
edited while a long process (a pytest session, a service worker) runs keeps the modules it
imported, while a fresh process imports the edited files, and ``git_commit()`` is cached anyway.
So the fingerprint hashes the loaded code objects themselves (bytecode, constants, names,
defaults) of the given modules, not the files on disk; line numbers and file paths are left out,
so moving a checkout or editing a comment only changes it when the bytecode changes.
"""

from __future__ import annotations

import hashlib
import importlib
import types
from collections.abc import Iterable
from typing import Any

SIMPLE = (int, float, complex, str, bytes, bool, type(None))


def _feed(h: Any, obj: object, depth: int = 0) -> None:
    """Hash ``obj`` without memory addresses or hash-seed-dependent orders."""
    if depth > 20:
        return
    if isinstance(obj, types.CodeType):
        h.update(obj.co_code)
        h.update(repr((obj.co_names, obj.co_varnames, obj.co_freevars, obj.co_cellvars, obj.co_argcount,
                       obj.co_kwonlyargcount, obj.co_flags)).encode())
        for c in obj.co_consts:
            _feed(h, c, depth + 1)
    elif isinstance(obj, types.FunctionType):
        _feed(h, obj.__code__, depth + 1)
        _feed(h, obj.__defaults__, depth + 1)
        _feed(h, sorted((obj.__kwdefaults__ or {}).items()), depth + 1)
    elif isinstance(obj, staticmethod | classmethod):
        _feed(h, obj.__func__, depth + 1)
    elif isinstance(obj, property):
        for f in (obj.fget, obj.fset, obj.fdel):
            _feed(h, f, depth + 1)
    elif isinstance(obj, tuple | list):
        h.update(f"{type(obj).__name__}{len(obj)}".encode())
        for x in obj:
            _feed(h, x, depth + 1)
    elif isinstance(obj, frozenset | set):  # iteration order depends on PYTHONHASHSEED
        h.update(repr(sorted(repr(x) for x in obj)).encode())
    elif isinstance(obj, SIMPLE):
        h.update(repr(obj).encode())
    else:
        r = repr(obj)
        h.update((f"<{type(obj).__module__}.{type(obj).__qualname__}>" if " at 0x" in r else r).encode())


def _feed_module(h: Any, module: types.ModuleType) -> None:
    h.update(module.__name__.encode())
    for name, value in sorted(vars(module).items()):
        if name.startswith("__"):
            continue
        if isinstance(value, type) and value.__module__ == module.__name__:
            h.update(f"class {name}".encode())
            for attr, member in sorted(vars(value).items()):
                if attr not in ("__dict__", "__weakref__", "__doc__", "__module__", "__dataclass_fields__",
                                "__dataclass_params__", "__match_args__", "__slots__"):
                    h.update(attr.encode())
                    _feed(h, member)
        elif isinstance(value, types.FunctionType) and value.__module__ == module.__name__:
            h.update(f"def {name}".encode())
            _feed(h, value)
        elif isinstance(value, (*SIMPLE, tuple, frozenset)):
            h.update(name.encode())
            _feed(h, value)


def code_fingerprint(modules: Iterable[str]) -> str:
    """sha256 (hex, 16 digits) of the code of ``modules`` (names, imported if need be) as loaded."""
    h = hashlib.sha256()
    for name in sorted(set(modules)):
        _feed_module(h, importlib.import_module(name))
    return h.hexdigest()[:16]
