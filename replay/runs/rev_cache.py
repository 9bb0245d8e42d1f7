"""The revision cache's size: what it holds, which entries are in use, pruning least recently used first.

Entries are revisions (``<cache>/revs/<sha>/``: a worktree and its ``site/``, or an older per-commit virtual
environment) and environments (``<cache>/envs/<key>/``, ``slamreplay.replay.runs.rev_envs``). Beside each,
two lock files that are never removed (a removed lock file would let two processes lock two files):
``.<name>.lock``, held exclusively while it is built, and ``.<name>.use``, held shared by every process that
runs cells with it (``Hold``: a ``Revision`` keeps one on its revision and its environment for as long as it
exists). Pruning takes both without waiting and skips an entry it cannot lock: one in use or being built is
never removed. Each use touches ``<entry>/used``, whose time is the entry's last use.

The limit is ``$SLAMREPLAY_CACHE_LIMIT_GB`` (``replay.tools.cache``, default 10); ``prepare_revision`` prunes to it
after each revision it prepares, and ``slamreplay cache prune`` on demand.
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import os
import shutil
import subprocess
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any


def build_lock(entry: Path) -> Path:
    """``.<name>.lock`` beside ``entry``: held while it is built."""
    return entry.parent / f".{entry.name}.lock"


def use_lock(entry: Path) -> Path:
    """``.<name>.use`` beside ``entry``: held shared while it is in use."""
    return entry.parent / f".{entry.name}.use"


def touch_used(entry: Path) -> None:
    """Stamp ``entry``'s last use (the time of ``<entry>/used``)."""
    with contextlib.suppress(OSError):  # removed meanwhile: nothing to stamp
        (entry / "used").write_text(f"{time.time():.0f}\n")


class Hold:
    """Shared use-locks on cache entries (``take``, which waits for a prune holding one to finish), released, and
    the entries' last use stamped, by ``release`` or when the hold is garbage collected."""

    def __init__(self) -> None:
        self._held: list[tuple[Path, IO[str]]] = []

    def take(self, entry: Path) -> None:
        """Hold ``entry`` in use, and stamp its use."""
        lock = use_lock(entry)
        lock.parent.mkdir(parents=True, exist_ok=True)
        f = open(lock, "a")  # noqa: SIM115 -- held until released
        fcntl.flock(f, fcntl.LOCK_SH)
        self._held.append((entry, f))
        touch_used(entry)

    @property
    def entries(self) -> list[Path]:
        return [entry for entry, _ in self._held]

    def release(self) -> None:
        """Stamp the last use and let go of the locks (once)."""
        held, self._held = self._held, []
        for entry, f in held:
            touch_used(entry)
            f.close()

    def __del__(self) -> None:
        with contextlib.suppress(Exception):  # at interpreter exit the modules may be gone: the OS unlocks anyway
            self.release()


def _try_lock(path: Path) -> IO[str] | None:
    """``path`` locked exclusively without waiting, or None when someone holds it."""
    path.parent.mkdir(parents=True, exist_ok=True)
    f = open(path, "a")  # noqa: SIM115 -- returned locked
    try:
        fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        f.close()
        return None
    return f


def disk_usage(path: Path) -> int:
    """Bytes on disk under ``path`` (links not followed, a hard-linked file counted once)."""
    seen: set[tuple[int, int]] = set()
    total = 0
    for root, dirs, files in os.walk(path):
        for name in (*dirs, *files):
            try:
                st = os.lstat(os.path.join(root, name))
            except OSError:
                continue
            if (st.st_dev, st.st_ino) not in seen:
                seen.add((st.st_dev, st.st_ino))
                total += st.st_blocks * 512
    return total


@dataclass
class Entry:
    """One revision or environment of the cache."""

    kind: str  # "revision" or "environment"
    name: str  # commit sha or environment key
    path: Path
    size: int
    last_use: float  # seconds since the epoch
    state: str  # "in use", "building" or "" (free)
    about: str  # a revision's subject line; an environment's dependency count and revisions
    info: dict[str, Any]

    @property
    def in_use(self) -> bool:
        return bool(self.state)


def _last_use(entry: Path) -> float:
    for stamp in ("used", "ready"):
        try:
            return (entry / stamp).stat().st_mtime
        except OSError:
            continue
    try:
        return entry.stat().st_mtime
    except OSError:
        return 0.0


def _state(entry: Path) -> str:
    for lock, busy in ((build_lock(entry), "building"), (use_lock(entry), "in use")):
        if not lock.exists():
            continue
        f = _try_lock(lock)
        if f is None:
            return busy
        f.close()
    return ""


def _json(path: Path) -> dict[str, Any]:
    try:
        doc = json.loads(path.read_text())
    except (OSError, ValueError):
        return {}
    return doc if isinstance(doc, dict) else {}


