"""The data directory's lock: one holder, its name in the refusal, stale locks taken over, workers holding it,
and no app start (so no re-queue of running jobs) without it."""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import textwrap
import time
import warnings
from pathlib import Path

import pytest
from service_helpers import SHA, InlineExecutor, make_store
from standin_jobs import standin_job

with warnings.catch_warnings():
    warnings.simplefilter("ignore", UserWarning)  # StarletteDeprecationWarning: it asks for httpx2; httpx works
    from fastapi.testclient import TestClient

from slamreplay.api.app import create_app
from slamreplay.api.service.datalock import LOCK_NAME, DataDirInUseError, DataDirLock, Owner
from slamreplay.api.service.executor import LocalExecutor
from slamreplay.api.service.settings import Settings

# A process that takes the lock of argv[1], writes argv[2] as its owner, says so and sleeps.
HOLDER = textwrap.dedent("""
    import fcntl, os, sys, time
    fd = os.open(os.path.join(sys.argv[1], "slamreplay.lock"), os.O_RDWR | os.O_CREAT, 0o644)
    fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    os.ftruncate(fd, 0)
    os.pwrite(fd, sys.argv[2].encode(), 0)
    print("held", flush=True)
    time.sleep(60)
""")


def hold(data_dir: Path, owner: dict[str, object] | None = None) -> subprocess.Popen[str]:
    """Another process holding ``data_dir``'s lock, naming ``owner`` (itself when None)."""
    proc = subprocess.Popen([sys.executable, "-c", HOLDER, str(data_dir), json.dumps(owner) if owner else "{}"],
                            stdout=subprocess.PIPE, text=True)
    assert proc.stdout is not None and proc.stdout.readline().strip() == "held"
    return proc


def test_owner_is_written_and_a_second_holder_refused(tmp_path: Path) -> None:
    """The holder's pid, host, address and start time are in the file; a second lock, even in the same process,
    is refused on one line naming them; after a release the next owner takes it and rewrites the file."""
    first = DataDirLock(tmp_path)
    first.acquire()
    first.set_address("http://127.0.0.1:8123")
    written = json.loads((tmp_path / LOCK_NAME).read_text())
    assert written["pid"] == os.getpid() and written["address"] == "http://127.0.0.1:8123" and written["started"]
    with pytest.raises(DataDirInUseError, match=rf"in use by the server pid {os.getpid()} at http://127.0.0.1:8123 "
                                                r"\(started .*\); stop it or pass another --data-dir") as err:
        DataDirLock(tmp_path).acquire()
    assert "\n" not in str(err.value)
    assert first.acquire().address == "http://127.0.0.1:8123"  # held already: a no-op
    first.release()
    second = DataDirLock(tmp_path)
    second.acquire()
    assert json.loads((tmp_path / LOCK_NAME).read_text())["address"] is None  # the new owner's content
    second.release()


def test_live_holder_in_another_process_is_refused_at_once(tmp_path: Path) -> None:
    """A live server holding the lock is named at once (no waiting for it)."""
    proc = hold(tmp_path, {"pid": 0, "host": "elsewhere", "address": "http://10.0.0.5:8000", "started": "T"})
    try:
        t0 = time.monotonic()
        with pytest.raises(DataDirInUseError, match=r"pid 0 on host elsewhere at http://10.0.0.5:8000 \(started T\)"):
            DataDirLock(tmp_path).acquire(wait_s=5.0)
        assert time.monotonic() - t0 < 1.0
    finally:
        proc.kill()
        proc.wait()


def test_lock_of_a_killed_server_is_taken_over(tmp_path: Path) -> None:
    """kill -9 of the holder frees the lock (the kernel drops it); the next owner rewrites the file."""
    proc = hold(tmp_path, {"pid": 1234567, "host": "h", "address": "http://127.0.0.1:1", "started": "T"})
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    lock = DataDirLock(tmp_path)
    owner = lock.acquire()
    assert owner.pid == os.getpid()
    assert Owner.parse((tmp_path / LOCK_NAME).read_text()) == owner
    lock.release()


def test_gone_server_whose_workers_hold_the_lock_is_waited_for_then_named(tmp_path: Path) -> None:
    """A holder naming a server of this machine that is gone (its workers still run) is waited for up to
    ``wait_s``, then refused with a message saying worker processes hold the lock."""
    gone = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    proc = hold(tmp_path, {"pid": int(gone.stdout), "host": socket.gethostname(), "address": None, "started": "T"})
    try:
        t0 = time.monotonic()
        with pytest.raises(DataDirInUseError, match=r"still locked by worker processes of the server pid \d+, which "
                                                    r"has ended \(waited 0.5 s\): they hold .*slamreplay.lock"):
            DataDirLock(tmp_path).acquire(wait_s=0.5)
        assert 0.5 <= time.monotonic() - t0 < 2.0
    finally:
        proc.kill()
        proc.wait()


def test_local_workers_keep_the_lock_after_the_server_lets_go(tmp_path: Path) -> None:
    """Workers of a LocalExecutor share the locked descriptor: with the server's own descriptor closed (as at
    its death) the directory stays locked until the workers have ended."""
    lock = DataDirLock(tmp_path)
    lock.acquire()
    ex = LocalExecutor(1, job=standin_job)
    ex.share_fd(lock.fd)
    ex.start()
    try:
        lock.release()
        with pytest.raises(DataDirInUseError, match=f"pid {os.getpid()}"):
            DataDirLock(tmp_path).acquire(wait_s=0)
    finally:
        ex.close()
    again = DataDirLock(tmp_path)
    again.acquire(wait_s=0)
    again.release()


def test_app_never_requeues_jobs_of_a_server_holding_the_directory(tmp_path: Path) -> None:
    """An app created by create_app (tests, embedding) starts only with the lock: while another server holds the
    directory its start fails naming it and that server's running job stays running (attempts 1); once the
    lock is free, the start re-queues it."""
    settings = Settings(allowed_hosts=("testserver",), data_dir=tmp_path, workers=1)
    settings.make_dirs()
    store = make_store(settings.db_path)
    store.add_job("1" * 32, SHA, "odometry", {}, 0)
    assert store.claim_next() is not None  # running under "the other server"
    other = DataDirLock(tmp_path)
    other.acquire()
    app = create_app(settings, executor=InlineExecutor())
    with pytest.raises(DataDirInUseError, match=f"pid {os.getpid()}"), TestClient(app):
        pass
    with pytest.raises(DataDirInUseError):
        app.state.jobs.start()  # the scheduler cannot start without it either
    job = store.get_job("1" * 32)
    assert job is not None and (job.status, job.attempts, job.note) == ("running", 1, None)
    other.release()
    with TestClient(create_app(settings, executor=InlineExecutor())):
        job = store.get_job("1" * 32)
        assert job is not None and job.note is not None and "re-queued" in job.note
    again = DataDirLock(tmp_path)
    again.acquire(wait_s=0)  # the app let go at its stop
    again.release()
