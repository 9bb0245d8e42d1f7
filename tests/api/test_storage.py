"""Storage by location: paths, file:// and fsspec URLs (memory:// here); jobs through a storage URL."""

from __future__ import annotations

import json
import time
import warnings
from collections.abc import Iterator
from pathlib import Path

import pytest
from conftest import write_tiny_recording
from service_helpers import InlineExecutor, wait_for

from slamreplay.api.service import storage
from slamreplay.api.service.executor import Outcome, Task, run_task

with warnings.catch_warnings():
    warnings.simplefilter("ignore", UserWarning)
    from fastapi.testclient import TestClient

from slamreplay.api.app import create_app
from slamreplay.api.service.settings import Settings

fsspec = pytest.importorskip("fsspec", reason="fsspec comes with the dev and ray extras: pip install -e '.[dev]'")


@pytest.fixture
def memory_root() -> Iterator[str]:
    """A fresh prefix in fsspec's in-process memory filesystem, removed afterwards."""
    root = f"memory://slamreplay-{time.monotonic_ns()}"
    yield root
    storage.remove_dir(root)


def test_locations_are_told_apart() -> None:
    """Plain paths and file:// URLs are local and used in place; other schemes are not."""
    assert storage.is_local("/srv/slam/a.mcap") and storage.is_local("runs/x") and storage.is_local("file:///a/b")
    assert not storage.is_local("s3://bucket/a.mcap") and not storage.is_local("memory://x")
    assert storage.local_path("file:///srv/a%20b.mcap") == Path("/srv/a b.mcap")
    assert storage.join("s3://bucket/slam/", "runs", "j") == "s3://bucket/slam/runs/j"
    assert storage.join("/srv/slam", "runs", "j") == "/srv/slam/runs/j"


def test_memory_round_trip(tmp_path: Path, memory_root: str) -> None:
    """Files and directories go to a memory:// URL and come back the same."""
    src = tmp_path / "run"
    (src / "sub").mkdir(parents=True)
    (src / "metrics.json").write_text('{"a": 1}')
    (src / "sub" / "x.bin").write_bytes(b"\x00\x01" * 1000)
    url = storage.join(memory_root, "runs", "r1")
    storage.put_dir(src, url)
    assert storage.list_files(url) == ["metrics.json", "sub/x.bin"]
    assert storage.exists(storage.join(url, "metrics.json")) and not storage.exists(storage.join(url, "nope"))
    back = tmp_path / "back"
    storage.get_dir(url, back)
    assert (back / "metrics.json").read_text() == '{"a": 1}'
    assert (back / "sub" / "x.bin").read_bytes() == b"\x00\x01" * 1000
    with pytest.raises(storage.StorageError, match="could not read memory://"):
        storage.get_file(storage.join(memory_root, "missing.mcap"), tmp_path / "m")
    assert storage.list_files(storage.join(memory_root, "nothing")) == []


def test_unknown_scheme_is_a_storage_error(tmp_path: Path) -> None:
    """A URL with no fsspec filesystem fails with the URL named."""
    with pytest.raises(storage.StorageError, match="nosuchscheme://x/a.mcap"):
        storage.exists("nosuchscheme://x/a.mcap")


def test_run_task_on_remote_locations(tmp_path: Path, memory_root: str) -> None:
    """A job reads a memory:// recording through a local copy and writes its run back, and
    gives the same metrics as the same job on local paths."""
    rec = write_tiny_recording(tmp_path / "tiny.mcap")
    remote_rec = storage.join(memory_root, "recordings", "tiny.mcap")
    storage.put_file(rec, remote_rec)
    remote_run = storage.join(memory_root, "runs", "7" * 32)
    seen: list[float] = []
    assert run_task(Task("7" * 32, remote_rec, "odometry", {}, 3, remote_run, "unused"), seen.append) == Outcome(
        "succeeded")
    assert seen and seen[-1] == 1.0
    assert {"run.rrd", "metrics.json", "manifest.json", "log.txt"} <= set(storage.list_files(remote_run))
    assert run_task(Task("8" * 32, str(rec), "odometry", {}, 3, str(tmp_path / "local"), "unused"),
                    lambda f: None) == Outcome("succeeded")
    fetched = tmp_path / "fetched"
    storage.get_dir(remote_run, fetched)
    metrics = json.loads((fetched / "metrics.json").read_text())
    assert metrics == json.loads((tmp_path / "local" / "metrics.json").read_text())
    missing = run_task(Task("9" * 32, storage.join(memory_root, "gone.mcap"), "odometry", {}, 0,
                            storage.join(memory_root, "runs", "9"), "unused"), lambda f: None)
    assert missing.status == "failed" and (missing.error or "").startswith("storage: could not read memory://")


def test_service_with_a_storage_url(tmp_path: Path, memory_root: str) -> None:
    """With SLAMREPLAY_STORAGE_URL, a job runs on the stored copy and its run is served from runs/ afterwards."""
    data_dir = tmp_path / "data"
    data_dir.mkdir()
    rec = write_tiny_recording(tmp_path / "tiny.mcap")
    app = create_app(Settings(allowed_hosts=("testserver",),
                              data_dir=data_dir, storage_url=memory_root), executor=InlineExecutor())
    with TestClient(app) as c:
        rid = c.post("/recordings", content=rec.read_bytes()).json()["id"]
        jid = c.post("/jobs", json={"recording_id": rid, "pipeline": "odometry", "seed": 1}).json()["id"]
        job = wait_for(c, jid)
        assert job["status"] == "succeeded", job
        assert job["metrics"] and c.get(f"/jobs/{jid}/metrics").status_code == 200
        assert job["progress"] == 1.0
    assert storage.exists(storage.join(memory_root, "recordings", f"{rid}.mcap"))
    assert "run.rrd" in storage.list_files(storage.join(memory_root, "runs", jid))
    assert (data_dir / "runs" / jid / "run.rrd").is_file()
