"""Makes ``tests.fuzz.*`` importable however pytest is started: ``python -m pytest`` (make test) puts the checkout
on ``sys.path``, the ``pytest`` script does not, and the fuzz tests import their harnesses and mutators by that name."""

from __future__ import annotations

import sys
from pathlib import Path

_ROOT = str(Path(__file__).resolve().parents[2])
if _ROOT not in sys.path:
    sys.path.insert(0, _ROOT)
