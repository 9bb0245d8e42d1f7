"""Importers that turn public datasets into slamreplay recordings.

The names below are loaded on first use (PEP 562), so that ``pole_config`` imports without
numpy: the command line builds ``record ros2 --help`` from it.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from slamreplay.recorder.importers.mrclam import ImportSummary, import_mrclam

__all__ = ["ImportSummary", "import_mrclam"]


def __getattr__(name: str) -> Any:
    """Load an exported name from ``mrclam`` on first use."""
    if name not in __all__:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(importlib.import_module(f"{__name__}.mrclam"), name)
    globals()[name] = value
    return value
