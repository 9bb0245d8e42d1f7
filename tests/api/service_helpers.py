"""Helpers shared by the service tests: a job store, claimed tasks, concurrent runs, an in-thread executor."""

from __future__ import annotations

import threading
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol

from slamreplay.api.service.executor import Outcome, Task, run_task
from slamreplay.api.service.store import RecordingRow, Store

if TYPE_CHECKING:
    from fastapi.testclient import TestClient

SHA = "a" * 64  # the one recording every test store holds


class Runs(Protocol):
    def run(self, task: Task) -> Outcome: ...
    def cancel(self, job_id: str) -> None: ...


def make_store(path: Path) -> Store:
    """A job store at ``path`` holding the recording :data:`SHA`."""
    s = Store(path)
    s.add_recording(RecordingRow(SHA, "x.mcap", 10, [], 0, 0, 0, 0.0))
    return s


def claimed(store: Store, recording: Path, job_id: str, pipeline: str, tmp_path: Path, seed: int = 0) -> Task:
    """Queue and claim a job, as the scheduler does, and describe it as a task."""
    store.add_job(job_id, SHA, pipeline, {}, seed)
    job = store.claim_next()
    assert job is not None and job.id == job_id
    return Task(job_id, str(recording), pipeline, {}, seed, str(tmp_path / job_id), str(store.path))


def run_all(executor: Runs, tasks: list[Task], cancel_after_s: float | None = None) -> list[Outcome]:
    """Run the tasks at once, one scheduler thread each, as JobService does; optionally cancel the first."""
    out: dict[str, Outcome] = {}
    threads = [threading.Thread(target=lambda t=t: out.__setitem__(t.job_id, executor.run(t))) for t in tasks]
    for t in threads:
        t.start()
    if cancel_after_s is not None:
        time.sleep(cancel_after_s)
        executor.cancel(tasks[0].job_id)
    for t in threads:
        t.join(120)
    return [out[t.job_id] for t in tasks]


class InlineExecutor:
    """Runs each task in the scheduler thread: the routes' contract without process start-up costs
    (and one process, so fsspec's memory:// is shared with the server)."""

    slots = 1

    def start(self) -> None:
        """Nothing to start."""

    def run(self, task: Task) -> Outcome:
        return run_task(task)

    def cancel(self, job_id: str) -> None:
        """Tasks here are too short to cancel."""

    def close(self) -> None:
        """Nothing to stop."""


def wait_for(client: TestClient, job_id: str, timeout_s: float = 60.0) -> dict[str, Any]:
    """Poll a job until it has ended."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        job: dict[str, Any] = client.get(f"/jobs/{job_id}").json()
        if job["status"] not in ("queued", "running"):
            return job
        time.sleep(0.05)
    raise AssertionError(f"job {job_id} did not end within {timeout_s} s")
