"""A suite's history in the service: versions from the runs' manifests, changes marked, JSON and page."""

from __future__ import annotations

import json
import warnings
from collections.abc import Iterator
from pathlib import Path

import pytest
from conftest import write_tiny_recording
from service_helpers import InlineExecutor
from test_suites_routes import suite_toml, wait_suite

with warnings.catch_warnings():
    warnings.simplefilter("ignore", UserWarning)
    from fastapi.testclient import TestClient

from slamreplay.api.app import create_app
from slamreplay.api.settings import Settings

OLD = "a" * 40


@pytest.fixture
def client(tmp_path: Path) -> Iterator[TestClient]:
    app = create_app(Settings(allowed_hosts=("testserver",), data_dir=tmp_path / "data", workers=1),
                     executor=InlineExecutor())
    with TestClient(app) as c:
        yield c


def test_history_of_a_suite_over_two_versions(client: TestClient, tmp_path: Path) -> None:
    """A suite run on an older version (its manifests say so) with a worse APE, then again now: two versions, the
    APE an improvement at the second and nothing else; the page draws it and links both suites."""
    rec = write_tiny_recording(tmp_path / "tiny.mcap", n=40)
    rid = client.post("/recordings", content=rec.read_bytes(), params={"filename": "tiny.mcap"}).json()["id"]
    first = client.post("/suites", content=suite_toml(rid, "[0, 1, 2]", "tiny").replace("seeds", "name = 'nightly'\n"
                                                                                         "seeds", 1)).json()
    doc = wait_suite(client, first["id"])
    for cell in doc["cells"]:  # as if an older code version had run it, with APE twice as large
        run = Path(client.app.state.jobs.run_dir(cell["job_id"]))  # type: ignore[attr-defined]
        manifest = json.loads((run / "manifest.json").read_text())
        manifest["slamreplay"]["git_commit"] = OLD
        (run / "manifest.json").write_text(json.dumps(manifest))
        metrics = json.loads((run / "metrics.json").read_text())
        metrics["metrics"]["ape_rmse_m"]["value"] *= 2
        (run / "metrics.json").write_text(json.dumps(metrics))
    second = client.post("/suites", content=suite_toml(rid, "[0, 1, 2]", "tiny").replace(
        "seeds", "name = 'nightly'\nseeds", 1)).json()
    wait_suite(client, second["id"])
    r = client.get("/history/suites/nightly")
    assert r.status_code == 200, r.text
    h = r.json()
    assert len(h["versions"]) == 2 and h["versions"][0]["code_version"] == OLD
    assert h["versions"][0]["suites"] == [first["id"]] and h["versions"][1]["suites"] == [second["id"]]
    assert [(c["metric"], c["verdict"], c["index"]) for c in h["changes"]] == [("ape_rmse_m", "improvement", 1)]
    ape = next(s for s in h["series"] if s["metric"] == "ape_rmse_m")
    assert [p["n"] for p in ape["points"]] == [3, 3] and ape["points"][0]["mean"] == pytest.approx(
        2 * ape["points"][1]["mean"])
    page = client.get("/ui/history/nightly")
    assert page.status_code == 200 and "stroke-dasharray" in page.text and "ape_rmse_m" in page.text
    assert f"/ui/compare?a={first['id']}&amp;b={second['id']}" in page.text
    assert 'href="/ui/history/nightly"' in client.get(f"/ui/suites/{second['id']}").text
    assert client.get("/history/suites/nope").status_code == 404
    assert client.get("/ui/history/nope").status_code == 404
    spaced = client.post("/suites", content=suite_toml(rid, "[0]", "tiny").replace(
        "seeds", "name = 'nightly odometry/v2'\nseeds", 1)).json()  # a name is any string the suite file gives
    wait_suite(client, spaced["id"])
    assert 'href="/ui/history/nightly%20odometry/v2"' in client.get(f"/ui/suites/{spaced['id']}").text
    assert client.get("/ui/history/nightly%20odometry/v2").status_code == 200
    assert client.get("/history/suites/nightly%20odometry/v2").json()["versions"][0]["suites"] == [spaced["id"]]
