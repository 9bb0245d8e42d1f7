"""Is this path a recording at all? Checked before anything is written, with no heavy import.

``slamreplay run`` refuses an input that does not exist, is empty, is not an MCAP file (or a ROS 2
bag folder holding one) or has no MCAP footer before it creates the run directory, and the command
line checks it before it imports the replay stack, so that a typo costs neither a second nor a
failed run directory. ``slamreplay.replay.engine.reader`` opens the file with the same two checks.
"""

from __future__ import annotations

from pathlib import Path

from slamreplay.replay.errors import ReplayError

MCAP_MAGIC = b"\x89MCAP0\r\n"


def resolve_mcap_path(path: Path) -> Path:
    """The MCAP file of ``path``: the file itself, or the one .mcap in a ROS 2 bag directory."""
    if not path.exists():
        raise ReplayError(f"{path}: no such file or directory")
    if path.is_dir():
        mcaps = sorted(path.glob("*.mcap"))
        if len(mcaps) == 1:
            return _regular(mcaps[0])
        if not mcaps and list(path.glob("*.db3")):
            raise ReplayError(f"{path} is a ROS 2 bag in sqlite3 storage; import it first: "
                              f"`slamreplay record ros2 {path} --out FILE.mcap`, then run FILE.mcap")
        what = "no .mcap file" if not mcaps else f"{len(mcaps)} .mcap files (split bag)"
        raise ReplayError(f"{path} is a directory with {what}; give one .mcap file, or import the bag with "
                          f"`slamreplay record ros2 {path} --out FILE.mcap`")
    return _regular(path)


def _regular(path: Path) -> Path:
    """``path`` when it is a regular file (a link to one included); a folder named ``x.mcap``, a FIFO or a device
    is refused here, before anything opens it (a FIFO would block the reader)."""
    if not path.is_file():
        kind = "a directory" if path.is_dir() else "not a regular file (a pipe, socket or device)"
        raise ReplayError(f"{path} is {kind}: give an .mcap recording file")
    return path


def check_framing(path: Path) -> None:
    """Raise ReplayError when ``path`` is empty, not an MCAP file, or truncated."""
    size = path.stat().st_size
    if size == 0:
        raise ReplayError(f"{path} is empty (0 bytes): nothing was recorded")
    with open(path, "rb") as f:
        head = f.read(8)
        if head != MCAP_MAGIC:
            raise ReplayError(f"{path} is not an MCAP file (it starts with {head[:8]!r}); slamreplay reads "
                              f"MCAP recordings and ROS 2 bags in MCAP storage")
        f.seek(max(0, size - 8))
        if size < 16 or f.read(8) != MCAP_MAGIC:
            raise ReplayError(f"{path} is truncated: it has no MCAP footer, so it was not closed cleanly. "
                              f"Salvage its messages with `slamreplay recover {path} --out FIXED.mcap`")


def check_recording(path: str | Path) -> Path:
    """The MCAP file of ``path`` (:func:`resolve_mcap_path`) after :func:`check_framing`; ReplayError, one line
    saying what is wrong and what to do, when it is not a whole recording."""
    mcap = resolve_mcap_path(Path(path))
    check_framing(mcap)
    return mcap
