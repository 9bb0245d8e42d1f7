"""slamreplay's version, and the git commit of the code when it runs from a checkout."""

from __future__ import annotations

import subprocess
from functools import cache
from importlib import metadata
from pathlib import Path

SOURCE_ROOT = Path(__file__).resolve().parents[1]


@cache
def version() -> str:
    """The installed distribution version of slamreplay, or ``0+unknown``."""
    try:
        return metadata.version("slamreplay")
    except metadata.PackageNotFoundError:
        return "0+unknown"


@cache
def git_commit() -> str:
    """``<sha>`` of the checkout the code runs from, ``<sha>-dirty`` with local changes, or ``unknown``."""
    try:
        sha = subprocess.run(["git", "rev-parse", "HEAD"], cwd=SOURCE_ROOT, capture_output=True,
                             text=True, timeout=5, check=True).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=SOURCE_ROOT,
                               capture_output=True, text=True, timeout=5, check=True).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return "unknown"
    return f"{sha}-dirty" if dirty else sha
