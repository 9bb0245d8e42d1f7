"""Commands the CLI prints for the user to type next, spelled so that they work as printed.

slamreplay and rerun are installed beside the Python running this code (``.venv/bin/``). When
that folder is on PATH (an activated environment, or an install onto PATH) a hint says bare
``rerun``; otherwise it names the executable by its path (``.venv/bin/rerun``), which works
from the current directory without activating anything. On a machine without a display the
native viewer cannot open, so the viewing hint gives the headless ways too.
"""

from __future__ import annotations

import os
import re
import shutil
import sys
from importlib import metadata
from pathlib import Path


def rerun_sdk_version() -> str:
    """``major.minor`` of the installed rerun-sdk: a viewer of that version opens the .rrd files it writes."""
    try:
        return ".".join(metadata.version("rerun-sdk").split(".")[:2])
    except metadata.PackageNotFoundError:
        return "0.41"


def tool(name: str) -> str:
    """How to type ``name`` (``rerun``, ``slamreplay``) from the current directory so that it runs."""
    beside = Path(sys.executable).parent / name
    if not beside.exists():
        return name  # installed elsewhere (pipx, a system package): it is on PATH or nowhere we know
    found = shutil.which(name)
    if found is not None and os.path.samefile(found, beside):
        return name
    try:
        rel = os.path.relpath(beside, Path.cwd())
    except ValueError:  # another drive on Windows
        return str(beside)
    return rel if not rel.startswith("..") else str(beside)


_COMMAND = re.compile(r"(?<![\w/.-])(slamreplay|rerun|pip)(?= (record|run|recover|pipelines|navigate|inspect|diff|"
                      r"serve|demo|graph|rrd|install)\b)")


def spell_commands(text: str) -> str:
    """``text`` (an error message from any layer) with the commands it suggests spelled to run as printed here."""
    return _COMMAND.sub(lambda m: tool(m.group(1)), text)


def has_display() -> bool:
    """Whether a native viewer window can open here (Linux needs X11 or Wayland; macOS and Windows have one)."""
    if not sys.platform.startswith("linux"):
        return True
    return any(os.environ.get(v) for v in ("DISPLAY", "WAYLAND_DISPLAY", "WAYLAND_SOCKET"))


def view_hint(rrd: str | Path) -> list[str]:
    """Lines telling how to open ``rrd``: the native viewer, and with no display the headless ways."""
    rerun, sdk = tool("rerun"), rerun_sdk_version()
    lines = [f"open it with: {rerun} {rrd}"]
    if not has_display():
        lines = [
            f"no display here (DISPLAY/WAYLAND_DISPLAY unset), so the native viewer cannot open {rrd}; instead:",
            f"  {rerun} --web-viewer --bind 127.0.0.1 {rrd}   # then browse http://127.0.0.1:9090 (this machine only: "
            f"without --bind it listens on every address; over ssh: ssh -L 9090:localhost:9090 -L 9876:localhost:9876 "
            f"HOST)",
            f"  or copy {rrd} to a machine with a display and rerun-sdk {sdk} (pip install 'rerun-sdk~={sdk}.0'; "
            f"rerun FILE)",
            f"  or render its tabs to PNG files: {tool('slamreplay')} snapshot {rrd} --out PICTURES_DIR",
        ]
    return lines
