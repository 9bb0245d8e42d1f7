"""Suites and comparisons in the service, and the web page's routes (TestClient, in-thread jobs)."""

from __future__ import annotations

import json
import time
import warnings
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from conftest import write_tiny_recording
from service_helpers import InlineExecutor, wait_for

with warnings.catch_warnings():
    warnings.simplefilter("ignore", UserWarning)
    from fastapi.testclient import TestClient

from slamreplay.api.app import create_app
from slamreplay.api.cli.command import main
from slamreplay.api.service.deps import rrd_key
from slamreplay.api.service.settings import Settings
from slamreplay.api.web.web import COOKIE, session_value

UNKNOWN = "0" * 32


@pytest.fixture(scope="module")
def client(tmp_path_factory: pytest.TempPathFactory) -> Iterator[TestClient]:
    app = create_app(Settings(allowed_hosts=("testserver",),
                              data_dir=tmp_path_factory.mktemp("data"), workers=1), executor=InlineExecutor())
    with TestClient(app) as c:
        yield c


@pytest.fixture(scope="module")
def recordings(client: TestClient, tmp_path_factory: pytest.TempPathFactory) -> tuple[str, str]:
    """(good, drifting): two tiny recordings uploaded, the second with 8x the odometry drift."""
    d = tmp_path_factory.mktemp("recs")
    out = []
    for name, drift in (("good.mcap", 0.05), ("drift.mcap", 0.4)):
        path = write_tiny_recording(d / name, drift=drift)
        out.append(client.post("/recordings", content=path.read_bytes(), params={"filename": name}).json()["id"])
    return out[0], out[1]


def suite_toml(rid: str, seeds: str = "[0, 1]", name: str = "tiny") -> str:
    return f'seeds = {seeds}\n[recordings.{name}]\nid = "{rid}"\n[pipelines.odometry]\n'


def wait_suite(client: TestClient, suite_id: str, timeout_s: float = 60.0) -> dict[str, Any]:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        doc: dict[str, Any] = client.get(f"/suites/{suite_id}").json()
        if doc["progress"]["ended"] == doc["progress"]["cells"]:
            return doc
        time.sleep(0.05)
    raise AssertionError(f"suite {suite_id} did not end within {timeout_s} s")


@pytest.fixture(scope="module")
def two_suites(client: TestClient, recordings: tuple[str, str]) -> tuple[str, str]:
    """The same cell names over the good and the drifting recording: B regresses against A."""
    ids = []
    for rid in recordings:
        r = client.post("/suites", content=suite_toml(rid), headers={"content-type": "application/toml"})
        assert r.status_code == 202, r.text
        ids.append(r.json()["id"])
    for s in ids:
        assert wait_suite(client, s)["progress"]["status"] == "succeeded"
    return ids[0], ids[1]


def test_suite_runs_every_cell_as_a_job(client: TestClient, two_suites: tuple[str, str]) -> None:
    """Two seeds through odometry: two jobs, each with metrics, progress 1."""
    doc = client.get(f"/suites/{two_suites[0]}").json()
    assert doc["progress"] == {"status": "succeeded", "cells": 2, "ended": 2, "counts": {"succeeded": 2},
                               "fraction": 1.0}
    assert [c["seed"] for c in doc["cells"]] == [0, 1]
    assert all(c["pipeline"] == "odometry" and c["variant"] == "default" for c in doc["cells"])
    for c in doc["cells"]:
        job = client.get(f"/jobs/{c['job_id']}").json()
        assert job["status"] == "succeeded" and job["seed"] == c["seed"]
        assert c["metrics"]["ape_rmse_m"] == pytest.approx(job["metrics"]["ape_rmse_m"])
    assert two_suites[0] in [s["id"] for s in client.get("/suites").json()]


