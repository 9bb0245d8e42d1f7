"""Bounded work on hostile recordings through the service, as through the CLI (tests/fuzz/test_bomb_file.py): a
2 MB file of valid-CRC decompression-bomb chunks is refused in one line, at upload or by its job, within the
same time bound, and leaves no run behind that looks finished."""

from __future__ import annotations

import time
import warnings
from pathlib import Path

from service_helpers import InlineExecutor, wait_for

with warnings.catch_warnings():
    warnings.simplefilter("ignore", DeprecationWarning)
    from fastapi.testclient import TestClient

from slamreplay.api.app import create_app
from slamreplay.api.service.settings import Settings
from tests.fuzz.bombs import bomb_file

SECONDS = 30  # as the CLI's bound, on a loaded 2-core machine


def test_a_bomb_recording_is_refused_in_one_line(tmp_path: Path) -> None:
    bomb = tmp_path / "bomb.mcap"
    assert bomb_file(bomb, chunks=300, records=1_000_000) < 3_000_000  # 25 GB and 300 million messages unpacked
    app = create_app(Settings(allowed_hosts=("testserver",), data_dir=tmp_path / "data", workers=1),
                     executor=InlineExecutor())
    with TestClient(app) as client:
        t0 = time.perf_counter()
        up = client.post("/recordings", content=bomb.read_bytes(), params={"filename": "bomb.mcap"})
        if up.status_code >= 400:
            detail = up.json()["detail"]
        else:
            r = client.post("/jobs", json={"recording_id": up.json()["id"], "pipeline": "odometry"})
            assert r.status_code == 202, r.text
            job = wait_for(client, r.json()["id"], timeout_s=10 * SECONDS)
            assert job["status"] == "failed"
            detail = job["error"]
            run = tmp_path / "data" / "runs" / job["id"]
            assert not (run / "metrics.json").exists() and not (run / "run.rrd").exists()
        elapsed = time.perf_counter() - t0
    assert "decompression bomb" in detail and "\n" not in detail, detail
    assert elapsed < SECONDS, elapsed
