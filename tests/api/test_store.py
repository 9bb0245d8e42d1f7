"""The job store and settings: queue order, restart recovery (re-queued once), cancellation, env and CLI settings."""

from __future__ import annotations

import sqlite3
from pathlib import Path

import pytest
from pydantic import ValidationError

from slamreplay.api.service.settings import Settings
from slamreplay.api.service.store import RecordingRow, Store

SHA = "a" * 64


def make_store(tmp_path: Path) -> Store:
    store = Store(tmp_path / "jobs.sqlite")
    store.add_recording(RecordingRow(SHA, "x.mcap", 10, [], 0, 0, 0, 0.0))
    return store


def test_database_is_in_wal_mode(tmp_path: Path) -> None:
    """The store switches SQLite to write-ahead logging."""
    make_store(tmp_path)
    with sqlite3.connect(tmp_path / "jobs.sqlite") as conn:
        assert conn.execute("PRAGMA journal_mode").fetchone()[0] == "wal"


def test_jobs_are_claimed_oldest_first(tmp_path: Path) -> None:
    """claim_next hands out queued jobs in submission order, then None."""
    store = make_store(tmp_path)
    for i in range(3):
        store.add_job(f"{i:032x}", SHA, "odometry", {}, i)
    claimed = [store.claim_next() for _ in range(4)]
    assert [j.seed if j else None for j in claimed] == [0, 1, 2, None]
    assert all(j.status == "running" and j.attempts == 1 for j in claimed if j)


def test_job_on_unknown_recording_is_not_stored(tmp_path: Path) -> None:
    """add_job returns None for a recording that is not in the store."""
    store = make_store(tmp_path)
    assert store.add_job("1" * 32, "b" * 64, "odometry", {}, 0) is None
    assert store.list_jobs() == []


def test_running_jobs_are_requeued_once_after_a_restart(tmp_path: Path) -> None:
    """A job cut off by a server stop is re-queued once, and marked interrupted the second time."""
    store = make_store(tmp_path)
    store.add_job("1" * 32, SHA, "odometry", {}, 0)
    store.claim_next()
    assert store.recover_after_restart() == (["1" * 32], [])
    job = store.get_job("1" * 32)
    assert job is not None and job.status == "queued" and "re-queued" in (job.note or "")
    store.claim_next()
    assert store.recover_after_restart() == ([], ["1" * 32])
    job = store.get_job("1" * 32)
    assert job is not None and job.status == "interrupted" and job.attempts == 2
    assert "not re-queued" in (job.error or "")


def test_finish_does_not_overwrite_a_cancel(tmp_path: Path) -> None:
    """A job cancelled while running stays cancelled when its worker reports back."""
    store = make_store(tmp_path)
    store.add_job("1" * 32, SHA, "odometry", {}, 0)
    store.claim_next()
    job, before = store.cancel_job("1" * 32)
    assert before == "running" and job is not None and job.status == "cancelled"
    assert not store.finish_job("1" * 32, "succeeded", None)
    assert store.count_by_status()["cancelled"] == 1


def test_settings_from_environment(tmp_path: Path) -> None:
    """SLAMREPLAY_* variables fill the settings; explicit overrides win; an empty token means none."""
    env = {"SLAMREPLAY_DATA_DIR": str(tmp_path), "SLAMREPLAY_WORKERS": "3", "SLAMREPLAY_TOKEN": "",
           "SLAMREPLAY_MAX_UPLOAD_BYTES": "1000", "SLAMREPLAY_EXECUTOR": "local"}
    s = Settings.from_env(env, workers=5)
    assert (s.data_dir, s.workers, s.token, s.max_upload_bytes) == (tmp_path, 5, None, 1000)
    assert s.db_path == tmp_path.resolve() / "runs" / "jobs.sqlite"


@pytest.mark.parametrize(("name", "value"), [("WORKERS", "0"), ("WORKERS", "many"), ("EXECUTOR", "celery"),
                                             ("MAX_UPLOAD_BYTES", "-1")])
def test_bad_settings_name_the_field(name: str, value: str) -> None:
    """An invalid variable raises a validation error naming its field."""
    with pytest.raises(ValidationError, match=name.lower()):
        Settings.from_env({f"SLAMREPLAY_{name}": value})


@pytest.mark.parametrize(("args", "message"), [(["--workers", "0"], "workers: Input should be greater than or equal"),
                                               (["--data-dir", "/dev/null/x"], "cannot create it")])
def test_serve_refuses_bad_settings(args: list[str], message: str, capsys: pytest.CaptureFixture[str]) -> None:
    """`slamreplay serve` with a bad setting exits 2 with one line saying what is wrong."""
    from slamreplay.api.cli.command import main

    assert main(["serve", *args]) == 2
    err = capsys.readouterr().err
    assert message in err and "Traceback" not in err
