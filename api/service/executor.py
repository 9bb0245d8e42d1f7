"""Where jobs run: the ``Executor`` interface and ``LocalExecutor``, long-lived spawned worker processes.

A ``Task`` holds file locations and parameters only, never recording bytes. ``run`` is called from a scheduler
thread (never the event loop) and blocks until the job ends; its ``Outcome`` says how. ``LocalExecutor`` keeps one
process per slot, started with the ``spawn`` method so no state of the server leaks into a worker; a worker that
dies (a crash, a kill, an out-of-memory kill) fails only the job it was running, with the cause recorded, and is
replaced for the next job. Workers write their progress to the job store themselves, run at a lower CPU priority
than the server, ignore Ctrl-C (the server decides when they stop) and exit when the server process is gone; each
holds a copy of the data directory's locked file (``share_fd``), so a new server cannot start while one of them
lives.

Both executors run the same job function, ``run_task``, under the same ``Watchdog``
(``slamreplay.api.service.limits``): a job past its memory or wall-time limit fails alone with that limit in its
error. ``LocalExecutor`` also watches each worker from outside and kills one that stays past a limit (a job stuck in
native code), and replaces a worker after a limit failure so that the next job starts with a fresh process, and
after ``MAX_JOBS_PER_WORKER`` jobs (memory a library keeps is given back). ``RayExecutor``
(``slamreplay.api.service.ray_executor``) runs the job as a Ray task.
"""

from __future__ import annotations

import multiprocessing
import os
import queue
import re
import signal
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from multiprocessing.connection import Connection, wait
from multiprocessing.process import BaseProcess
from pathlib import Path
from typing import Any, Literal, Protocol

from slamreplay.api.service.limits import GRACE_S, JobLimitExceeded, JobLimits, Watchdog, describe_exit, rss_mib

OutcomeStatus = Literal["succeeded", "failed", "cancelled", "interrupted"]
PROGRESS_INTERVAL_S = 0.25
WORKER_NICENESS = 10  # replays yield the CPU to the server process, so status requests stay fast under load
# A worker is replaced by a fresh process after this many jobs: rerun-sdk 0.41 keeps about 0.6 MiB
# of native memory per RecordingStream after it is disconnected and deleted (a replay grows a
# worker by about 1.7 MiB), so a long-lived worker would grow without bound (benchmarks/service_load.py).
MAX_JOBS_PER_WORKER = 100


@dataclass(frozen=True, slots=True)
class Task:
    """One job, by location: replay ``recording`` through ``pipeline`` into ``run_dir``.

    ``recording`` and ``run_dir`` are local paths or URLs (``slamreplay.api.service.storage``).
    """

    job_id: str
    recording: str
    pipeline: str
    config: dict[str, Any]
    seed: int
    run_dir: str
    db_path: str  # where a local worker reports progress ("" for none: a suite's cells)
    topic_map: dict[str, str] = field(default_factory=dict)  # file topic -> slamreplay topic (suites)
    rev: str | None = None  # a commit sha: run that revision's own code (``run_at_revision``); None: this code
    rev_cache: str = ""  # where revisions are built (``<cache>/revs/<sha>``), for a ``rev`` task


@dataclass(frozen=True, slots=True)
class Outcome:
    """How a job ended; ``interrupted``: the executor was shut down under it (re-queue it)."""

    status: OutcomeStatus
    error: str | None = None


Report = Callable[[float], None]  # progress of the running job, 0..1
Job = Callable[[Task, Report | None], Outcome]  # what a worker runs: ``run_task``, or a stand-in in tests


class Executor(Protocol):
    """Runs tasks somewhere; ``slots`` of them at once."""

    slots: int

    def start(self) -> None:
        """Get ready (start workers, connect to a cluster)."""

    def run(self, task: Task) -> Outcome:
        """Run ``task`` to its end; called from a scheduler thread, one per slot."""

    def cancel(self, job_id: str) -> None:
        """Stop ``job_id`` if it is running, and never start it if it is not yet."""

    def close(self) -> None:
        """Stop every worker; tasks still running end ``interrupted``."""


