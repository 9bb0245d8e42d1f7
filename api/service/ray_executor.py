"""``RayExecutor``: each job is a Ray task running the same ``run_task`` as ``LocalExecutor``.

Ray is an optional extra (``pip install -e '.[ray]'``) imported only when this executor
is built. Without an address it starts a local Ray instance with one CPU per slot; with one
(``ray://head:10001``, ``auto``) it joins that cluster. Each job asks for one CPU and is never
retried by Ray (a job that crashed its worker fails, as it does locally).

Progress goes through a small actor that the server owns (``_JobSink``): the task reports
to it, and the scheduler thread waiting on the job polls it and writes the job store, so
workers need no access to the server's database. Recordings and runs must be where workers
can reach them: on one machine the data directory does; on a cluster set a storage URL
(``Settings.storage_url``: an object store, or a file system shared by every node).

Limits: the task runs under the same ``Watchdog`` as a local job, which reports the limit
to the sink before the job is stopped, so its error survives the worker when the job has to
be ended with the process. The server also cancels (force) a job still running ``GRACE_S``
past its wall-time limit. Cancellation is ``ray.cancel(force=True)``: the worker process
is killed, as a local one is.
"""

from __future__ import annotations

import contextlib
import logging
import os
import threading
import time
from typing import Any

from slamreplay.api.service.executor import (
    PROGRESS_INTERVAL_S,
    WORKER_NICENESS,
    Job,
    Outcome,
    Task,
    run_limited,
    run_task,
)
from slamreplay.api.service.limits import GRACE_S, JobLimits

log = logging.getLogger("slamreplay.ray")
INSTALL_HINT = "the ray executor needs the ray extra: `pip install -e '.[ray]'` in the slamreplay checkout"


class RayMissingError(ImportError):
    """Ray is not installed; the message says how to install it."""


def import_ray() -> Any:
    """The ``ray`` module; RayMissingError with the install command when it is missing."""
    try:
        import ray
    except ImportError as err:
        raise RayMissingError(f"{INSTALL_HINT} ({err})") from err
    return ray


class _JobSink:
    """A Ray actor beside the server: progress and limit errors reported by running tasks."""

    def __init__(self) -> None:
        self.progress: dict[str, float] = {}
        self.errors: dict[str, str] = {}

    def report(self, job_id: str, fraction: float) -> None:
        self.progress[job_id] = fraction

    def exceeded(self, job_id: str, message: str) -> None:
        self.errors[job_id] = message

    def take(self, job_id: str) -> tuple[float | None, str | None]:
        """The latest progress not taken yet, and the limit error if any."""
        return self.progress.pop(job_id, None), self.errors.get(job_id)

    def forget(self, job_id: str) -> None:
        self.progress.pop(job_id, None)
        self.errors.pop(job_id, None)


def _ray_job(job: Job, task: Task, limits: JobLimits, sink: Any) -> Outcome:
    """The body of the Ray task: ``job`` under the limits, reporting to ``sink``."""
    import ray

    niceness = os.nice(0)
    if niceness < WORKER_NICENESS:
        os.nice(WORKER_NICENESS - niceness)  # on the server's machine, replays yield the CPU to it
    sink.report.remote(task.job_id, 0.0)  # started: the server's wall-time backstop counts from here

    def report(fraction: float) -> None:
        sink.report.remote(task.job_id, fraction)

    def exceeded(message: str) -> None:
        ray.get(sink.exceeded.remote(task.job_id, message), timeout=GRACE_S / 2)

    return run_limited(job, task, limits, report, exceeded)


def _warm_up() -> int:
    """Import the pipelines in a Ray worker before the first job needs them."""
    import slamreplay.replay.runs.run  # noqa: F401
    from slamreplay.replay.engine.pipeline import all_pipelines

    all_pipelines()

    return os.getpid()


