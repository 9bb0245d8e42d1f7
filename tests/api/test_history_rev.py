"""Run a suite on another commit from its history page: the cells run that commit's code, and the history lists it."""

from __future__ import annotations

import json
import subprocess
import sys
import warnings
from collections.abc import Iterator
from pathlib import Path

import pytest
from conftest import REPO, write_tiny_recording
from service_helpers import InlineExecutor
from test_suites_routes import suite_toml, wait_suite

with warnings.catch_warnings():
    warnings.simplefilter("ignore", UserWarning)
    from fastapi.testclient import TestClient

from slamreplay.api.app import create_app
from slamreplay.api.service.executor import Task, run_task
from slamreplay.api.service.settings import Settings
from slamreplay.replay.runs import revisions

NIGHTLY = "name = 'nightly'\nseeds"


def _client(tmp_path: Path) -> TestClient:
    app = create_app(Settings(allowed_hosts=("testserver",), data_dir=tmp_path / "data", workers=1),
                     executor=InlineExecutor())
    return TestClient(app)


def _nightly(client: TestClient, tmp_path: Path) -> tuple[str, str]:
    """Upload a tiny recording and run the suite 'nightly' (one cell) on the service's own code: (recording, suite)."""
    rec = write_tiny_recording(tmp_path / "tiny.mcap", n=40)
    rid = client.post("/recordings", content=rec.read_bytes(), params={"filename": "tiny.mcap"}).json()["id"]
    first = client.post("/suites", content=suite_toml(rid, "[0]").replace("seeds", NIGHTLY, 1)).json()
    assert wait_suite(client, first["id"])["progress"]["status"] == "succeeded"
    return rid, first["id"]


@pytest.fixture
def clone(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[str]:
    """The service runs from a fresh clone of the repository (cwd); revisions run with this interpreter. Its sha."""
    repo = tmp_path / "clone"
    subprocess.run(["git", "clone", "-q", "--no-hardlinks", str(REPO), str(repo)], check=True)
    monkeypatch.chdir(repo)
    monkeypatch.setenv("SLAMREPLAY_REV_PYTHON", sys.executable)  # no venv built: still the worktree's code
    # a commit that is not the service's own code version: in a clean checkout the service runs HEAD's code, and a
    # suite "on HEAD" would rightly reuse its runs instead of running that revision
    subprocess.run(["git", "-c", "user.name=t", "-c", "user.email=t@t", "commit", "-q", "--allow-empty", "-m",
                    "a commit the service does not run"], cwd=repo, check=True)
    yield subprocess.run(["git", "rev-parse", "HEAD"], cwd=repo, capture_output=True, text=True,
                         check=True).stdout.strip()


def test_run_a_suite_on_a_commit(tmp_path: Path, clone: str) -> None:
    """POST runs on HEAD: the new suite's runs come from HEAD's worktree (their manifests say HEAD's sha) and the
    history lists that version; the page's form does the same (reusing those runs); an unknown revision is a 422
    that queues nothing."""
    with _client(tmp_path) as client:
        _rid, first = _nightly(client, tmp_path)
        page = client.get("/ui/history/nightly")
        assert page.status_code == 200 and 'action="/ui/history/nightly/runs"' in page.text
        r = client.post("/history/suites/nightly/runs", json={"rev": "HEAD"})
        assert r.status_code == 202, r.text
        doc = wait_suite(client, r.json()["id"], timeout_s=120)
        assert doc["name"] == "nightly" and doc["progress"]["status"] == "succeeded", doc
        for cell in doc["cells"]:
            manifest = json.loads((tmp_path / "data" / "runs" / cell["job_id"] / "manifest.json").read_text())
            assert manifest["slamreplay"]["git_commit"] == clone
            assert client.app.state.jobs.store.get_job(cell["job_id"]).rev == clone  # type: ignore[attr-defined]
        assert (tmp_path / "data" / "cache" / "revs" / clone / "ready").is_file()
        history = client.get("/history/suites/nightly").json()
        at_head = [v for v in history["versions"] if v["code_version"] == clone]
        assert at_head and r.json()["id"] in at_head[0]["suites"]
        assert history["versions"][0]["suites"] == [first]  # the service's own code, before

        before = (len(client.get("/suites").json()), len(client.get("/jobs").json()))
        bad = client.post("/ui/history/nightly/runs", data={"rev": "no-such-branch"})
        assert bad.status_code == 422 and "unknown revision &#39;no-such-branch&#39;: give" in bad.text
        assert client.post("/history/suites/nightly/runs", json={"rev": "no-such-branch"}).status_code == 422
        assert (len(client.get("/suites").json()), len(client.get("/jobs").json())) == before
        assert client.post("/history/suites/nope/runs", json={"rev": "HEAD"}).status_code == 404

        again = client.post("/ui/history/nightly/runs", data={"rev": clone[:12]}, follow_redirects=False)
        assert again.status_code == 303 and again.headers["location"].startswith("/ui/suites/")
        cells = wait_suite(client, again.headers["location"].rsplit("/", 1)[1])["cells"]
        assert [c["reused"] for c in cells] == [True] and cells[0]["job_id"] == doc["cells"][0]["job_id"]


def test_not_in_a_git_checkout(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A service that does not run from a git checkout shows no form and answers 409 with one line; a job of a
    revision that cannot be prepared there fails with one line."""
    outside = tmp_path / "outside"
    outside.mkdir()
    monkeypatch.chdir(outside)
    monkeypatch.setenv("GIT_CEILING_DIRECTORIES", str(tmp_path))
    monkeypatch.setattr(revisions, "SOURCE_ROOT", outside)
    with _client(tmp_path) as client:
        _nightly(client, tmp_path)
        page = client.get("/ui/history/nightly")
        assert page.status_code == 200 and "history-run" not in page.text
        r = client.post("/history/suites/nightly/runs", json={"rev": "HEAD"})
        assert r.status_code == 409 and "does not run from a git checkout" in r.json()["detail"]
        assert client.post("/ui/history/nightly/runs", data={"rev": "HEAD"}).status_code == 409
        assert len(client.get("/suites").json()) == 1
    rec = tmp_path / "tiny.mcap"
    out = run_task(Task("j" * 32, str(rec), "odometry", {}, 0, str(tmp_path / "run"), "", rev="a" * 40,
                        rev_cache=str(tmp_path / "cache")))
    assert out.status == "failed" and out.error is not None and out.error.startswith("not in a git checkout")
    assert "\n" not in out.error