# ---------------------------------------------------------------------------------------
# Worker side (runs in the spawned process)


def _watch_parent(parent_pid: int) -> None:
    """Exit when the server process is gone, so an orphan never writes into a re-queued job's directory."""
    while True:
        if os.getppid() != parent_pid:
            os._exit(3)
        time.sleep(0.5)


def service_words(message: str, recording: str | None = None) -> str:
    """A replay error in the terms of jobs and suites: the replay CLI's ``--topic-map FILE_TOPIC=TOPIC`` is their
    ``topic_map`` field, and the recording is named by its file name (the server's folders are not the user's)."""
    if recording:
        message = message.replace(str(Path(recording).parent) + os.sep, "")
    return re.sub(r"--topic-map (\S+)=(\S+)", lambda m: f'topic_map {{"{m[1]}": "{m[2]}"}} '
                  "(a field of the job, or of the recording in a suite)", message)


def run_task(task: Task, report: Report | None = None) -> Outcome:
    """Run one task in this process (the body of a worker; also usable directly).

    The recording is staged to a local file when it is remote and the run directory is
    uploaded when it is (``slamreplay.api.service.storage``). ``report`` receives progress; by default it is
    written to the job store at ``task.db_path``.
    """
    from slamreplay.api.service.storage import StorageError, staged_recording, staged_run_dir
    from slamreplay.api.service.store import set_progress
    from slamreplay.replay.errors import ReplayError
    from slamreplay.replay.runs.run import run_recording

    if report is None:
        def report(fraction: float) -> None:
            set_progress(task.db_path, task.job_id, fraction)
    last = 0.0

    def progress(done: int, total: int) -> None:
        nonlocal last
        now = time.monotonic()
        if total > 0 and (now - last >= PROGRESS_INTERVAL_S or done >= total):
            last = now
            report(done / total)

    try:
        with staged_recording(task.recording) as recording, staged_run_dir(task.run_dir) as run_dir:
            if task.rev is not None:
                error = run_at_revision(task, task.rev, recording, run_dir)
                if error is not None:
                    return Outcome("failed", service_words(error, task.recording))
            else:
                run_recording(recording, task.pipeline, run_dir, seed=task.seed, config=task.config,
                              topic_map=task.topic_map, progress=progress, run_id=task.job_id)
    except ReplayError as err:
        return Outcome("failed", service_words(str(err), task.recording))
    except StorageError as err:
        return Outcome("failed", f"storage: {err}")
    except Exception as err:  # noqa: BLE001 -- any other error is this job's failure, not the worker's
        return Outcome("failed", f"internal error: {type(err).__name__}: {err}")
    return Outcome("succeeded")


def run_at_revision(task: Task, rev: str, recording: Path, run_dir: Path) -> str | None:
    """Run ``task`` with the code of the revision ``rev`` (its worktree under ``task.rev_cache``, in the environment
    shared by commits of the same dependencies, running its own ``slamreplay run``), in the git checkout the service
    runs from; an
    error message (one line: the checkout is gone, the revision does not build, the run failed), or None."""
    from slamreplay.replay.errors import ReplayError
    from slamreplay.replay.runs.revisions import find_repo, prepare_revision, run_at

    try:
        revision = prepare_revision(find_repo(), rev, Path(task.rev_cache))
    except ReplayError as err:
        return str(err)
    return run_at(revision, recording, task.pipeline, run_dir, task.seed, task.config, task.topic_map)


def run_limited(job: Job, task: Task, limits: JobLimits, report: Report | None = None,
                on_exceeded: Callable[[str], None] | None = None) -> Outcome:
    """``job(task, report)`` under a ``Watchdog``: past a limit, a failed outcome naming it."""
    dog = Watchdog(limits, on_exceeded)
    try:
        with dog:
            outcome = job(task, report)
    except JobLimitExceeded:
        pass  # delivered just after the block ended; dog.error says which limit
    if dog.error is not None:
        return Outcome("failed", dog.error)
    return outcome


