"""Where slamreplay keeps what it computed once and reuses: ``$SLAMREPLAY_CACHE``, else ``~/.cache/slamreplay``
(revisions' worktrees and results, simulated recordings, external programs' determinism verdicts)."""

from __future__ import annotations

import os
from pathlib import Path


def cache_dir() -> Path:
    """``$SLAMREPLAY_CACHE``, else ``~/.cache/slamreplay``."""
    env = os.environ.get("SLAMREPLAY_CACHE")
    return Path(env).expanduser() if env else Path.home() / ".cache" / "slamreplay"
