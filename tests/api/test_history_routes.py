"""A suite's history in the service: versions from the runs' manifests, changes marked, JSON and page."""

from __future__ import annotations

import json
import subprocess
import warnings
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from conftest import REPO, write_tiny_recording
from service_helpers import InlineExecutor
from test_suites_routes import suite_toml, wait_suite

with warnings.catch_warnings():
    warnings.simplefilter("ignore", UserWarning)
    from fastapi.testclient import TestClient

from slamreplay.api.app import create_app
from slamreplay.api.service.settings import Settings

STRANGER = "f" * 40  # a commit the server's checkout does not have


def ancestor(n: int) -> str:
    """The sha of HEAD~n of the checkout the service (and this test) runs from."""
    return subprocess.run(["git", "rev-parse", f"HEAD~{n}"], cwd=REPO, capture_output=True, text=True,
                          check=True).stdout.strip()


def as_if_run_on(client: TestClient, doc: dict[str, Any], version: str, ape_scale: float = 1.0) -> None:
    """Rewrite a suite's runs as if ``version`` had made them, with their APE times ``ape_scale``."""
    for cell in doc["cells"]:
        run = Path(client.app.state.jobs.run_dir(cell["job_id"]))  # type: ignore[attr-defined]
        manifest = json.loads((run / "manifest.json").read_text())
        manifest["slamreplay"]["git_commit"] = version
        (run / "manifest.json").write_text(json.dumps(manifest))
        metrics = json.loads((run / "metrics.json").read_text())
        metrics["metrics"]["ape_rmse_m"]["value"] *= ape_scale
        (run / "metrics.json").write_text(json.dumps(metrics))


def nightly(rid: str, seeds: str = "[0, 1, 2]") -> str:
    return suite_toml(rid, seeds, "tiny").replace("seeds", "name = 'nightly'\nseeds", 1)


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
    as_if_run_on(client, wait_suite(client, first["id"]), ancestor(1), 2.0)  # an older commit, APE twice as large
    second = client.post("/suites", content=suite_toml(rid, "[0, 1, 2]", "tiny").replace(
        "seeds", "name = 'nightly'\nseeds", 1)).json()
    wait_suite(client, second["id"])
    r = client.get("/history/suites/nightly")
    assert r.status_code == 200, r.text
    h = r.json()
    assert len(h["versions"]) == 2 and h["versions"][0]["code_version"] == ancestor(1)
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


def test_backfilled_version_in_git_order(client: TestClient, tmp_path: Path) -> None:
    """HEAD~1 runs first, HEAD~2 is backfilled after it with twice the APE, then a commit the checkout lacks: the
    JSON and the page read HEAD~2, HEAD~1, the stranger (last, by date, said so), and the APE's change is an
    improvement judged from HEAD~2 to HEAD~1."""
    rec = write_tiny_recording(tmp_path / "tiny.mcap", n=40)
    rid = client.post("/recordings", content=rec.read_bytes(), params={"filename": "tiny.mcap"}).json()["id"]
    newer, older = ancestor(1), ancestor(2)
    ids = []
    for version, scale in ((newer, 1.0), (older, 2.0), (STRANGER, 1.0)):
        doc = wait_suite(client, client.post("/suites", content=nightly(rid)).json()["id"])
        assert not any(c["reused"] for c in doc["cells"])  # each an earlier suite's runs rewritten: never reused
        as_if_run_on(client, doc, version, scale)
        ids.append(doc["id"])
    h = client.get("/history/suites/nightly").json()
    assert [v["code_version"] for v in h["versions"]] == [older, newer, STRANGER]
    assert [v["suites"] for v in h["versions"]] == [[ids[1]], [ids[0]], [ids[2]]]
    assert [v["placed"] for v in h["versions"]][:2] == ["git", "git"]
    assert "not a commit of the repository" in h["versions"][2]["placed"] and "come last" in h["order"]
    ape = [(c["previous"], c["commit"], c["verdict"]) for c in h["changes"] if c["metric"] == "ape_rmse_m"]
    assert ape[0] == (older, newer, "improvement")
    page = client.get("/ui/history/nightly").text
    table = page[page.index('id="history-versions"'):]
    rows = [table.index(f"<code>{v[:10]}</code>") for v in (older, newer, STRANGER)]
    assert rows == sorted(rows) and "placed by date, after the commits git orders" in page
    assert f"/ui/compare?a={ids[1]}&amp;b={ids[0]}" in page  # the older version's suite against the newer's