class SharedFd:
    """An open file descriptor that a spawned worker receives a copy of (the same open file, as ``fork``
    would share it): the worker holds the data directory's lock for as long as it lives."""

    def __init__(self, fd: int) -> None:
        self.fd = fd

    def __reduce__(self) -> tuple[Any, ...]:
        from multiprocessing import reduction

        # DupFd passes the descriptor to the child being spawned (as multiprocessing does for Pipe ends)
        return (_received_fd, (reduction.DupFd(self.fd),))


def _received_fd(dup: Any) -> SharedFd:
    return SharedFd(dup.detach())


def _worker_main(conn: Connection, parent_pid: int, job: Job, limits: JobLimits,
                 held: SharedFd | None = None) -> None:
    # ``held`` is never closed: the data directory stays locked until this process ends
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    os.nice(WORKER_NICENESS)
    threading.Thread(target=_watch_parent, args=(parent_pid,), daemon=True).start()
    import slamreplay.replay.runs.run  # noqa: F401
    from slamreplay.replay.engine.pipeline import all_pipelines

    all_pipelines()  # pay the import cost before the first job, not during it

    while True:
        try:
            task = conn.recv()
        except (EOFError, OSError):
            return
        outcome = run_limited(job, task, limits)
        conn.send(outcome)
        if limits.is_limit_error(outcome.error):
            return  # memory the job held may not all go back to the system: the next job gets a fresh process


# ---------------------------------------------------------------------------------------
# Server side


@dataclass
class _Worker:
    proc: BaseProcess | None = None
    conn: Connection | None = None
    job_id: str | None = None
    jobs: int = 0  # jobs this process has run

    def alive(self) -> bool:
        return self.proc is not None and self.proc.is_alive()

    def stop(self) -> None:
        """Terminate the process (kill it if it lingers) and wait for it; it may be running a job."""
        if self.proc is not None and self.proc.is_alive():
            self.proc.terminate()
            self.proc.join(2.0)
            if self.proc.is_alive():
                self.proc.kill()
                self.proc.join(2.0)

    def replace(self, ctx: Any, parent_pid: int, job: Job, limits: JobLimits, held: int | None = None) -> None:
        """Start a fresh process in place of this one (which is stopped first); it gets a copy of ``held``."""
        self.stop()
        if self.conn is not None:
            self.conn.close()
        parent, child = ctx.Pipe()
        shared = None if held is None else SharedFd(held)
        proc = ctx.Process(target=_worker_main, args=(child, parent_pid, job, limits, shared), daemon=True,
                           name="slamreplay-worker")
        proc.start()
        child.close()
        self.proc, self.conn, self.jobs = proc, parent, 0