def test_suite_as_json(client: TestClient, recordings: tuple[str, str]) -> None:
    """The same structure as JSON works, and names the format."""
    body = {"seeds": [3], "recordings": {"j": {"id": recordings[0]}}, "pipelines": {"odometry": {}}}
    r = client.post("/suites", json=body)
    assert r.status_code == 202, r.text
    doc = wait_suite(client, r.json()["id"])
    assert doc["format"] == "json" and doc["cells"][0]["seed"] == 3 and doc["cells"][0]["status"] == "succeeded"


def test_queued_jobs_with_the_same_inputs_are_reused(tmp_path: Path) -> None:
    """A second suite over the same inputs while the first is queued adds no job."""
    idle = TestClient(create_app(Settings(allowed_hosts=("testserver",),
                                          data_dir=tmp_path, workers=1), executor=InlineExecutor()))
    rid = idle.post("/recordings", content=write_tiny_recording(tmp_path / "t.mcap").read_bytes()).json()["id"]
    first = idle.post("/suites", content=suite_toml(rid)).json()
    second = idle.post("/suites", content=suite_toml(rid)).json()
    assert [c["reused"] for c in first["cells"]] == [False, False]
    assert [c["reused"] for c in second["cells"]] == [True, True]
    assert [c["job_id"] for c in first["cells"]] == [c["job_id"] for c in second["cells"]]
    assert len(idle.get("/jobs").json()) == 2
    assert second["progress"]["status"] == "running" and second["progress"]["counts"] == {"queued": 2}
    r = idle.get("/compare", params={"a": first["id"], "b": second["id"]})
    assert r.status_code == 409 and "still running (0 of 2 cells ended)" in r.json()["detail"]


@pytest.mark.parametrize(("body", "ctype", "expect"), [
    ('seeds = [0]\n[recordings.x]\nid = "{unknown}"\n[pipelines.odometry]\n', "application/toml",
     "suite.toml:3: recordings.x.id: recording 0000000000000000000000000000000000000000000000000000000000000000 "
     "not found; upload it with POST /recordings first"),
    ('[recordings.x]\npath = "/etc/passwd"\n[pipelines.odometry]\n', "application/toml",
     "suite.toml:2: recordings.x.path: the service runs uploaded recordings only"),
    ('[recordings.x]\nid = "{rid}"\n[pipelines.odometry]\nx = 1\n', "application/toml",
     "suite.toml:4: pipelines.odometry.x: unknown key"),
    ('[recordings.x]\nid = "{rid}"\n[pipelines.nope]\n', "application/toml", "suite.toml:3: pipelines.nope"),
    ("seeds = [", "application/toml", "suite.toml: not valid TOML"),
    ("[1, 2]", "application/json", "suite.json: a suite must be a JSON object, got list"),
    ('{"recordings": {"x": {"id": "zz"}}, "pipelines": {"odometry": {}}}', "application/json",
     "suite.json: recordings.x.id: 'zz' is not a recording id"),
])
def test_bad_suites_are_422_naming_the_key(client: TestClient, recordings: tuple[str, str], body: str, ctype: str,
                                           expect: str) -> None:
    """Every validation error of a suite file names the key (and for TOML the line); nothing is queued."""
    before = len(client.get("/jobs", params={"limit": 1000}).json())
    text = body.replace("{unknown}", "0" * 64).replace("{rid}", recordings[0])
    r = client.post("/suites", content=text, headers={"content-type": ctype})
    assert r.status_code == 422, r.text
    assert r.json()["detail"].startswith(expect)
    assert len(client.get("/jobs", params={"limit": 1000}).json()) == before


def test_oversized_and_non_utf8_suites(client: TestClient) -> None:
    r = client.post("/suites", content=b"#" * ((1 << 20) + 1))
    assert r.status_code == 413 and "at most" in r.json()["detail"]
    r = client.post("/suites", content=b"\xff\xfe")
    assert r.status_code == 400 and "not UTF-8" in r.json()["detail"]


