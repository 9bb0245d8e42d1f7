"""One server per data directory: an exclusive ``flock`` on ``DATA_DIR/slamreplay.lock``.

The lock is a kernel lock on an open file, not the file's existence: it goes away with the
last process holding it, however that process ends (``kill -9`` included), so a lock left by
a killed server is never stale in a way that needs a person to delete a file. The file's
content (pid, host, address, start time) only names the holder for the one-line refusal a
second server prints; each new owner rewrites it.

Local worker processes get a copy of the locked file descriptor (``LocalExecutor.share_fd``):
the lock is held until the server *and* every worker it started are gone, so a new server
cannot re-queue a job that a killed server's orphan worker is still writing.
"""

from __future__ import annotations

import fcntl
import json
import os
import socket
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path

LOCK_NAME = "slamreplay.lock"
# How long a new server waits for the workers of a killed one to let go of the lock: they poll for
# their parent every 0.5 s (executor._watch_parent), so 5 s covers a loaded host.
TAKEOVER_WAIT_S = 5.0
POLL_S = 0.1


class DataDirInUseError(RuntimeError):
    """Another server holds the data directory; the message names it on one line."""


@dataclass(frozen=True, slots=True)
class Owner:
    """Who holds a data directory, as written in its lock file.

    Attributes
    ----------
    pid : process id of the server
    host : host name of the machine it runs on
    address : base URL it serves (``http://127.0.0.1:8000``); None for an app started by other means
    started : UTC start time, ISO 8601
    """

    pid: int
    host: str
    address: str | None
    started: str

    @classmethod
    def this_process(cls, address: str | None = None) -> Owner:
        return cls(os.getpid(), socket.gethostname(), address,
                   time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()))

    @classmethod
    def parse(cls, text: str) -> Owner | None:
        """The owner written in ``text``; None when it is empty or not ours (a holder that has not written yet)."""
        try:
            d = json.loads(text)
            return cls(int(d["pid"]), str(d["host"]), d.get("address"), str(d["started"]))
        except (ValueError, KeyError, TypeError):
            return None

    def is_gone(self) -> bool:
        """Whether this owner is a process of this machine that no longer exists."""
        if self.host != socket.gethostname():
            return False  # cannot tell from here (a data directory on a shared file system)
        try:
            os.kill(self.pid, 0)
        except ProcessLookupError:
            return True
        except PermissionError:
            return False
        return False


class DataDirLock:
    """The exclusive lock of one data directory, held through an open file descriptor.

    Parameters
    ----------
    data_dir : the directory (it must exist); the lock file ``slamreplay.lock`` is made in it
    """

    def __init__(self, data_dir: Path) -> None:
        self.data_dir = data_dir
        self.path = data_dir / LOCK_NAME
        self._fd: int | None = None
        self._owner: Owner | None = None

    @property
    def held(self) -> bool:
        return self._fd is not None

    @property
    def fd(self) -> int:
        """The locked file descriptor (for worker processes to share); RuntimeError when not held."""
        if self._fd is None:
            raise RuntimeError(f"{self.path} is not held by this process")
        return self._fd

    def acquire(self, address: str | None = None, wait_s: float = TAKEOVER_WAIT_S) -> Owner:
        """Take the lock and write this process in it; a no-op returning the owner when already held.

        Waits up to ``wait_s`` only while the holder is a server of this machine that is gone (its
        workers are exiting) or has not written its name yet; a live holder is refused at once.

        Raises
        ------
        DataDirInUseError
            Another process holds the lock; the message names it (pid, address, start time).
        OSError
            The lock file cannot be opened (a read-only data directory).
        """
        if self._fd is not None and self._owner is not None:
            return self._owner
        fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)  # not inheritable (PEP 446): see share_fd
        deadline = time.monotonic() + wait_s
        try:
            while True:
                try:
                    fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                    break
                except BlockingIOError:
                    holder = Owner.parse(os.pread(fd, 4096, 0).decode("utf-8", "replace"))
                    transient = holder is None or holder.is_gone()
                    if not transient or time.monotonic() >= deadline:
                        raise DataDirInUseError(self._busy_message(holder, wait_s)) from None
                    time.sleep(POLL_S)
            owner = Owner.this_process(address)
            _write(fd, owner)
        except BaseException:
            os.close(fd)  # closing our descriptor drops our lock too, if we took it
            raise
        self._fd, self._owner = fd, owner
        return owner

    def set_address(self, address: str) -> Owner:
        """Name the address this process serves in the lock file (known once its port is bound)."""
        owner = replace(self._owner or Owner.this_process(), address=address)
        _write(self.fd, owner)
        self._owner = owner
        return owner

    def release(self) -> None:
        """Close this process's descriptor. No explicit unlock: worker processes sharing it keep the
        lock until they end, so a worker that outlives a stop still blocks the next server."""
        if self._fd is not None:
            os.close(self._fd)
            self._fd, self._owner = None, None

    def _busy_message(self, holder: Owner | None, wait_s: float) -> str:
        where = f"the data directory {self.data_dir.resolve()}"
        if holder is None:
            return (f"{where} is in use by another slamreplay server (its lock file {self.path} names none yet); "
                    "stop it or pass another --data-dir")
        if holder.is_gone():
            return (f"{where} is still locked by worker processes of the server pid {holder.pid}, which has ended "
                    f"(waited {wait_s:g} s): they hold {self.path}; stop them or pass another --data-dir")
        at = f"at {holder.address}" if holder.address else "(an app without an address)"
        on = "" if holder.host == socket.gethostname() else f" on host {holder.host}"
        return (f"{where} is in use by the server pid {holder.pid}{on} {at} (started {holder.started}); "
                "stop it or pass another --data-dir")


def _write(fd: int, owner: Owner) -> None:
    """Replace the lock file's content with ``owner`` (the previous owner's, if any, is gone with its lock)."""
    os.ftruncate(fd, 0)
    os.pwrite(fd, (json.dumps(asdict(owner)) + "\n").encode(), 0)
    os.fsync(fd)
