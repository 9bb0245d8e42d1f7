"""Per-job limits: the resident memory of the job's process and its wall time.

The limit is on resident memory (RSS, read from ``/proc``), the figure the kernel's
out-of-memory killer weighs, not on address space: RLIMIT_AS would count the gigabytes
that thread stacks, allocator arenas and mapped libraries reserve but never touch (an idle
worker reserves about 3.6 GiB and uses about 200 MiB). It includes the worker's own imports.

``Watchdog`` runs in the job's process, beside the job: once a limit is passed it raises
``JobLimitExceeded`` in the job's thread, so the run ends like a failed run (its manifest
and log written); a job stuck in native code that does not let go within ``GRACE_S`` is
ended with ``os._exit(EXIT_MEMORY | EXIT_WALL)``. Executors that watch their workers from
outside (``LocalExecutor``) also kill a worker that is past a limit by ``GRACE_S`` more.
Memory is read on Linux only; elsewhere only the wall-time limit holds.
"""

from __future__ import annotations

import contextlib
import ctypes
import os
import signal
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from types import TracebackType

POLL_S = 0.05
GRACE_S = 3.0
EXIT_MEMORY = 86  # exit codes of a worker ended by its own watchdog
EXIT_WALL = 87
_PAGE = os.sysconf("SC_PAGE_SIZE") if hasattr(os, "sysconf") else 4096


class JobLimitExceeded(BaseException):
    """Raised in a job's thread by its watchdog; a BaseException so that no ``except Exception`` in a
    pipeline swallows it."""


@dataclass(frozen=True, slots=True)
class JobLimits:
    """Limits of one job; None: no limit."""

    memory_mib: int | None = None
    wall_s: float | None = None

    def memory_error(self) -> str:
        return f"job exceeded its memory limit of {self.memory_mib} MiB"

    def wall_error(self) -> str:
        return f"job exceeded its wall-time limit of {self.wall_s or 0:g} s"

    def exit_error(self, exitcode: int | None) -> str | None:
        """The error of a worker that its watchdog ended with ``exitcode``; None for other exits."""
        if exitcode == EXIT_MEMORY and self.memory_mib is not None:
            return self.memory_error()
        if exitcode == EXIT_WALL and self.wall_s is not None:
            return self.wall_error()
        return None

    def is_limit_error(self, error: str | None) -> bool:
        """Whether ``error`` is the message of one of these limits."""
        return error is not None and error in (self.memory_error(), self.wall_error())

    def any(self) -> bool:
        return self.memory_mib is not None or self.wall_s is not None


def rss_mib(pid: int | None = None) -> float | None:
    """Resident memory of process ``pid`` (this one by default) in MiB; None when it cannot be read."""
    try:
        with open(f"/proc/{pid or 'self'}/statm", encoding="ascii") as f:
            return int(f.read().split()[1]) * _PAGE / 2**20
    except (OSError, IndexError, ValueError):
        return None


def _raise_in(thread_id: int, exc: type[BaseException]) -> None:
    """Raise ``exc`` in another thread at its next bytecode (not inside a native call)."""
    ctypes.pythonapi.PyThreadState_SetAsyncExc(ctypes.c_ulong(thread_id), ctypes.py_object(exc))


def _clear_pending(thread_id: int) -> None:
    ctypes.pythonapi.PyThreadState_SetAsyncExc(ctypes.c_ulong(thread_id), None)


class Watchdog:
    """Enforce ``limits`` on the code run inside ``with Watchdog(limits) as dog:`` in this thread.

    ``on_exceeded(message)`` is called (from the watchdog thread) before the job is stopped,
    e.g. to report the reason somewhere that outlives this process. After the block,
    ``dog.error`` is the limit's message when one was passed.
    """

    def __init__(self, limits: JobLimits, on_exceeded: Callable[[str], None] | None = None) -> None:
        self.limits = limits
        self.on_exceeded = on_exceeded
        self.error: str | None = None
        self._done = threading.Event()
        self._target = threading.get_ident()
        self._thread: threading.Thread | None = None

    def __enter__(self) -> Watchdog:
        self._target = threading.get_ident()
        if self.limits.any():
            self._thread = threading.Thread(target=self._watch, name="slamreplay-watchdog", daemon=True)
            self._thread.start()
        return self

    def __exit__(self, kind: type[BaseException] | None, value: BaseException | None,
                 tb: TracebackType | None) -> bool:
        self._done.set()
        if self._thread is not None:
            self._thread.join()
        if self.error is not None:
            _clear_pending(self._target)  # the job ended as the watchdog fired: drop the undelivered exception
        return kind is JobLimitExceeded and self.error is not None  # swallow our own exception only

    def _watch(self) -> None:
        start = time.monotonic()
        while not self._done.wait(POLL_S):
            rss = rss_mib() if self.limits.memory_mib is not None else None
            if rss is not None and self.limits.memory_mib is not None and rss > self.limits.memory_mib:
                self._stop(self.limits.memory_error(), EXIT_MEMORY)
                return
            if self.limits.wall_s is not None and time.monotonic() - start > self.limits.wall_s:
                self._stop(self.limits.wall_error(), EXIT_WALL)
                return

    def _stop(self, message: str, exitcode: int) -> None:
        self.error = message
        if self.on_exceeded is not None:
            with contextlib.suppress(Exception):  # reporting is best effort; stopping the job is not
                self.on_exceeded(message)
        _raise_in(self._target, JobLimitExceeded)
        if not self._done.wait(GRACE_S):
            os._exit(exitcode)  # the job is stuck in native code; its process goes, the limit holds


def describe_exit(exitcode: int | None) -> str:
    """Why a worker process ended, in words."""
    if exitcode is None:
        return "the worker process stopped answering"
    if exitcode < 0:
        try:
            name = signal.Signals(-exitcode).name
        except ValueError:
            name = f"signal {-exitcode}"
        hint = " (for example by the out-of-memory killer)" if -exitcode == signal.SIGKILL else ""
        return f"the worker process was killed by {name}{hint}"
    return f"the worker process exited with code {exitcode}"