def test_compare_suites_finds_the_regression(client: TestClient, two_suites: tuple[str, str]) -> None:
    """8x the drift: robot ATE worse on both seeds, a regression; A against itself: none."""
    doc = client.get("/compare", params={"a": two_suites[0], "b": two_suites[1]}).json()
    assert "tiny/odometry/default: ape_rmse_m" in doc["regressions"]
    ate = next(r for r in doc["results"] if r["metric"] == "ape_rmse_m")
    assert ate["verdict"] == "regression" and ate["b_mean"] > 2 * ate["a_mean"] and len(ate["a"]) == 2
    same = client.get("/compare", params={"a": two_suites[0], "b": two_suites[0]}).json()
    assert same["regressions"] == [] and {r["verdict"] for r in same["results"]} == {"unchanged"}


def test_compare_html_by_accept_or_format(client: TestClient, two_suites: tuple[str, str]) -> None:
    """The report: the regression's row is marked, cells link to job pages and A/B pairs in the viewer."""
    a, b = two_suites
    for kwargs in ({"params": {"a": a, "b": b, "format": "html"}},
                   {"params": {"a": a, "b": b}, "headers": {"accept": "text/html"}}):
        r = client.get("/compare", **kwargs)  # type: ignore[arg-type]
        assert r.status_code == 200 and r.headers["content-type"].startswith("text/html")
        row = next(line for line in r.text.splitlines() if "ape_rmse_m" in line and "<tr" in line)
        assert "class='regression'" in row
        assert "/ui/jobs/" in row and "/viewer/?url=" in row and "%2Fui%2Fshared%2F" in row and "%2Fdiff%2F" in row
    assert client.get("/compare", params={"a": a, "b": b, "format": "json"}).headers["content-type"].startswith(
        "application/json")


def test_compare_jobs_and_errors(client: TestClient, two_suites: tuple[str, str], recordings: tuple[str, str]
                                 ) -> None:
    """Two jobs compare as one cell; unknown and malformed ids 404, nothing in common 422, bad tolerance 422."""
    sa = client.get(f"/suites/{two_suites[0]}").json()["cells"][0]["job_id"]
    sb = client.get(f"/suites/{two_suites[1]}").json()["cells"][0]["job_id"]
    doc = client.get("/compare", params={"a": sa, "b": sb}).json()
    assert any(r.endswith("ape_rmse_m") for r in doc["regressions"])
    r = client.get("/compare", params={"a": UNKNOWN, "b": sb})
    assert r.status_code == 404 and "neither a suite nor a job" in r.json()["detail"]
    r = client.get("/compare", params={"a": "../x", "b": sb})
    assert r.status_code == 404 and "'../x'" in r.json()["detail"]  # a malformed id: 404 naming it
    other = client.post("/suites", content=suite_toml(recordings[0], "[0]", name="elsewhere")).json()["id"]
    wait_suite(client, other)
    r = client.get("/compare", params={"a": two_suites[0], "b": other})
    assert r.status_code == 422 and "no cell in common" in r.json()["detail"]
    r = client.get("/compare", params={"a": sa, "b": sb, "tolerance": "nope=1"})
    assert r.status_code == 422 and "unknown metrics: nope" in r.json()["detail"]
    assert client.get(f"/suites/{UNKNOWN}").status_code == 404


# -- the web page -------------------------------------------------------------------------------


def test_page_lists_recordings_jobs_and_suites(client: TestClient, two_suites: tuple[str, str]) -> None:
    r = client.get("/")
    assert r.status_code == 200 and r.headers["content-type"].startswith("text/html")
    for marker in ('id="upload-form"', 'id="job-form"', 'id="suite-form"', 'id="compare-form"', "good.mcap",
                   f"/ui/suites/{two_suites[0]}", 'src="/static/web.js"'):
        assert marker in r.text
    suite = client.get(f"/ui/suites/{two_suites[0]}")
    assert suite.status_code == 200 and "ape_rmse_m" in suite.text and 'id="suite-compare"' in suite.text
    part = client.get("/ui/part/lists", params={"part": "jobs"})
    assert part.status_code == 200 and 'id="jobs-table"' in part.text


