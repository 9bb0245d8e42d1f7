"""Files that appear complete or not at all: write under a temporary name beside the target, rename when done.

Every writer of a finished file (run files, graphs, snapshots, staged copies, recovered recordings) goes
through :func:`replacing`. The temporary name starts with ``.`` and ends with ``.partial``, so listings
and start-up sweeps know it for what it is; an error (a full disk, a kill signal turned exception) removes
it, and the target is never touched until the content is whole. A ``Recorder`` keeps its own
``FILE.partial`` instead: a recording cut off mid-way is kept to be recovered, not removed.
"""

from __future__ import annotations

import os
import uuid
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path


def temporary_name(path: Path) -> Path:
    """A unique hidden ``.partial`` name beside ``path`` (two writers of one target never share it)."""
    return path.with_name(f".{path.name}.{uuid.uuid4().hex[:8]}.partial")


@contextmanager
def replacing(path: str | os.PathLike[str], *, sync: bool = True) -> Iterator[Path]:
    """Yield a temporary path beside ``path`` to write; on a clean exit rename it onto ``path`` (fsync'd first
    when ``sync``), on any error remove it and leave ``path`` as it was."""
    target = Path(path)
    tmp = temporary_name(target)
    try:
        yield tmp
        if sync and tmp.is_file():
            with open(tmp, "rb+") as f:
                os.fsync(f.fileno())
        os.replace(tmp, target)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def atomic_write(path: str | os.PathLike[str], data: str | bytes) -> None:
    """Write ``data`` to ``path`` so that it appears complete or not at all."""
    with replacing(path) as tmp:
        tmp.write_bytes(data.encode() if isinstance(data, str) else data)
