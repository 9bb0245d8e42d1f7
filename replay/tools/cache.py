"""Where slamreplay keeps what it computed once and reuses: ``$SLAMREPLAY_CACHE``, else ``~/.cache/slamreplay``
(revisions' worktrees and environments, results, simulated recordings, external programs' determinism verdicts),
and how large its revisions and environments may grow: ``$SLAMREPLAY_CACHE_LIMIT_GB``, else 10."""

from __future__ import annotations

import math
import os
import re
from pathlib import Path

from slamreplay.replay.errors import ReplayError

LIMIT_ENV = "SLAMREPLAY_CACHE_LIMIT_GB"
DEFAULT_LIMIT_GB = 10.0
_UNITS = {"": 1 << 30, "b": 1, "k": 1 << 10, "m": 1 << 20, "g": 1 << 30, "t": 1 << 40}  # a bare number is GB
_SIZE = re.compile(r"\s*(\d+(?:\.\d*)?|\.\d+)\s*(?:([kmgt])(?:i?b)?|(b))?\s*", re.IGNORECASE)


def cache_dir() -> Path:
    """``$SLAMREPLAY_CACHE``, else ``~/.cache/slamreplay``."""
    env = os.environ.get("SLAMREPLAY_CACHE")
    return Path(env).expanduser() if env else Path.home() / ".cache" / "slamreplay"


def parse_size(text: str, what: str = "size") -> int:
    """Bytes of ``text``: a number with an optional unit, B, K, M, G or T (powers of 1024; KB, KiB ... too), a bare
    number in GB; ReplayError naming ``what`` for anything else."""
    m = _SIZE.fullmatch(text)
    value = float(m.group(1)) * _UNITS[(m.group(2) or m.group(3) or "").lower()] if m else math.nan
    if not math.isfinite(value):
        raise ReplayError(f"{what} {text!r}: give a size such as 10G, 500M or 2.5 (GB)")
    return int(value)


def cache_limit() -> int:
    """Bytes the revision cache may hold (``$SLAMREPLAY_CACHE_LIMIT_GB``, default 10); ReplayError if malformed."""
    text = os.environ.get(LIMIT_ENV, "").strip()
    return parse_size(text, f"${LIMIT_ENV}") if text else int(DEFAULT_LIMIT_GB * (1 << 30))
