"""LocalExecutor: jobs in spawned worker processes; a killed worker fails only its job; cancel; progress."""

from __future__ import annotations

import os
import signal
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
from conftest import write_tiny_recording
from service_helpers import claimed, make_store

from slamreplay.api.service.executor import LocalExecutor, Outcome, Task, run_task
from slamreplay.api.service.limits import describe_exit
from slamreplay.api.service.store import Store


@pytest.fixture(scope="module")
def executor() -> Iterator[LocalExecutor]:
    """One spawned worker, shared by the tests of this module."""
    ex = LocalExecutor(1)
    ex.start()
    yield ex
    ex.close()


@pytest.fixture
def store(tmp_path: Path) -> Store:
    return make_store(tmp_path / "jobs.sqlite")


def run_in_thread(executor: LocalExecutor, task: Task) -> tuple[threading.Thread, list[Outcome]]:
    out: list[Outcome] = []
    t = threading.Thread(target=lambda: out.append(executor.run(task)))
    t.start()
    return t, out


def pid_of(executor: LocalExecutor, job_id: str, timeout_s: float = 30.0) -> int:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        pid = executor.worker_pids().get(job_id)
        if pid is not None:
            return pid
        time.sleep(0.02)
    raise AssertionError(f"job {job_id} never reached a worker")


def test_killed_worker_fails_only_its_job(executor: LocalExecutor, store: Store, tmp_path: Path) -> None:
    """SIGKILL of the worker fails that job with the cause; the next job runs in a fresh worker and reports progress."""
    rec = write_tiny_recording(tmp_path / "tiny.mcap")
    doomed = claimed(store, rec, "1" * 32, "odometry", tmp_path)
    thread, out = run_in_thread(executor, doomed)
    os.kill(pid_of(executor, doomed.job_id), signal.SIGKILL)
    thread.join(60)
    assert out == [Outcome("failed", "the worker process was killed by SIGKILL (for example by the out-of-memory "
                                     "killer) while running this job")]
    healthy = claimed(store, rec, "2" * 32, "odometry", tmp_path)
    assert executor.run(healthy) == Outcome("succeeded")
    assert (tmp_path / healthy.job_id / "run.rrd").is_file()
    job = store.get_job(healthy.job_id)
    assert job is not None and job.progress == 1.0  # written by the worker process itself


def test_cancel_stops_a_running_job(executor: LocalExecutor, store: Store, tmp_path: Path) -> None:
    """cancel() of a running job ends it as cancelled, and the worker is replaced."""
    rec = write_tiny_recording(tmp_path / "tiny.mcap")
    task = claimed(store, rec, "3" * 32, "odometry", tmp_path)
    thread, out = run_in_thread(executor, task)
    pid = pid_of(executor, task.job_id)
    executor.cancel(task.job_id)
    thread.join(60)
    assert out == [Outcome("cancelled", "cancelled by request")]
    with pytest.raises(ProcessLookupError):
        os.kill(pid, 0)


def test_run_task_reports_bad_input_and_clears_a_stale_run_dir(store: Store, tmp_path: Path) -> None:
    """run_task turns a ReplayError into a failed outcome and replaces what an interrupted attempt left."""
    missing = Task("4" * 32, str(tmp_path / "nope.mcap"), "odometry", {}, 0, str(tmp_path / "r4"), str(store.path))
    outcome = run_task(missing)
    assert outcome.status == "failed" and "nope.mcap: no such file" in (outcome.error or "")
    rec = write_tiny_recording(tmp_path / "tiny.mcap")
    stale = tmp_path / "r5"
    stale.mkdir()
    (stale / ".run.rrd.partial").write_bytes(b"half")
    assert run_task(Task("5" * 32, str(rec), "odometry", {}, 0, str(stale), str(store.path))) == Outcome("succeeded")
    assert not (stale / ".run.rrd.partial").exists()


def test_describe_exit() -> None:
    """Exit codes and signals are told in words."""
    assert describe_exit(2) == "the worker process exited with code 2"
    assert describe_exit(-signal.SIGSEGV) == "the worker process was killed by SIGSEGV"


def test_worker_is_replaced_after_max_jobs(store: Store, tmp_path: Path) -> None:
    """With max_jobs_per_worker=2, jobs 1-2 run in one process and job 3 in a fresh one; all succeed."""
    rec = write_tiny_recording(tmp_path / "tiny.mcap", n=30)
    ex = LocalExecutor(1, max_jobs_per_worker=2)
    ex.start()
    try:
        pids = []
        for k in range(3):
            task = claimed(store, rec, f"{k + 3}" * 32, "odometry", tmp_path)
            thread, out = run_in_thread(ex, task)
            pids.append(pid_of(ex, task.job_id))
            thread.join(60)
            assert out == [Outcome("succeeded")]
        assert pids[0] == pids[1] != pids[2]
    finally:
        ex.close()


def test_service_words_name_the_recording_by_its_file_and_the_topic_map_as_a_field() -> None:
    """A run's error as the service shows it: no server folder before the file name, topic_map as a job field."""
    from slamreplay.api.service.executor import service_words

    msg = service_words("/srv/data/recordings/named/ab12/sim.mcap: truncated at byte 70; pass --topic-map "
                        "/wheel/odom=/odom", "/srv/data/recordings/named/ab12/sim.mcap")
    assert msg.startswith("sim.mcap: truncated at byte 70")
    assert 'topic_map {"/wheel/odom": "/odom"}' in msg and "/srv/data" not in msg