class LocalExecutor:
    """``workers`` spawned processes, each running one job at a time and replaced when it dies.

    ``job`` is what workers run (``run_task``; a module-level function, as it is pickled).
    """

    def __init__(self, workers: int, limits: JobLimits | None = None, job: Job = run_task,
                 max_jobs_per_worker: int = MAX_JOBS_PER_WORKER) -> None:
        self.slots = workers
        self.max_jobs_per_worker = max_jobs_per_worker
        self.limits = limits or JobLimits()
        self._job = job
        self._ctx = multiprocessing.get_context("spawn")
        self._workers = [_Worker() for _ in range(workers)]
        self._idle: queue.Queue[_Worker] = queue.Queue()
        self._lock = threading.Lock()
        self._cancelled: set[str] = set()
        self._closed = False
        self._held: int | None = None

    def share_fd(self, fd: int) -> None:
        """Give every worker started from now on a copy of ``fd``, the data directory's locked file: the lock
        then outlives a killed server until its last worker has exited (slamreplay.api.service.datalock)."""
        self._held = fd

    def start(self) -> None:
        with self._lock:
            for worker in self._workers:
                worker.replace(self._ctx, os.getpid(), self._job, self.limits, self._held)
                self._idle.put(worker)

    def worker_pids(self) -> dict[str, int]:
        """Job id -> pid of the process running it."""
        with self._lock:
            return {w.job_id: w.proc.pid for w in self._workers
                    if w.job_id is not None and w.proc is not None and w.proc.pid is not None}

    def run(self, task: Task) -> Outcome:
        worker = self._idle.get()
        retire = False
        try:
            with self._lock:
                if self._closed:
                    return Outcome("interrupted", "the server is shutting down")
                if task.job_id in self._cancelled:
                    return Outcome("cancelled", "cancelled by request")
                if not worker.alive():
                    worker.replace(self._ctx, os.getpid(), self._job, self.limits, self._held)
                worker.job_id = task.job_id
                proc, conn = worker.proc, worker.conn
            if proc is None or conn is None:
                raise RuntimeError("worker slot has no process")  # replace() always sets both
            killed_for: str | None = None
            try:
                conn.send(task)
                killed_for = self._wait(conn, proc)
                if killed_for is None and conn.poll():
                    result: Outcome = conn.recv()
                    if self.limits.is_limit_error(result.error):
                        # the worker exits after a limit failure; it is replaced below even if it has not
                        # exited yet (a loaded host can take longer than GRACE_S to return its memory), or
                        # the next job would be sent to a process about to end
                        retire = True
                        proc.join(GRACE_S)
                    return result
            except (EOFError, OSError, BrokenPipeError):
                pass
            proc.join(1.0)
            exitcode = proc.exitcode
            with self._lock:
                if self._closed:
                    return Outcome("interrupted", "the server is shutting down")
                if task.job_id in self._cancelled:
                    return Outcome("cancelled", "cancelled by request")
            error = killed_for or self.limits.exit_error(exitcode)
            return Outcome("failed", error or f"{describe_exit(exitcode)} while running this job")
        finally:
            with self._lock:
                worker.job_id = None
                worker.jobs += 1
                self._cancelled.discard(task.job_id)
                if not self._closed and (retire or not worker.alive() or worker.jobs >= self.max_jobs_per_worker):
                    worker.replace(self._ctx, os.getpid(), self._job, self.limits, self._held)  # idle: safe to stop
            self._idle.put(worker)

    def _wait(self, conn: Connection, proc: BaseProcess) -> str | None:
        """Wait for the worker's answer or its end; kill it when it stays past a limit ``GRACE_S`` longer
        than its own watchdog allows (stuck in native code), and return that limit's error."""
        limits = self.limits
        if not limits.any():
            wait([conn, proc.sentinel])
            return None
        started, over_since = time.monotonic(), None
        while not wait([conn, proc.sentinel], timeout=0.1):
            now = time.monotonic()
            if limits.wall_s is not None and now - started > limits.wall_s + GRACE_S:
                proc.kill()
                return limits.wall_error()
            rss = rss_mib(proc.pid) if limits.memory_mib is not None and proc.pid is not None else None
            if rss is not None and limits.memory_mib is not None and rss > limits.memory_mib:
                over_since = over_since if over_since is not None else now
                if now - over_since > GRACE_S:
                    proc.kill()
                    return limits.memory_error()
            else:
                over_since = None
        return None

    def cancel(self, job_id: str) -> None:
        with self._lock:
            self._cancelled.add(job_id)
            for worker in self._workers:
                if worker.job_id == job_id and worker.proc is not None:
                    worker.proc.kill()  # the job's run directory keeps a failed manifest at most

    def close(self) -> None:
        with self._lock:
            self._closed = True
            workers = list(self._workers)
        for worker in workers:
            if worker.proc is not None and worker.proc.is_alive():
                worker.proc.terminate()
        for worker in workers:
            worker.stop()  # pipes stay open: a scheduler thread may still be waiting on one