def test_page_upload_job_and_compare(client: TestClient, tmp_path: Path, two_suites: tuple[str, str]) -> None:
    """The forms: upload redirects to the list, a job redirects to its page, which shows metrics and the viewer link."""
    data = write_tiny_recording(tmp_path / "form.mcap", seed=7).read_bytes()
    r = client.post("/ui/recordings", files={"file": ("form.mcap", data)}, follow_redirects=False)
    assert r.status_code == 303 and r.headers["location"].startswith("/?uploaded=")
    rid = r.headers["location"].split("=")[1].split("#")[0]
    r = client.post("/ui/jobs", data={"recording_id": rid, "pipeline": "odometry", "seed": "2", "config": ""},
                    follow_redirects=False)
    assert r.status_code == 303
    job_id = r.headers["location"].rsplit("/", 1)[1]
    assert wait_for(client, job_id)["status"] == "succeeded"
    page = client.get(f"/ui/jobs/{job_id}").text
    assert 'id="metrics-table"' in page and "ape_rmse_m" in page
    key = rrd_key(None, f"/jobs/{job_id}/run.rrd")
    assert f"/viewer/?url=http%3A%2F%2Ftestserver%2Fui%2Fshared%2F{key}%2Fjobs%2F{job_id}%2Frun.rrd" in page
    for url in (f"/ui/jobs/{job_id}/run.rrd", f"/ui/shared/{key}/jobs/{job_id}/run.rrd"):
        rrd = client.get(url)
        assert rrd.status_code == 200 and rrd.content[:4] == b"RRF2"
    report = client.get("/ui/compare", params={"a": two_suites[0], "b": two_suites[1]})
    assert report.status_code == 200 and "class='regression'" in report.text and 'class="top"' in report.text


@pytest.mark.parametrize(("form", "expect"), [
    ({"recording_id": "0" * 64, "pipeline": "odometry", "seed": "0"}, (404, "not found")),
    ({"recording_id": "0" * 64, "pipeline": "odometry", "seed": "x"}, (422, "bad job form")),
    ({"recording_id": "0" * 64, "pipeline": "odometry", "seed": "0", "config": "[1]"}, (422, "JSON object")),
    ({"recording_id": "0" * 64, "pipeline": "nope", "seed": "0"}, (422, "nope")),
])
def test_page_job_form_errors_are_pages(client: TestClient, form: dict[str, str], expect: tuple[int, str]) -> None:
    r = client.post("/ui/jobs", data=form)
    assert r.status_code == expect[0] and 'id="error"' in r.text and expect[1] in r.text


def test_page_upload_and_suite_errors_are_pages(client: TestClient) -> None:
    r = client.post("/ui/recordings", files={"file": ("x.mcap", b"not an mcap at all")})
    assert r.status_code == 415 and 'id="error"' in r.text
    r = client.post("/ui/recordings", content=b"raw")
    assert r.status_code == 400 and "upload form" in r.text
    r = client.post("/ui/suites", data={"suite": "seeds = ["})
    assert r.status_code == 422 and "not valid TOML" in r.text
    assert client.get(f"/ui/jobs/{UNKNOWN}").status_code == 404
    assert client.get(f"/ui/suites/{UNKNOWN}").status_code == 404


def test_viewer_is_served_from_rerun_sdk_files(client: TestClient) -> None:
    """index.html, JS and wasm come from the installed rerun-sdk, with no link to another host."""
    index = client.get("/viewer/")
    assert index.status_code == 200 and "re_viewer.js" in index.text
    assert "fonts.googleapis.com" not in index.text
    assert "connect-src 'self'" in index.headers["content-security-policy"]
    wasm = client.get("/viewer/re_viewer_bg.wasm")
    assert wasm.status_code == 200 and wasm.content[:4] == b"\0asm"
    assert wasm.headers["content-type"] == "application/wasm"
    assert client.get("/viewer/../jobs.sqlite").status_code == 404
    assert client.get("/viewer/secret.txt").status_code == 404


