"""Whether an external program is deterministic, checked once per program and remembered (docs/external.md).

A program that gives another answer on the same input makes a single run's change meaningless, and a
comparison that does not know it calls seed noise a regression. So the first run of each program (its
identity: version string, command, build command and the sha256 of its executable, declaration and files,
``PROGRAM_FIELDS``) runs it twice on the same input and compares the outputs; the verdict is kept in
``<cache>/determinism/<identity>.json`` and every later run of the same program records it in its manifest
(``pipeline_run.determinism``, ``checked: "cached"``) without running twice. ``compare`` and ``history`` then
judge a program that is not deterministic by its seeds' spread. Editing the program (any hash) checks again.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from slamreplay.recorder.files import atomic_write
from slamreplay.replay.tools.cache import cache_dir

# what makes a program that program (paths left out: the same program elsewhere is the same program)
PROGRAM_FIELDS = ("version", "command", "build", "executable_sha256", "declaration_sha256", "files_sha256")


def identity(origin: Mapping[str, Any]) -> str:
    """The sha256 of a program's ``PROGRAM_FIELDS`` (its ``pipeline_origin``)."""
    doc = {k: origin.get(k) for k in PROGRAM_FIELDS}
    return hashlib.sha256(json.dumps(doc, sort_keys=True).encode()).hexdigest()


def _path(origin: Mapping[str, Any]) -> Path:
    return cache_dir() / "determinism" / f"{identity(origin)}.json"


def known(origin: Mapping[str, Any]) -> dict[str, Any] | None:
    """The remembered verdict of this program (``deterministic``, ``max_difference_m``), or None."""
    try:
        doc = json.loads(_path(origin).read_text())
    except (OSError, ValueError):
        return None
    if not isinstance(doc, dict) or not isinstance(doc.get("deterministic"), bool):
        return None
    return {"deterministic": doc["deterministic"], "max_difference_m": doc.get("max_difference_m")}


def remember(origin: Mapping[str, Any], deterministic: bool, max_difference_m: float | None) -> None:
    """Keep the verdict of this program (atomically; a cache that cannot be written only means checking again)."""
    path = _path(origin)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        atomic_write(path, json.dumps({"deterministic": deterministic, "max_difference_m": max_difference_m,
                                       "program": {k: origin.get(k) for k in PROGRAM_FIELDS}}, indent=1) + "\n")
    except OSError:
        pass
