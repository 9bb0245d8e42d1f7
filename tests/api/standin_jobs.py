"""Stand-in jobs for executor tests: ``task.pipeline`` picks one; a real pipeline name runs ``run_task``.

Module-level functions, so that spawned workers import them and Ray pickles them (by value:
``ray.cloudpickle.register_pickle_by_value`` on this module).
"""

from __future__ import annotations

import os
import signal
import threading
import time

import numpy as np

from slamreplay.api.service.executor import Outcome, Report, Task, run_task
from slamreplay.api.service.limits import JobLimits

HOG_STEP_BYTES = 32 << 20
SLOW_EXIT_S = 6.0  # longer than the executor's GRACE_S wait for a worker to exit
SLOW_EXIT_LIMIT_S = 60.0  # the wall-time limit whose failure ``slow-exit`` reports (the executor's in the test)
HOG_MAX_BYTES = 3 << 30  # the stand-in gives up (and "succeeds") here, so a broken limit fails the test, not the host


def standin_job(task: Task, report: Report | None = None) -> Outcome:
    """``hog``: allocate until stopped; ``sleep``: 60 s in short naps; ``stuck``: 60 s in one native call;
    ``slow-exit``: fails on the wall-time limit SLOW_EXIT_LIMIT_S at once, its process ending SLOW_EXIT_S later;
    ``crash``: SIGKILL itself;
    anything else: the real job."""
    if task.pipeline == "hog":
        chunks = []
        while len(chunks) * HOG_STEP_BYTES < HOG_MAX_BYTES:
            chunks.append(np.ones(HOG_STEP_BYTES // 8))  # touched, so resident
            time.sleep(0.005)
        return Outcome("succeeded", "the hog was never stopped")
    if task.pipeline == "sleep":
        for _ in range(600):
            time.sleep(0.1)
        return Outcome("succeeded", "the sleeper was never stopped")
    if task.pipeline == "stuck":
        time.sleep(60)  # one call: an exception raised into this thread waits for it to return
        return Outcome("succeeded", "the stuck job was never stopped")
    if task.pipeline == "slow-exit":  # fails on a limit at once; its process lives on, as a slow exit on a loaded host
        threading.Thread(target=time.sleep, args=(SLOW_EXIT_S,)).start()  # not a daemon: the exit waits for it
        return Outcome("failed", JobLimits(wall_s=SLOW_EXIT_LIMIT_S).wall_error())
    if task.pipeline == "crash":
        os.kill(os.getpid(), signal.SIGKILL)
    return run_task(task, report)
