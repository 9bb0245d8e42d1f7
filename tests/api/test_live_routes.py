"""/recordings/live: a live Foxglove WebSocket stream recorded on the server, listed while it grows, stopped,
stored like an upload; refused unless the operator allows it."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
import warnings
from collections.abc import Iterator
from pathlib import Path

import pytest
from conftest import REPO
from patience import deadline as give_up_at
from service_helpers import InlineExecutor

with warnings.catch_warnings():
    warnings.simplefilter("ignore", UserWarning)  # StarletteDeprecationWarning: it asks for httpx2; httpx works
    from fastapi.testclient import TestClient

from slamreplay.api.app import create_app
from slamreplay.api.service.settings import Settings
from slamreplay.recorder.sim.landmarks import LandmarkSimConfig, simulate_landmarks
from slamreplay.replay.engine.reader import RecordingReader

pytest.importorskip("foxglove", reason="the Foxglove SDK (foxglove-sdk, in the dev extra) serves the test stream")
PEER = Path(__file__).parents[1] / "recorder" / "live_peer.py"


def _client(tmp_path: Path, allow: bool) -> TestClient:
    return TestClient(create_app(Settings(allowed_hosts=("testserver",), data_dir=tmp_path / "data", workers=1,
                                          allow_live_recording=allow), executor=InlineExecutor()))


@pytest.fixture
def robot(tmp_path: Path) -> Iterator[str]:
    """A Foxglove SDK server publishing 30 s of sim-landmarks at 5x (6 s); its URL."""
    sim = tmp_path / "sim.mcap"
    simulate_landmarks(sim, LandmarkSimConfig(duration_s=30.0), seed=1)
    port_file = tmp_path / "port"
    proc = subprocess.Popen([sys.executable, str(PEER), str(sim), "--port-file", str(port_file), "--sent-file",
                             str(tmp_path / "sent"), "--speed", "5"])
    try:
        deadline = time.monotonic() + 20
        while not port_file.exists() and time.monotonic() < deadline and proc.poll() is None:
            time.sleep(0.02)
        yield f"ws://127.0.0.1:{port_file.read_text()}"
    finally:
        proc.kill()
        proc.wait()


def test_live_recording_is_refused_unless_the_operator_allows_it(tmp_path: Path) -> None:
    """403 naming SLAMREPLAY_ALLOW_LIVE_RECORDING: the server would connect to any URL a client names."""
    r = _client(tmp_path, allow=False).post("/recordings/live", json={"url": "ws://127.0.0.1:8765"})
    assert r.status_code == 403 and "SLAMREPLAY_ALLOW_LIVE_RECORDING=true" in r.json()["detail"]


def test_live_recording_starts_grows_stops_and_is_stored_like_an_upload(tmp_path: Path, robot: str) -> None:
    """POST starts it (201 once it records), GET lists it with its counts growing, stop stores the file."""
    with _client(tmp_path, allow=True) as client:
        r = client.post("/recordings/live", json={"url": robot, "topics": ["/odom", "/landmarks/*", "/ground_truth/*"]})
        assert r.status_code == 201, r.text
        live = r.json()
        assert live["state"] == "recording" and live["links"]["stop"] == f"/recordings/live/{live['id']}/stop"
        deadline = time.monotonic() + 20
        while True:
            listed = client.get("/recordings/live").json()
            assert [x["id"] for x in listed] == [live["id"]]
            if listed[0]["messages"] >= 200 or time.monotonic() > deadline:
                break
            time.sleep(0.1)
        row = listed[0]
        assert row["messages"] >= 200 and row["connected"] and row["bytes"] > 0
        assert {t["topic"] for t in row["topics"]} == {"/odom", "/landmarks/range_bearing", "/ground_truth/pose",
                                                       "/ground_truth/landmarks"}
        stopped = client.post(f"/recordings/live/{live['id']}/stop").json()
        assert stopped["state"] == "done" and stopped["end_reason"] == "stopped", stopped
        rec = stopped["recording"]
        assert rec["message_count"] == stopped["messages"] >= row["messages"]
        assert client.get(f"/recordings/{rec['id']}").status_code == 200
        stored = tmp_path / "data" / "recordings" / f"{rec['id']}.mcap"
        assert sum(1 for _ in RecordingReader(stored).messages()) == rec["message_count"]
        assert not list((tmp_path / "data" / "recordings").glob(".live-*"))  # its folder is gone
        assert client.get(f"/recordings/live/{live['id']}").json()["state"] == "done"


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@pytest.mark.parametrize(("url", "expected"), [("http://robot:8765", "is not a WebSocket URL"),
                                               ("ws://127.0.0.1:{free}", "cannot connect to ws://127.0.0.1:")])
def test_live_recording_that_cannot_start_answers_422_with_the_reason(tmp_path: Path, url: str,
                                                                      expected: str) -> None:
    """A URL that is not ws://, or no server there: 422 with the one-line reason, nothing listed."""
    client = _client(tmp_path, allow=True)
    r = client.post("/recordings/live", json={"url": url.format(free=_free_port())})
    assert r.status_code == 422 and expected in r.json()["detail"], r.text
    assert client.get("/recordings/live").json() == []


