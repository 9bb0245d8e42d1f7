"""Simulators that produce slamreplay recordings.

The names below are loaded on first use (PEP 562), so that a simulator's config module
(``landmarks_config``, ``seabed_config``, ``corridor_config``) imports without numpy: the
command line builds ``record SIM --help`` from them.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from slamreplay.recorder.sim.landmarks import LandmarkSimConfig, SimSummary, simulate_landmarks

__all__ = ["LandmarkSimConfig", "SimSummary", "simulate_landmarks"]


def __getattr__(name: str) -> Any:
    """Load an exported name from ``landmarks`` on first use."""
    if name not in __all__:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(importlib.import_module(f"{__name__}.landmarks"), name)
    globals()[name] = value
    return value