class RayExecutor:
    """Jobs as Ray tasks, ``slots`` at once; ``job`` is what tasks run (``run_task``)."""

    def __init__(self, slots: int, limits: JobLimits | None = None, *, address: str | None = None,
                 job: Job = run_task, warm_up: bool = True) -> None:
        self.ray = import_ray()
        self.slots = slots
        self.limits = limits or JobLimits()
        self.address = address
        self._job = job
        self._warm_up = warm_up
        self._lock = threading.Lock()
        self._running: dict[str, Any] = {}  # job id -> ObjectRef
        self._cancelled: set[str] = set()
        self._closed = False
        self._started_ray = False
        self._sink: Any = None
        self._task: Any = None

    def start(self) -> None:
        ray = self.ray
        if not ray.is_initialized():
            kwargs: dict[str, Any] = {"address": self.address} if self.address else {"num_cpus": self.slots}
            ray.init(include_dashboard=False, log_to_driver=False, **kwargs)
            self._started_ray = True
        self._sink = ray.remote(num_cpus=0)(_JobSink).remote()
        self._task = ray.remote(num_cpus=1, max_retries=0)(_ray_job)
        if self._warm_up:
            warm = ray.remote(num_cpus=1)(_warm_up)
            ray.get([warm.remote() for _ in range(self.slots)])

    def run(self, task: Task) -> Outcome:
        ray = self.ray
        with self._lock:
            if self._closed:
                return Outcome("interrupted", "the server is shutting down")
            if task.job_id in self._cancelled:
                self._cancelled.discard(task.job_id)
                return Outcome("cancelled", "cancelled by request")
            ref = self._task.remote(self._job, task, self.limits, self._sink)
            self._running[task.job_id] = ref
        killed_for: str | None = None
        limit_error: str | None = None
        try:
            started: float | None = None
            while True:
                ready, _ = ray.wait([ref], timeout=PROGRESS_INTERVAL_S)
                fraction, limit_error = self._forward(task)
                if fraction is not None and started is None:
                    started = time.monotonic()
                if ready:
                    break
                wall = self.limits.wall_s
                if wall is not None and started is not None and time.monotonic() - started > wall + GRACE_S:
                    killed_for = self.limits.wall_error()
                    ray.cancel(ref, force=True)
                    break
            try:
                outcome: Outcome = ray.get(ref)
                return outcome
            except ray.exceptions.RayError as err:
                _, limit_error = self._forward(task)
                return self._failure(task.job_id, err, killed_for or limit_error)
        finally:
            with contextlib.suppress(Exception):  # Ray already gone: nothing to forget
                self._sink.forget.remote(task.job_id)  # before the job leaves _running: close() may then end Ray
            with self._lock:
                self._running.pop(task.job_id, None)
                self._cancelled.discard(task.job_id)

    def _forward(self, task: Task) -> tuple[float | None, str | None]:
        """Copy the job's latest progress from the sink into the job store; (progress, limit error)."""
        from slamreplay.api.service.store import set_progress

        try:
            fraction, error = self.ray.get(self._sink.take.remote(task.job_id), timeout=10)
        except self.ray.exceptions.RayError as err:  # progress is best effort
            log.warning("job %s: no progress from the sink: %s", task.job_id, err)
            return None, None
        if fraction is not None and task.db_path:  # no job store (a suite's cells): nothing to write
            set_progress(task.db_path, task.job_id, fraction)
        return fraction, error

    def _failure(self, job_id: str, err: Exception, limit_error: str | None) -> Outcome:
        """The outcome of a task that Ray could not complete."""
        exceptions = self.ray.exceptions
        with self._lock:
            if self._closed:
                return Outcome("interrupted", "the server is shutting down")
            if job_id in self._cancelled:
                return Outcome("cancelled", "cancelled by request")
        if limit_error is not None:
            return Outcome("failed", limit_error)
        if isinstance(err, exceptions.OutOfMemoryError):
            return Outcome("failed", "Ray's memory monitor killed the worker running this job: its node was short of "
                                     "memory")
        if isinstance(err, exceptions.WorkerCrashedError | exceptions.TaskCancelledError):
            return Outcome("failed", "the Ray worker process running this job died (a crash, or a kill, for example "
                                     "by the out-of-memory killer)")
        text = str(err).strip().splitlines()
        return Outcome("failed", f"ray: {type(err).__name__}: {text[-1] if text else ''}")

    def cancel(self, job_id: str) -> None:
        with self._lock:
            self._cancelled.add(job_id)
            ref = self._running.get(job_id)
        if ref is not None:
            self.ray.cancel(ref, force=True)

    def close(self) -> None:
        with self._lock:
            self._closed = True
            running = list(self._running.values())
        for ref in running:
            self.ray.cancel(ref, force=True)
        if self._started_ray:
            deadline = time.monotonic() + 10.0
            while time.monotonic() < deadline:  # let the scheduler threads see their tasks end before Ray goes
                with self._lock:
                    if not self._running:
                        break
                time.sleep(0.05)
            self.ray.shutdown()