# -- a token -------------------------------------------------------------------------------------


def test_token_page_asks_for_it_and_api_keeps_requiring_it(tmp_path: Path) -> None:
    guarded = TestClient(create_app(Settings(allowed_hosts=("testserver",),
                                             data_dir=tmp_path, token="s3cret"), executor=InlineExecutor()))
    r = guarded.get("/", follow_redirects=False)
    assert r.status_code == 303 and r.headers["location"] == "/login?next=%2F"
    assert "This server needs its token" in guarded.get("/login").text
    assert guarded.get("/viewer/", follow_redirects=False).status_code == 303
    assert guarded.get(f"/ui/jobs/{UNKNOWN}/run.rrd").status_code == 401
    bad = guarded.get(f"/ui/shared/{rrd_key('other', f'/jobs/{UNKNOWN}/run.rrd')}/jobs/{UNKNOWN}/run.rrd")
    assert bad.status_code == 401 and "wrong key" in bad.json()["detail"]
    good = guarded.get(f"/ui/shared/{rrd_key('s3cret', f'/jobs/{UNKNOWN}/run.rrd')}/jobs/{UNKNOWN}/run.rrd")
    assert good.status_code == 404  # the key opens that path only, and there is no such job
    moved = guarded.get(f"/ui/shared/{rrd_key('s3cret', f'/jobs/{UNKNOWN}/run.rrd')}/diff/{UNKNOWN}-{UNKNOWN}.rrd")
    assert moved.status_code == 401
    wrong = guarded.post("/login", data={"token": "nope", "next": "/"}, follow_redirects=False)
    assert wrong.status_code == 401 and 'id="login-error"' in wrong.text and COOKIE not in wrong.cookies
    ok = guarded.post("/login", data={"token": "s3cret", "next": "//evil.example"}, follow_redirects=False)
    assert ok.status_code == 303 and ok.headers["location"] == "/"
    assert ok.cookies[COOKIE] == session_value("s3cret") and "s3cret" not in ok.headers["set-cookie"]
    assert "samesite=strict" in ok.headers["set-cookie"].lower() and "httponly" in ok.headers["set-cookie"].lower()
    guarded.cookies.set(COOKIE, ok.cookies[COOKIE])
    assert guarded.get("/").status_code == 200
    assert guarded.get("/suites").status_code == 200  # the page's session reads through the API (its links)
    assert guarded.post("/suites", content=b"x").status_code == 401  # but changes want the bearer token
    assert guarded.get("/suites", headers={"authorization": "Bearer s3cret"}).status_code == 200
    guarded.cookies.clear()  # some httpx versions keep the response's cookie beside a set() one
    guarded.cookies.set(COOKIE, "forged")
    assert guarded.get("/", follow_redirects=False).status_code == 303


# -- serve --data-dir ----------------------------------------------------------------------------


def test_data_dir_is_created(tmp_path: Path) -> None:
    settings = Settings(data_dir=tmp_path / "new" / "deeper")
    settings.make_dirs()
    assert (tmp_path / "new" / "deeper" / "recordings").is_dir() and settings.runs_dir.is_dir()


def test_serve_data_dir_that_cannot_be_made_exits_2(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    (tmp_path / "file").write_text("x")
    assert main(["serve", "--data-dir", str(tmp_path / "file" / "sub")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "cannot create it" in err[0]


def test_suite_json_body_shape(client: TestClient, two_suites: tuple[str, str]) -> None:
    """GET /suites/{id}: the documented fields, links to the page and to compare."""
    doc = client.get(f"/suites/{two_suites[0]}").json()
    assert set(doc) == {"id", "name", "format", "created_at", "progress", "cells", "links"}
    assert doc["name"] == "suite" and doc["links"]["page"] == f"/ui/suites/{two_suites[0]}"
    assert json.dumps(doc)
