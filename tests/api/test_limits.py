"""Per-job limits: a job past its memory or wall-time limit fails alone with the limit in its error."""

from __future__ import annotations

import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
from conftest import write_tiny_recording
from service_helpers import claimed, make_store, run_all
from standin_jobs import SLOW_EXIT_LIMIT_S, standin_job

from slamreplay.api.service.app import make_executor
from slamreplay.api.service.executor import LocalExecutor, Outcome, Task, run_limited
from slamreplay.api.service.limits import EXIT_MEMORY, EXIT_WALL, JobLimits, Watchdog, rss_mib
from slamreplay.api.service.settings import Settings
from slamreplay.api.service.store import Store

MEMORY_MIB = 450  # a worker holds about 200 MiB after its imports; a tiny replay adds about 30


@pytest.fixture
def store(tmp_path: Path) -> Store:
    return make_store(tmp_path / "jobs.sqlite")


@pytest.fixture(scope="module")
def two_limited_workers() -> Iterator[LocalExecutor]:
    # wall_s is generous: on a loaded host the hog takes 10 s or more to fill its memory
    ex = LocalExecutor(2, JobLimits(memory_mib=MEMORY_MIB, wall_s=120.0), job=standin_job)
    ex.start()
    yield ex
    ex.close()


def test_memory_hog_fails_alone(two_limited_workers: LocalExecutor, store: Store, tmp_path: Path) -> None:
    """A job past the memory limit fails with it; a job beside it succeeds, and so does the next one."""
    rec = write_tiny_recording(tmp_path / "tiny.mcap")
    hog = claimed(store, rec, "1" * 32, "hog", tmp_path)
    good = claimed(store, rec, "2" * 32, "odometry", tmp_path)
    assert run_all(two_limited_workers, [hog, good]) == [
        Outcome("failed", f"job exceeded its memory limit of {MEMORY_MIB} MiB"), Outcome("succeeded")]
    assert (tmp_path / good.job_id / "metrics.json").is_file()
    after = claimed(store, rec, "3" * 32, "odometry", tmp_path)
    assert run_all(two_limited_workers, [after]) == [Outcome("succeeded")]  # the hog's worker was replaced


def test_a_worker_slow_to_exit_after_a_limit_gets_no_next_job(store: Store, tmp_path: Path) -> None:
    """A worker ends after a limit failure; if it has not ended within the executor's wait (a loaded host), it is
    replaced anyway: the next job runs in a fresh process, not in one about to exit (CI: 'exited with code 0')."""
    # a generous limit: the job after it runs in a fresh worker whose start a loaded host can make slow
    ex = LocalExecutor(1, JobLimits(wall_s=SLOW_EXIT_LIMIT_S), job=standin_job)
    ex.start()
    try:
        rec = write_tiny_recording(tmp_path / "tiny.mcap")
        slow = claimed(store, rec, "6" * 32, "slow-exit", tmp_path)
        after = claimed(store, rec, "7" * 32, "odometry", tmp_path)
        assert run_all(ex, [slow]) == [Outcome("failed", "job exceeded its wall-time limit of 60 s")]
        assert run_all(ex, [after]) == [Outcome("succeeded")]
    finally:
        ex.close()


def test_wall_time_limit_and_stuck_job(store: Store, tmp_path: Path) -> None:
    """A job past its wall time fails with the limit, even one stuck in a native call (ended with its process)."""
    ex = LocalExecutor(2, JobLimits(wall_s=1.0), job=standin_job)
    ex.start()
    try:
        rec = write_tiny_recording(tmp_path / "tiny.mcap")
        sleeper = claimed(store, rec, "4" * 32, "sleep", tmp_path)
        stuck = claimed(store, rec, "5" * 32, "stuck", tmp_path)
        tic = time.monotonic()
        assert run_all(ex, [sleeper, stuck]) == [Outcome("failed", "job exceeded its wall-time limit of 1 s")] * 2
        assert time.monotonic() - tic < 30
    finally:
        ex.close()


def test_watchdog_in_process() -> None:
    """run_limited stops a job in this thread at its limit and leaves a job under it alone."""
    task = Task("6" * 32, "unused.mcap", "sleep", {}, 0, "unused", "unused.sqlite")
    tic = time.monotonic()
    assert run_limited(standin_job, task, JobLimits(wall_s=0.3)) == Outcome("failed",
                                                                         "job exceeded its wall-time limit of 0.3 s")
    assert time.monotonic() - tic < 2
    quick = run_limited(lambda t, r: Outcome("succeeded"), task, JobLimits(memory_mib=1 << 20, wall_s=60))
    assert quick == Outcome("succeeded")
    with Watchdog(JobLimits()) as dog:  # no limits: no thread
        pass
    assert dog.error is None


def test_limit_messages_and_exit_codes() -> None:
    """Limit errors say which limit and its size; the watchdog's exit codes map back to them."""
    limits = JobLimits(memory_mib=512, wall_s=2.5)
    assert limits.exit_error(EXIT_MEMORY) == "job exceeded its memory limit of 512 MiB"
    assert limits.exit_error(EXIT_WALL) == "job exceeded its wall-time limit of 2.5 s"
    assert limits.exit_error(1) is None and JobLimits().exit_error(EXIT_MEMORY) is None
    assert limits.is_limit_error("job exceeded its memory limit of 512 MiB") and not limits.is_limit_error(None)
    rss = rss_mib()
    assert rss is None or 10 < rss < 1 << 20


def test_settings_from_env_reach_the_executor() -> None:
    """SLAMREPLAY_JOB_* set the local executor's limits; SLAMREPLAY_EXECUTOR/RAY_ADDRESS/STORAGE_URL are read."""
    env = {"SLAMREPLAY_JOB_MEMORY_MIB": "512", "SLAMREPLAY_JOB_TIMEOUT_S": "90", "SLAMREPLAY_WORKERS": "3",
           "SLAMREPLAY_RAY_ADDRESS": "ray://head:10001", "SLAMREPLAY_STORAGE_URL": "s3://bucket/slam"}
    settings = Settings.from_env(env)
    assert (settings.ray_address, settings.storage_url) == ("ray://head:10001", "s3://bucket/slam")
    ex = make_executor(settings)
    assert isinstance(ex, LocalExecutor) and ex.slots == 3 and ex.limits == JobLimits(512, 90.0)
    assert Settings.from_env({"SLAMREPLAY_EXECUTOR": "ray"}).executor == "ray"
    with pytest.raises(ValueError, match="job_memory_mib"):
        Settings.from_env({"SLAMREPLAY_JOB_MEMORY_MIB": "10"})


def test_ray_executor_without_ray_says_how_to_install(monkeypatch: pytest.MonkeyPatch) -> None:
    """--executor ray without the extra fails at start-up with the install command."""
    from slamreplay.api.service.ray_executor import RayMissingError

    monkeypatch.setitem(sys.modules, "ray", None)  # import ray -> ImportError
    with pytest.raises(RayMissingError, match=r"the ray executor needs the ray extra: `pip install -e '\.\[ray\]'`"):
        make_executor(Settings(executor="ray"))