def entries(cache: Path, sizes: bool = True) -> list[Entry]:
    """The cache's revisions and environments, least recently used first (sizes 0 unless ``sizes``)."""
    found: list[Entry] = []
    users: dict[str, int] = {}
    for kind, folder, meta in (("revision", "revs", "revision.json"), ("environment", "envs", "spec.json")):
        try:
            children = sorted(p for p in (cache / folder).iterdir() if p.is_dir() and not p.name.startswith("."))
        except OSError:
            continue
        for p in children:
            info = _json(p / meta)
            if kind == "revision":
                if info.get("env"):
                    users[str(info["env"])] = users.get(str(info["env"]), 0) + 1
                about = str(info.get("subject") or ("(an older per-commit environment)" if (p / "venv").is_dir()
                                                    else ""))
            else:
                about = f"{len(info.get('dependencies', []))} dependencies"
            found.append(Entry(kind, p.name, p, disk_usage(p) if sizes else 0, _last_use(p), _state(p), about, info))
    for e in found:
        if e.kind == "environment":
            e.about += f", {users.get(e.name, 0)} revision(s)"
    return sorted(found, key=lambda e: (e.last_use, e.kind, e.name))


def _remove_worktree(entry: Path, repo: str | None) -> None:
    src = entry / "src"
    if repo and Path(repo).is_dir():
        if src.exists():
            subprocess.run(["git", "worktree", "remove", "--force", str(src)], cwd=repo, capture_output=True,
                           timeout=120)
        shutil.rmtree(entry, ignore_errors=True)
        subprocess.run(["git", "worktree", "prune"], cwd=repo, capture_output=True, timeout=120)
    else:
        shutil.rmtree(entry, ignore_errors=True)


def remove(entry: Entry) -> bool:
    """Remove ``entry`` if it is neither in use nor being built (locks taken without waiting); whether it was."""
    build = _try_lock(build_lock(entry.path))
    if build is None:
        return False
    try:
        use = _try_lock(use_lock(entry.path))
        if use is None:
            return False
        try:
            if entry.kind == "revision":
                _remove_worktree(entry.path, entry.info.get("repo") or _legacy_repo(entry.path))
            else:
                shutil.rmtree(entry.path, ignore_errors=True)
        finally:
            use.close()
    finally:
        build.close()
    return not entry.path.exists()


def _legacy_repo(entry: Path) -> str | None:
    """The repository a worktree was made from, read from its ``.git`` file (``gitdir: <repo>/.git/worktrees/x``)."""
    try:
        line = (entry / "src" / ".git").read_text().strip()
    except OSError:
        return None
    gitdir = Path(line.removeprefix("gitdir:").strip())
    return str(gitdir.parents[2]) if len(gitdir.parents) > 2 and gitdir.parent.name == "worktrees" else None


@dataclass(frozen=True, slots=True)
class Pruned:
    """What a prune did: the entries removed, those it had to keep (in use), the size before and after."""

    removed: list[Entry]
    kept_in_use: list[Entry]
    before: int
    after: int


def prune(cache: Path, limit: int, note: Callable[[str], None] | None = None) -> Pruned:
    """Remove least recently used entries until the cache holds at most ``limit`` bytes; never one in use."""
    note = note or (lambda text: None)
    found = entries(cache)
    total = before = sum(e.size for e in found)
    removed: list[Entry] = []
    kept: list[Entry] = []
    for e in found:
        if total <= limit:
            break
        if e.in_use or not remove(e):
            kept.append(e)
            continue
        removed.append(e)
        total -= e.size
        note(f"removed {e.kind} {e.name[:16]} ({format_size(e.size)}, last used {format_time(e.last_use)})")
    return Pruned(removed, kept, before, total)


def total_size(cache: Path) -> int:
    """Bytes of every revision and environment in ``cache``."""
    return sum(disk_usage(cache / folder) for folder in ("revs", "envs") if (cache / folder).is_dir())


def record_size(entry: Path) -> None:
    """Write ``entry``'s size when built into ``<entry>/size``, for ``estimated_size``."""
    (entry / "size").write_text(f"{disk_usage(entry)}\n")


def estimated_size(cache: Path) -> int:
    """Bytes of the cache's entries as recorded when each was built (measured for one that has no record):
    milliseconds where measuring all takes a second; what running adds since (``__pycache__``) is not in it."""
    total = 0
    for folder in ("revs", "envs"):
        try:
            children = [p for p in (cache / folder).iterdir() if p.is_dir() and not p.name.startswith(".")]
        except OSError:
            continue
        for p in children:
            try:
                total += int((p / "size").read_text())
            except (OSError, ValueError):
                total += disk_usage(p)
    return total


def format_size(n: float) -> str:
    for unit in ("B", "KiB", "MiB", "GiB"):
        if abs(n) < 1024 or unit == "GiB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1024
    raise AssertionError("unreachable")


def format_time(t: float) -> str:
    return time.strftime("%Y-%m-%d %H:%M", time.localtime(t)) if t else "-"
