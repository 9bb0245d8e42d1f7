"""The service under faults: a full disk (507, nothing stored, still serving), uploads cut off, what a
killed server left behind, and the recover route's account of what it kept and lost."""

from __future__ import annotations

import asyncio
import errno
import sqlite3
import subprocess
import threading
import warnings
from collections.abc import AsyncIterator, Iterator
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import pytest
from conftest import write_tiny_recording
from service_helpers import InlineExecutor, wait_for

with warnings.catch_warnings():
    warnings.simplefilter("ignore", UserWarning)
    from fastapi.testclient import TestClient

import slamreplay.api.service.recordings as api_recordings
from slamreplay.api.app import create_app
from slamreplay.api.service.errors import ApiError, is_disk_full
from slamreplay.api.service.executor import Outcome, Task
from slamreplay.api.service.settings import Settings
from slamreplay.recorder import GroundTruthPose, Recorder
from slamreplay.recorder.recover import recover


@pytest.fixture(scope="module")
def recording(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_tiny_recording(tmp_path_factory.mktemp("rec") / "tiny.mcap", n=60)


@pytest.fixture
def served(tmp_path: Path) -> Iterator[tuple[TestClient, Path]]:
    """A running app over a fresh data directory, and that directory."""
    data = tmp_path / "data"
    data.mkdir()
    with TestClient(create_app(Settings(allowed_hosts=("testserver",),
                                        data_dir=data, workers=1), executor=InlineExecutor())) as c:
        yield c, data


class _FullDisk:
    """A file whose writes fail with ENOSPC once ``room`` bytes have been written."""

    def __init__(self, f: Any, room: int) -> None:
        self.f, self.room = f, room

    def write(self, b: bytes) -> int:
        if len(b) > self.room:
            raise OSError(errno.ENOSPC, "No space left on device")
        self.room -= len(b)
        return int(self.f.write(b))

    def __enter__(self) -> _FullDisk:
        return self

    def __exit__(self, *exc: object) -> None:
        self.f.close()


def leftovers(data: Path) -> list[str]:
    """Files in recordings/ that no recording row names: temporary uploads and recoveries."""
    return sorted(p.name for p in (data / "recordings").iterdir() if p.name.startswith("."))


def test_upload_onto_a_full_disk_is_507_and_the_service_keeps_serving(
        served: tuple[TestClient, Path], recording: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """ENOSPC while an upload streams to disk: 507 naming the cause, the partial file removed, nothing listed;
    other routes answer meanwhile, and the same upload succeeds once there is room."""
    client, data = served
    real_open = open
    monkeypatch.setattr(api_recordings, "open", lambda p, mode="r": _FullDisk(real_open(p, mode), 4096),
                        raising=False)
    body = recording.read_bytes()
    assert len(body) > 4096
    r = client.post("/recordings", content=body, params={"filename": "tiny.mcap"})
    assert r.status_code == 507, r.text
    detail = r.json()["detail"]
    assert "no space left on the device" in detail and "tiny.mcap" in detail and "nothing was stored" in detail
    assert client.get("/healthz").status_code == 200
    assert client.get("/recordings").json() == [] and leftovers(data) == []
    monkeypatch.undo()
    r = client.post("/recordings", content=body, params={"filename": "tiny.mcap"})
    assert r.status_code == 201, r.text
    assert [x["id"] for x in client.get("/recordings").json()] == [r.json()["id"]]


def test_database_on_a_full_disk_is_507(served: tuple[TestClient, Path], recording: Path,
                                        monkeypatch: pytest.MonkeyPatch) -> None:
    """SQLITE_FULL while queueing a job: 507, no job stored; listing jobs still works; a later submit succeeds."""
    client, _ = served
    rid = client.post("/recordings", content=recording.read_bytes()).json()["id"]
    store = client.app.state.jobs.store  # type: ignore[attr-defined]

    def full(*args: Any, **kwargs: Any) -> None:
        raise sqlite3.OperationalError("database or disk is full")

    monkeypatch.setattr(store, "add_job", full)
    r = client.post("/jobs", json={"recording_id": rid, "pipeline": "odometry"})
    assert r.status_code == 507 and "POST /jobs" in r.json()["detail"], r.text
    assert client.get("/jobs").json() == []
    monkeypatch.undo()
    r = client.post("/jobs", json={"recording_id": rid, "pipeline": "odometry"})
    assert r.status_code == 202
    assert wait_for(client, r.json()["id"])["status"] == "succeeded"


def test_other_os_errors_stay_internal_errors(served: tuple[TestClient, Path], monkeypatch: pytest.MonkeyPatch) -> None:
    """Only a full disk becomes 507: a permission error is still a 500 (a bug or a broken set-up, not the user's)."""
    client, _ = served
    recordings = client.app.state.recordings  # type: ignore[attr-defined]

    def denied() -> list[Any]:
        raise PermissionError(errno.EACCES, "Permission denied")

    monkeypatch.setattr(recordings.store, "list_recordings", denied)
    with TestClient(client.app, raise_server_exceptions=False) as c:
        assert c.get("/recordings").status_code == 500


@pytest.mark.parametrize(("exc", "full"), [
    (OSError(errno.ENOSPC, "No space left on device"), True),
    (OSError(errno.EDQUOT, "Disk quota exceeded"), True),
    (sqlite3.OperationalError("database or disk is full"), True),
    (OSError(errno.EIO, "I/O error"), False),
    (sqlite3.OperationalError("database is locked"), False),
    (ValueError("x"), False),
])
def test_is_disk_full(exc: BaseException, full: bool) -> None:
    """ENOSPC, EDQUOT and SQLITE_FULL, also as the cause of another error; nothing else."""
    assert is_disk_full(exc) is full
    try:
        raise RuntimeError("wrapped") from exc
    except RuntimeError as wrapped:
        assert is_disk_full(wrapped) is full


def test_dropped_upload_leaves_nothing(tmp_path: Path, recording: Path) -> None:
    """A client that goes away mid-upload: no partial file stays, no recording is listed."""
    from starlette.requests import ClientDisconnect

    settings = Settings(data_dir=tmp_path, workers=1)
    settings.make_dirs()
    service = api_recordings.RecordingService(settings, create_app(settings, InlineExecutor()).state.jobs.store)
    body = recording.read_bytes()

    async def cut() -> AsyncIterator[bytes]:
        yield body[:1000]
        yield body[1000:2000]
        raise ClientDisconnect()

    with pytest.raises(ClientDisconnect):
        asyncio.run(service.upload(cut(), "tiny.mcap", len(body), False))
    assert leftovers(tmp_path) == [] and service.store.list_recordings() == []


def test_start_up_removes_what_a_killed_server_left(tmp_path: Path, recording: Path) -> None:
    """Temporary uploads and recoveries cut off by a kill are removed at start-up; recordings stay."""
    settings = Settings(allowed_hosts=("testserver",), data_dir=tmp_path, workers=1)
    with TestClient(create_app(settings, executor=InlineExecutor())) as c:
        rid = c.post("/recordings", content=recording.read_bytes()).json()["id"]
    rec_dir = tmp_path / "recordings"
    (rec_dir / ".upload-0123.partial").write_bytes(recording.read_bytes()[:500])
    (rec_dir / ".recover-4567.mcap").write_bytes(b"\x89MCAP0\r\n")
    with TestClient(create_app(settings, executor=InlineExecutor())) as c:
        assert leftovers(tmp_path) == []
        assert [r["id"] for r in c.get("/recordings").json()] == [rid]
        assert c.get(f"/recordings/{rid}/download").content == recording.read_bytes()


def test_recover_route_reports_kept_lost_and_dropped_ranges(served: tuple[TestClient, Path], tmp_path: Path) -> None:
    """POST /recordings/{id}/recover gives the same account as the CLI: kept, lost, each dropped byte range."""
    client, _ = served
    src = tmp_path / "big.mcap"
    with Recorder(src, source={}) as rec:
        for k in range(30000):  # several 1 MiB chunks
            rec.write("/ground_truth/pose", GroundTruthPose(1000 + k, float(k), 0.0, 0.0))
    cut = src.read_bytes()[: int(src.stat().st_size * 0.6)]
    (tmp_path / "cut.mcap").write_bytes(cut)
    expected = recover(tmp_path / "cut.mcap", tmp_path / "fixed.mcap")
    r = client.post("/recordings", content=cut, params={"filename": "cut.mcap"})
    assert r.status_code == 422
    out = client.post(r.json()["recover"]["url"])
    assert out.status_code == 201, out.text
    got = out.json()["recovered"]
    assert got["messages"] == expected.messages == out.json()["message_count"] > 0
    assert (got["lost"], got["lost_exact"], got["expected"]) == (expected.lost, expected.lost_exact,
                                                                  expected.expected)
    assert [(d["start"], d["end"], d["reason"]) for d in got["dropped"]] == list(expected.dropped)
    assert got["dropped"] and all(d["bytes"] == d["end"] - d["start"] > 0 for d in got["dropped"])
    assert got["dropped"][-1]["end"] == len(cut)


def _can_mount_tmpfs(where: Path) -> bool:
    where.mkdir()
    ok = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=3m", "tmpfs", str(where)], capture_output=True,
                        check=False).returncode == 0
    return ok


def test_real_full_disk_tmpfs(tmp_path: Path) -> None:
    """On a 3 MiB tmpfs (when this process may mount one): uploads fill it, the one that does not fit is 507,
    every listed recording downloads whole, and deleting one makes room for the next upload."""
    mnt = tmp_path / "small"
    if not _can_mount_tmpfs(mnt):
        pytest.skip("cannot mount a tmpfs here (needs root); the simulated ENOSPC tests cover the same paths")
    try:
        settings = Settings(allowed_hosts=("testserver",), data_dir=mnt, workers=1)
        with TestClient(create_app(settings, executor=InlineExecutor())) as c:
            stored: dict[str, bytes] = {}
            answer = None
            for seed in range(40):
                body = write_tiny_recording(tmp_path / f"r{seed}.mcap", n=600, seed=seed).read_bytes()
                answer = c.post("/recordings", content=body)
                if answer.status_code != 201:
                    break
                stored[answer.json()["id"]] = body
            assert answer is not None and answer.status_code == 507, answer.text
            assert "no space left on the device" in answer.json()["detail"]
            assert len(stored) >= 2
            assert c.get("/healthz").status_code == 200
            listed = [r["id"] for r in c.get("/recordings").json()]
            assert sorted(listed) == sorted(stored) and leftovers(mnt) == []
            for rid, body in stored.items():
                assert c.get(f"/recordings/{rid}/download").content == body
            assert c.delete(f"/recordings/{listed[0]}").status_code == 204
            small = write_tiny_recording(tmp_path / "small.mcap", n=50, seed=99).read_bytes()
            assert c.post("/recordings", content=small).status_code == 201
    finally:
        subprocess.run(["umount", "-l", str(mnt)], check=False)  # lazy: connections may still be open


def test_api_error_507_is_an_api_error() -> None:
    """The 507 error goes through the one error handler like every service error."""
    from slamreplay.api.service.errors import disk_full_error

    err = disk_full_error("doing x")
    assert isinstance(err, ApiError) and err.status == 507 and "while doing x" in err.detail


class CountingExecutor:
    """Four slots whose job only counts its runs: the queue's contract under concurrency, in milliseconds."""

    slots = 4

    def __init__(self) -> None:
        self.runs: list[str] = []
        self._lock = threading.Lock()

    def start(self) -> None:
        """Nothing to start."""

    def run(self, task: Task) -> Outcome:
        with self._lock:
            self.runs.append(task.job_id)
        return Outcome("succeeded")

    def cancel(self, job_id: str) -> None:
        """Runs end at once."""

    def close(self) -> None:
        """Nothing to stop."""


def test_concurrent_uploads_and_jobs_none_lost_none_run_twice(tmp_path: Path) -> None:
    """30 different recordings uploaded at once and 300 jobs submitted from 30 threads, 4 scheduler threads:
    every upload stored and listed, every job run exactly once (attempts 1) and succeeded."""
    bodies = [write_tiny_recording(tmp_path / f"r{k}.mcap", n=12, seed=k).read_bytes() for k in range(30)]
    ex = CountingExecutor()
    data = tmp_path / "data"
    data.mkdir()
    with TestClient(create_app(Settings(allowed_hosts=("testserver",), data_dir=data, workers=4), executor=ex)) as c:
        with ThreadPoolExecutor(30) as pool:
            codes = list(pool.map(lambda b: c.post("/recordings", content=b).status_code, bodies))
        assert codes == [201] * 30
        rids = sorted(r["id"] for r in c.get("/recordings").json())
        assert len(rids) == 30 and leftovers(data) == []

        def submit(i: int) -> str:
            job_id: str = c.post("/jobs", json={"recording_id": rids[i % 30], "pipeline": "odometry",
                                                "seed": i}).json()["id"]
            return job_id

        with ThreadPoolExecutor(30) as pool:
            ids = list(pool.map(submit, range(300)))
        ends = [wait_for(c, j) for j in ids]
    assert {e["status"] for e in ends} == {"succeeded"} and {e["attempts"] for e in ends} == {1}
    assert sorted(ex.runs) == sorted(ids)  # each exactly once