def test_a_live_recording_of_a_killed_server_is_salvaged_when_it_starts_again(tmp_path: Path, robot: str) -> None:
    """kill -9 of `slamreplay serve` while it records a live stream: started again, it salvages the .partial into a
    recording like any upload, every message written out before the kill in it, listed as done."""
    sys.path.insert(0, str(REPO / "benchmarks"))
    import crash_suite_service as cs

    data = tmp_path / "serve-data"
    with cs.server(data, tmp_path / "serve.log", workers=1, env={"SLAMREPLAY_ALLOW_LIVE_RECORDING": "true"}) as (
            proc, client):
        r = client.post("/recordings/live", json={"url": robot})
        assert r.status_code == 201, r.text
        task_id = r.json()["id"]
        deadline = give_up_at(20)
        while (counted := client.get(f"/recordings/live/{task_id}").json()["messages"]) < 200:
            assert time.monotonic() < deadline, "the live recording did not grow"
            time.sleep(0.1)
        time.sleep(1.5)  # the chunk in progress is written out every second: what was counted is on disk
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait()
    folder = data / "recordings" / f".live-{task_id}"
    assert (folder / "live.mcap.partial").exists() and not (folder / "live.mcap").exists()
    with cs.server(data, tmp_path / "serve2.log", workers=1) as (_, client):
        listed = client.get("/recordings/live").json()
        assert [(t["id"], t["state"], t["url"]) for t in listed] == [(task_id, "done", robot)], listed
        task = listed[0]
        assert task["end_reason"] == "the server stopped while recording: salvaged at its restart"
        assert any(line.startswith("recovered ") for line in task["lines"]), task["lines"]
        rec = task["recording"]
        assert rec["message_count"] == task["messages"] >= counted >= 200
        assert client.get(f"/recordings/{rec['id']}").status_code == 200
    stored = data / "recordings" / f"{rec['id']}.mcap"
    assert sum(1 for _ in RecordingReader(stored).messages()) == rec["message_count"]
    assert not list((data / "recordings").glob(".live-*"))  # salvaged and stored: its folder is gone


def test_a_live_recording_left_with_nothing_to_salvage_is_listed_failed_with_the_reason(tmp_path: Path) -> None:
    """A killed server's live folder whose .partial holds no message: listed as failed, saying why; folder gone."""
    folder = tmp_path / "data" / "recordings" / ".live-0123456789ab"
    folder.mkdir(parents=True)
    (folder / "task.json").write_text('{"url": "ws://robot:8765", "started_at": "2026-01-02T03:04:05+00:00"}')
    (folder / "live.mcap.partial").write_bytes(b"")
    with _client(tmp_path, allow=False) as client:
        listed = client.get("/recordings/live").json()
    assert [(t["id"], t["state"], t["url"], t["recording"]) for t in listed] == [
        ("0123456789ab", "failed", "ws://robot:8765", None)]
    assert listed[0]["error"].startswith("the server stopped while recording; live.mcap.partial cannot be salvaged")
    assert "is empty" in listed[0]["error"] and listed[0]["started_at"].startswith("2026-01-02T03:04:05")
    assert not folder.exists()
