"""POST /recordings/record/NAME: recordings made on the server by the importers that may run there, one route
per importer from the registry; GET /importers says which and why not."""

from __future__ import annotations

import warnings
from pathlib import Path

import pytest
from service_helpers import InlineExecutor

with warnings.catch_warnings():
    warnings.simplefilter("ignore", UserWarning)  # StarletteDeprecationWarning: it asks for httpx2; httpx works
    from fastapi.testclient import TestClient

from slamreplay.api.app import create_app
from slamreplay.api.service.settings import Settings
from slamreplay.recorder.sim.landmarks import LandmarkSimConfig, simulate_landmarks
from slamreplay.replay.runs.run import sha256_file


@pytest.fixture
def client(tmp_path: Path) -> TestClient:
    return TestClient(create_app(Settings(allowed_hosts=("testserver",),
                                          data_dir=tmp_path / "data", workers=1), executor=InlineExecutor()))


def test_importers_lists_every_importer_and_why_the_file_readers_are_not_offered(client: TestClient) -> None:
    rows = {r["name"]: r for r in client.get("/importers").json()}
    assert {"sim-landmarks", "sim-seabed", "sim-corridor", "images", "mrclam", "ros2", "victoria-park"} <= set(rows)
    assert rows["sim-landmarks"]["offered"] and rows["sim-landmarks"]["route"] == "/recordings/record/sim-landmarks"
    options = {o["name"]: o for o in rows["sim-landmarks"]["options"]}
    assert options["duration_s"]["option"] == "--duration-s" and options["seed"]["type"] == "int"
    assert "out" not in options
    assert "texture" not in {o["name"] for o in rows["sim-seabed"]["options"]}  # a file on the server
    assert not rows["ros2"]["offered"] and "reads bag from the machine it runs on" in rows["ros2"]["why_not"]
    paths = client.get("/openapi.json").json()["paths"]
    assert "/recordings/record/sim-landmarks" in paths and "/recordings/record/ros2" not in paths


def test_a_simulation_made_on_the_server_equals_the_cli_one(client: TestClient, tmp_path: Path) -> None:
    """The same options and seed give the file `slamreplay record` gives (same sha256, the recording's id); the
    second request stores nothing new (200); a job runs on it."""
    r = client.post("/recordings/record/sim-landmarks", json={"duration_s": 20, "seed": 3})
    assert r.status_code == 201, r.text
    rec = r.json()
    simulate_landmarks(tmp_path / "cli.mcap", LandmarkSimConfig(duration_s=20.0), seed=3)
    assert rec["id"] == sha256_file(tmp_path / "cli.mcap")
    assert rec["filename"].startswith("sim-landmarks-duration_s20") and rec["message_count"] > 0
    again = client.post("/recordings/record/sim-landmarks", json={"duration_s": 20, "seed": 3})
    assert again.status_code == 200 and again.json()["id"] == rec["id"]
    job = client.post("/jobs", json={"recording_id": rec["id"], "pipeline": "odometry"})
    assert job.status_code == 202
    assert not [p.name for p in (tmp_path / "data" / "recordings").iterdir() if p.name.startswith(".")]


@pytest.mark.parametrize(("body", "status", "detail"), [
    ({"duration_s": "long"}, 422, "duration_s"),  # the body's type check
    ({"texture": "/etc"}, 422, "texture"),  # a file option is not offered: an unknown key
    ({"out": "/tmp/x.mcap"}, 422, "out"),
    ({"duration_s": -5}, 422, "duration_s must be > 0"),  # the simulator's own check, one line
    ({"sensor_range_m": True}, 422, "sensor_range_m"),  # JSON true is not the number 1 (the fuzzer's case)
    ({"seed": 2.5}, 422, "seed"),
    ({"seed": -1}, 422, "seed"),  # numpy refuses a negative seed: a 500 the fuzzer found
])
def test_bad_options_are_422_and_store_nothing(client: TestClient, body: dict, status: int, detail: str) -> None:  # type: ignore[type-arg]
    name = "sim-seabed" if "texture" in body else "sim-landmarks"
    r = client.post(f"/recordings/record/{name}", json=body)
    assert r.status_code == status, r.text
    assert detail in r.text
    assert client.get("/recordings").json() == []


def test_an_importer_that_reads_server_files_has_no_route(client: TestClient) -> None:
    assert client.post("/recordings/record/mrclam", json={}).status_code in (404, 405)
