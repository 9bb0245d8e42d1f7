"""Where jobs run: the ``Executor`` interface and ``LocalExecutor``, long-lived spawned worker processes.

A ``Task`` holds file locations and parameters only, never recording bytes. ``run`` is
called from a scheduler thread (never the event loop) and blocks until the job ends; its
``Outcome`` says how. ``LocalExecutor`` keeps one process per slot, started with the
``spawn`` method so no state of the server leaks into a worker; a worker that dies (a
crash, a kill, an out-of-memory kill) fails only the job it was running, with the cause
recorded, and is replaced for the next job. Workers write their progress to the job store
themselves, run at a lower CPU priority than the server, ignore Ctrl-C (the server decides
when they stop) and exit when the server process is gone.
"""

from __future__ import annotations

import multiprocessing
import os
import queue
import shutil
import signal
import threading
import time
from dataclasses import dataclass
from multiprocessing.connection import Connection, wait
from multiprocessing.process import BaseProcess
from pathlib import Path
from typing import Any, Literal, Protocol

OutcomeStatus = Literal["succeeded", "failed", "cancelled", "interrupted"]
PROGRESS_INTERVAL_S = 0.25
WORKER_NICENESS = 10  # replays yield the CPU to the server process, so status requests stay fast under load


@dataclass(frozen=True, slots=True)
class Task:
    """One job, by file location: replay ``recording`` through ``pipeline`` into ``run_dir``."""

    job_id: str
    recording: str
    pipeline: str
    config: dict[str, Any]
    seed: int
    run_dir: str
    db_path: str  # where the worker reports progress


@dataclass(frozen=True, slots=True)
class Outcome:
    """How a job ended; ``interrupted``: the executor was shut down under it (re-queue it)."""

    status: OutcomeStatus
    error: str | None = None


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


def run_task(task: Task) -> Outcome:
    """Run one task in this process (the body of a worker; also usable directly)."""
    from api.store import set_progress
    from replay.errors import ReplayError
    from replay.run import run_recording

    run_dir = Path(task.run_dir)
    if run_dir.exists():
        shutil.rmtree(run_dir)  # left by an attempt that a server stop interrupted
    last = 0.0

    def progress(done: int, total: int) -> None:
        nonlocal last
        now = time.monotonic()
        if total > 0 and (now - last >= PROGRESS_INTERVAL_S or done >= total):
            last = now
            set_progress(task.db_path, task.job_id, done / total)

    try:
        run_recording(task.recording, task.pipeline, run_dir, seed=task.seed, config=task.config,
                      progress=progress, run_id=task.job_id)
    except ReplayError as err:
        return Outcome("failed", str(err))
    except Exception as err:  # noqa: BLE001 -- any other error is this job's failure, not the worker's
        return Outcome("failed", f"internal error: {type(err).__name__}: {err}")
    return Outcome("succeeded")


def _worker_main(conn: Connection, parent_pid: int) -> None:
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    os.nice(WORKER_NICENESS)
    threading.Thread(target=_watch_parent, args=(parent_pid,), daemon=True).start()
    import replay.pipelines  # pay the import cost before the first job, not during it
    import replay.run  # noqa: F401

    while True:
        try:
            task = conn.recv()
        except (EOFError, OSError):
            return
        conn.send(run_task(task))


# ---------------------------------------------------------------------------------------
# Server side


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


@dataclass
class _Worker:
    proc: BaseProcess | None = None
    conn: Connection | None = None
    job_id: str | None = None

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

    def replace(self, ctx: Any, parent_pid: int) -> None:
        """Start a fresh process in place of this one (which is stopped first)."""
        self.stop()
        if self.conn is not None:
            self.conn.close()
        parent, child = ctx.Pipe()
        proc = ctx.Process(target=_worker_main, args=(child, parent_pid), daemon=True, name="slamreplay-worker")
        proc.start()
        child.close()
        self.proc, self.conn = proc, parent


class LocalExecutor:
    """``workers`` spawned processes, each running one job at a time and replaced when it dies."""

    def __init__(self, workers: int) -> None:
        self.slots = workers
        self._ctx = multiprocessing.get_context("spawn")
        self._workers = [_Worker() for _ in range(workers)]
        self._idle: queue.Queue[_Worker] = queue.Queue()
        self._lock = threading.Lock()
        self._cancelled: set[str] = set()
        self._closed = False

    def start(self) -> None:
        with self._lock:
            for worker in self._workers:
                worker.replace(self._ctx, os.getpid())
                self._idle.put(worker)

    def worker_pids(self) -> dict[str, int]:
        """Job id -> pid of the process running it."""
        with self._lock:
            return {w.job_id: w.proc.pid for w in self._workers
                    if w.job_id is not None and w.proc is not None and w.proc.pid is not None}

    def run(self, task: Task) -> Outcome:
        worker = self._idle.get()
        try:
            with self._lock:
                if self._closed:
                    return Outcome("interrupted", "the server is shutting down")
                if task.job_id in self._cancelled:
                    return Outcome("cancelled", "cancelled by request")
                if not worker.alive():
                    worker.replace(self._ctx, os.getpid())
                worker.job_id = task.job_id
                proc, conn = worker.proc, worker.conn
            if proc is None or conn is None:
                raise RuntimeError("worker slot has no process")  # replace() always sets both
            try:
                conn.send(task)
                wait([conn, proc.sentinel])
                if conn.poll():
                    result: Outcome = conn.recv()
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
            return Outcome("failed", f"{describe_exit(exitcode)} while running this job")
        finally:
            with self._lock:
                worker.job_id = None
                self._cancelled.discard(task.job_id)
                if not self._closed and not worker.alive():
                    worker.replace(self._ctx, os.getpid())
            self._idle.put(worker)

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
