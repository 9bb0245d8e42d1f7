"""How long a test waits for something that takes wall-clock time (a server starting, a killed process's workers
leaving), scaled by how busy the machine is: a deadline is a guard against a hang, not a speed test (those are in
benchmarks/), and a loaded 2-core machine must not fail the suite by missing one by a fraction of a second.

``patience()``: the factor, at least 1: the 1-minute load average per CPU, times ``$SLAMREPLAY_TEST_PATIENCE``
(default 1; CI on a shared machine may raise it). ``deadline(s)``: ``time.monotonic()`` plus ``s`` times it.
"""

from __future__ import annotations

import os
import time


def patience() -> float:
    try:
        busy = os.getloadavg()[0] / (os.cpu_count() or 1)
    except OSError:
        busy = 1.0
    return max(1.0, busy) * max(1.0, float(os.environ.get("SLAMREPLAY_TEST_PATIENCE", "1") or 1))


def deadline(seconds: float) -> float:
    """When to stop waiting for something that takes about ``seconds`` on an idle machine."""
    return time.monotonic() + seconds * patience()
