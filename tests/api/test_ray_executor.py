"""RayExecutor against a local Ray instance: same metrics as local, progress, cancel, crash, limits, service.

Run with `make test-ray` (it installs the ray extra); skipped when Ray is not installed.
"""

from __future__ import annotations

import json
import warnings
from collections.abc import Iterator
from pathlib import Path

import pytest

ray = pytest.importorskip("ray", reason="the ray extra is not installed: `pip install -e '.[ray]'` or `make test-ray`")

import standin_jobs  # noqa: E402
from conftest import write_tiny_recording  # noqa: E402
from service_helpers import claimed, make_store, run_all, wait_for  # noqa: E402
from standin_jobs import standin_job  # noqa: E402

from slamreplay.api.service.executor import Outcome, Task, run_task  # noqa: E402
from slamreplay.api.service.limits import JobLimits  # noqa: E402
from slamreplay.api.service.ray_executor import RayExecutor  # noqa: E402
from slamreplay.api.service.settings import Settings  # noqa: E402
from slamreplay.api.service.store import Store  # noqa: E402

with warnings.catch_warnings():
    warnings.simplefilter("ignore", UserWarning)
    from fastapi.testclient import TestClient

from slamreplay.api.app import create_app  # noqa: E402

pytestmark = pytest.mark.ray
MEMORY_MIB = 900  # a Ray worker holds about 270 MiB after importing the pipelines


@pytest.fixture(scope="module", autouse=True)
def local_ray() -> Iterator[None]:
    """One local Ray instance (2 CPUs) for the module; executors built here join it and leave it running."""
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    ray.cloudpickle.register_pickle_by_value(standin_jobs)  # workers cannot import tests/api
    yield
    ray.shutdown()


@pytest.fixture(scope="module")
def executor() -> Iterator[RayExecutor]:
    ex = RayExecutor(2, JobLimits(memory_mib=MEMORY_MIB, wall_s=30.0), job=standin_job)
    ex.start()
    yield ex
    ex.close()


@pytest.fixture
def store(tmp_path: Path) -> Store:
    return make_store(tmp_path / "jobs.sqlite")


@pytest.fixture(scope="module")
def recording(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_tiny_recording(tmp_path_factory.mktemp("rec") / "tiny.mcap")


def test_same_metrics_as_local_and_progress(executor: RayExecutor, store: Store, recording: Path,
                                            tmp_path: Path) -> None:
    """A Ray job gives the metrics of the same job run locally, and its progress reaches the store."""
    task = claimed(store, recording, "1" * 32, "dslam", tmp_path, seed=7)
    assert executor.run(task) == Outcome("succeeded")
    job = store.get_job(task.job_id)
    assert job is not None and job.progress == 1.0  # forwarded from the sink by the server side
    local = Task("2" * 32, str(recording), "dslam", {}, 7, str(tmp_path / "local"), str(store.path))
    assert run_task(local, lambda f: None) == Outcome("succeeded")
    ours, theirs = (json.loads((Path(d) / "metrics.json").read_text()) for d in (task.run_dir, local.run_dir))
    assert ours == theirs


def test_cancel_then_the_next_job_runs(executor: RayExecutor, store: Store, recording: Path, tmp_path: Path) -> None:
    """cancel() ends a running job as cancelled; the executor goes on."""
    sleeper = claimed(store, recording, "3" * 32, "sleep", tmp_path)
    assert run_all(executor, [sleeper], cancel_after_s=1.5) == [Outcome("cancelled", "cancelled by request")]
    after = claimed(store, recording, "4" * 32, "odometry", tmp_path)
    assert executor.run(after) == Outcome("succeeded")


def test_crash_fails_alone(executor: RayExecutor, store: Store, recording: Path, tmp_path: Path) -> None:
    """A job that kills its worker fails with the cause; the job beside it succeeds."""
    crash = claimed(store, recording, "5" * 32, "crash", tmp_path)
    good = claimed(store, recording, "6" * 32, "odometry", tmp_path)
    crashed, ok = run_all(executor, [crash, good])
    assert crashed.status == "failed" and "Ray worker process running this job died" in (crashed.error or "")
    assert ok == Outcome("succeeded")


def test_memory_limit_fails_alone(executor: RayExecutor, store: Store, recording: Path, tmp_path: Path) -> None:
    """A job past its memory limit fails with it; the job beside it succeeds."""
    hog = claimed(store, recording, "7" * 32, "hog", tmp_path)
    good = claimed(store, recording, "8" * 32, "odometry", tmp_path)
    assert run_all(executor, [hog, good]) == [
        Outcome("failed", f"job exceeded its memory limit of {MEMORY_MIB} MiB"), Outcome("succeeded")]


def test_wall_time_limit(store: Store, recording: Path, tmp_path: Path) -> None:
    """Past its wall time a job fails with the limit, also one stuck in a native call."""
    ex = RayExecutor(2, JobLimits(wall_s=1.0), job=standin_job, warm_up=False)
    ex.start()
    try:
        sleeper = claimed(store, recording, "9" * 32, "sleep", tmp_path)
        stuck = claimed(store, recording, "a" * 32, "stuck", tmp_path)
        assert run_all(ex, [sleeper, stuck]) == [Outcome("failed", "job exceeded its wall-time limit of 1 s")] * 2
    finally:
        ex.close()


def test_service_with_the_ray_executor(tmp_path: Path, recording: Path) -> None:
    """`--executor ray` with a file:// storage URL: upload, submit, the job succeeds and its run is served."""
    data_dir, shared = tmp_path / "data", tmp_path / "shared"
    data_dir.mkdir()
    settings = Settings(allowed_hosts=("testserver",),
                        data_dir=data_dir, workers=2, executor="ray", storage_url=shared.as_uri())
    with TestClient(create_app(settings)) as c:
        rid = c.post("/recordings", content=recording.read_bytes()).json()["id"]
        jid = c.post("/jobs", json={"recording_id": rid, "pipeline": "odometry"}).json()["id"]
        job = wait_for(c, jid, timeout_s=120.0)
        assert job["status"] == "succeeded", job["error"]
        assert job["progress"] == 1.0 and job["metrics"]
        assert c.get(f"/jobs/{jid}/rrd").status_code == 200
    assert (shared / "recordings" / f"{rid}.mcap").is_file() and (shared / "runs" / jid / "run.rrd").is_file()
