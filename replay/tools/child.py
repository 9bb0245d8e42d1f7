"""Programs slamreplay starts (external pipelines, a revision's ``slamreplay run``): what the child does between
fork and exec, so that a job killed past its limits, or cancelled, leaves nothing running behind it.
"""

from __future__ import annotations

import ctypes
import resource
import signal
from collections.abc import Callable
from typing import Any

PR_SET_PDEATHSIG = 1  # linux/prctl.h


def child_setup(memory_mib: int | None = None) -> Callable[[], None]:
    """A ``preexec_fn``: the child's address-space limit (``memory_mib``), and (Linux) SIGKILL when the thread that
    started it dies, so that a worker killed by the service's limits or a cancel takes its program with it."""
    try:
        libc: Any = ctypes.CDLL(None, use_errno=True)
        prctl = libc.prctl
    except (OSError, AttributeError):
        prctl = None

    def apply() -> None:  # in the child: its address space, not slamreplay's
        if memory_mib is not None:
            limit = memory_mib * 1024 * 1024
            resource.setrlimit(resource.RLIMIT_AS, (limit, limit))
        if prctl is not None:
            prctl(PR_SET_PDEATHSIG, signal.SIGKILL)

    return apply
