"""The HTTP contract: every route, its happy path and every bad-input path (TestClient, in-thread jobs)."""

from __future__ import annotations

import warnings
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from conftest import write_tiny_recording
from service_helpers import InlineExecutor, wait_for

with warnings.catch_warnings():
    warnings.simplefilter("ignore", UserWarning)  # StarletteDeprecationWarning: it asks for httpx2; httpx works
    from fastapi.testclient import TestClient

from slamreplay.api.app import create_app
from slamreplay.api.service.settings import Settings

UNKNOWN_SHA = "0" * 64
UNKNOWN_JOB = "0" * 32


@pytest.fixture(scope="module")
def recording(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A tiny valid recording for the odometry pipeline."""
    return write_tiny_recording(tmp_path_factory.mktemp("rec") / "tiny.mcap")


@pytest.fixture(scope="module")
def client(tmp_path_factory: pytest.TempPathFactory) -> Iterator[TestClient]:
    """A running app (scheduler on) over a fresh data directory."""
    app = create_app(Settings(allowed_hosts=("testserver",),
                              data_dir=tmp_path_factory.mktemp("data"), workers=1), executor=InlineExecutor())
    with TestClient(app) as c:
        yield c


@pytest.fixture
def idle(tmp_path: Path) -> TestClient:
    """An app whose scheduler never starts (no lifespan): submitted jobs stay queued."""
    return TestClient(create_app(Settings(allowed_hosts=("testserver",),
                                          data_dir=tmp_path, workers=1), executor=InlineExecutor()))


def upload(client: TestClient, data: bytes, **params: Any) -> Any:
    return client.post("/recordings", content=data, params=params)


@pytest.fixture(scope="module")
def two_jobs(client: TestClient, recording: Path) -> tuple[str, str, str]:
    """(recording id, job A, job B): the same recording through odometry with seeds 0 and 1, both succeeded."""
    rid = upload(client, recording.read_bytes(), filename="tiny.mcap").json()["id"]
    ids = [client.post("/jobs", json={"recording_id": rid, "pipeline": "odometry", "seed": s}).json()["id"]
           for s in (0, 1)]
    for job_id in ids:
        assert wait_for(client, job_id)["status"] == "succeeded"
    return rid, ids[0], ids[1]


# -- service -------------------------------------------------------------------------------------


def test_healthz(client: TestClient) -> None:
    """/healthz answers ok with the version."""
    r = client.get("/healthz")
    assert r.status_code == 200 and r.json()["status"] == "ok"


def test_prometheus_metrics(client: TestClient, two_jobs: tuple[str, str, str]) -> None:
    """/metrics has jobs by status, the queue length and a duration histogram in Prometheus text format."""
    r = client.get("/metrics")
    assert r.status_code == 200 and r.headers["content-type"].startswith("text/plain")
    text = r.text
    assert 'slamreplay_jobs{status="succeeded"}' in text and "slamreplay_queue_length 0" in text
    assert 'slamreplay_job_duration_seconds_count{status="succeeded"}' in text
    assert "# TYPE slamreplay_job_duration_seconds histogram" in text


# -- recordings ----------------------------------------------------------------------------------


def test_upload_answers_topics_counts_and_span(client: TestClient, recording: Path) -> None:
    """A valid upload is stored by sha256 and described: topics, counts, time span."""
    import hashlib

    r = upload(client, recording.read_bytes(), filename="../../etc/tiny.mcap")
    assert r.status_code in (200, 201), r.text
    rec = r.json()
    assert rec["id"] == hashlib.sha256(recording.read_bytes()).hexdigest()
    assert rec["filename"] in ("tiny.mcap",)
    assert rec["message_count"] == 221 and rec["start_ns"] == 1_000_000_000 and rec["end_ns"] == 10_900_000_000
    topics = {t["topic"]: t["messages"] for t in rec["topics"]}
    assert topics["/odom"] == 100 and topics["/landmarks/range_bearing"] == 20
    assert client.get(f"/recordings/{rec['id']}").json()["id"] == rec["id"]
    assert any(x["id"] == rec["id"] for x in client.get("/recordings").json())


def test_same_file_twice_is_one_recording(tmp_path: Path) -> None:
    """201 for a new file; the same bytes again answer 200 with the same body (as documented), one recording stored."""
    data = write_tiny_recording(tmp_path / "a.mcap").read_bytes()
    c = TestClient(create_app(Settings(allowed_hosts=("testserver",), data_dir=tmp_path), executor=InlineExecutor()))
    first, second = upload(c, data, filename="a.mcap"), upload(c, data, filename="b.mcap")
    assert (first.status_code, second.status_code) == (201, 200)
    assert first.json() == second.json() and len(c.get("/recordings").json()) == 1  # the first label stays
    assert len(list((tmp_path / "recordings").glob("*.mcap"))) == 1
    documented = c.get("/openapi.json").json()["paths"]["/recordings"]["post"]["responses"]
    assert documented["201"]["description"] == "stored as a new recording"
    assert documented["200"]["description"].startswith("the same file (same sha256) was stored before")


def test_download_gives_back_the_bytes(client: TestClient, recording: Path) -> None:
    """GET /recordings/{id}/download returns the uploaded file."""
    rid = upload(client, recording.read_bytes(), filename="tiny.mcap").json()["id"]
    r = client.get(f"/recordings/{rid}/download")
    assert r.status_code == 200 and r.content == recording.read_bytes()
    assert "tiny.mcap" in r.headers["content-disposition"]


def test_non_mcap_upload_is_415(client: TestClient) -> None:
    """A file that is not an MCAP is refused with 415 and the reason."""
    r = upload(client, b"PNG? no, just text\n" * 10, filename="notes.txt")
    assert r.status_code == 415
    assert "notes.txt is not an MCAP file" in r.json()["detail"]


def test_empty_upload_is_422(client: TestClient) -> None:
    """An empty body is refused with 422 saying it is empty."""
    r = upload(client, b"")
    assert r.status_code == 422 and "empty" in r.json()["detail"]


def test_truncated_upload_is_offered_for_recovery(client: TestClient, tmp_path: Path) -> None:
    """A truncated MCAP answers 422 with a recovery offer; the offer stores the salvaged messages."""
    data = write_tiny_recording(tmp_path / "cut.mcap", n=40).read_bytes()[:-300]
    r = upload(client, data, filename="cut.mcap")
    assert r.status_code == 422
    body = r.json()
    assert "cut.mcap is truncated" in body["detail"] and "/recover" in body["detail"]
    assert str(tmp_path) not in body["detail"]
    rec = client.post(body["recover"]["url"])
    assert rec.status_code == 201, rec.text
    out = rec.json()
    assert out["recovered"]["from_id"] == body["recover"]["id"] and out["message_count"] > 0
    assert client.get(f"/recordings/{out['id']}").status_code == 200
    again = client.post(body["recover"]["url"])
    assert again.status_code == 404  # the damaged upload was consumed


def test_truncated_upload_with_recover_flag_is_salvaged_at_once(client: TestClient, tmp_path: Path) -> None:
    """?recover=true stores the salvaged part of a truncated upload in one request."""
    data = write_tiny_recording(tmp_path / "cut.mcap", n=30).read_bytes()[:-200]
    r = upload(client, data, recover="true")
    assert r.status_code in (200, 201), r.text
    assert r.json()["recovered"]["messages"] > 0


def test_damaged_index_upload_names_record_and_offset(client: TestClient) -> None:
    """An upload whose summary has a 3.75 GB record length: 422 naming the record and offset, no CLI hint;
    a random body between MCAP magics cannot be recovered: 422 saying nothing could be salvaged."""
    cases = Path(__file__).resolve().parents[1] / "fuzz" / "cases"
    r = upload(client, (cases / "summary-record-length.mcap").read_bytes(), filename="bad.mcap")
    assert r.status_code == 422
    detail = r.json()["detail"]
    assert "Schema record at byte 8752 claims 4,026,531,840 bytes" in detail and "slamreplay recover" not in detail
    r = upload(client, (cases / "random-body.mcap").read_bytes(), filename="junk.mcap")
    assert r.status_code == 422
    rec = client.post(r.json()["recover"]["url"])
    assert rec.status_code == 422 and "nothing could be salvaged" in rec.json()["detail"], rec.text
    assert "holds no readable message" in rec.json()["detail"]


def test_oversized_upload_is_413(tmp_path: Path, recording: Path) -> None:
    """Over SLAMREPLAY_MAX_UPLOAD_BYTES: 413 whether the size is declared or found while streaming."""
    c = TestClient(create_app(Settings(allowed_hosts=("testserver",),
                                       data_dir=tmp_path, max_upload_bytes=1000), executor=InlineExecutor()))
    data = recording.read_bytes()
    declared = upload(c, data)
    assert declared.status_code == 413 and "limit of 1000 bytes" in declared.json()["detail"]

    def chunks() -> Iterator[bytes]:
        for i in range(0, len(data), 256):
            yield data[i:i + 256]

    streamed = c.post("/recordings", content=chunks())
    assert streamed.status_code == 413
    assert not list((tmp_path / "recordings").glob(".upload-*")), "the partial upload was not removed"
    assert c.get("/recordings").json() == []


def test_delete_recording_refused_while_a_job_uses_it(idle: TestClient, recording: Path) -> None:
    """DELETE /recordings/{id} answers 409 while a job is queued on it, 204 once the job is cancelled."""
    rid = upload(idle, recording.read_bytes()).json()["id"]
    job = idle.post("/jobs", json={"recording_id": rid, "pipeline": "odometry"}).json()
    r = idle.delete(f"/recordings/{rid}")
    assert r.status_code == 409 and "1 queued or running job" in r.json()["detail"]
    assert idle.delete(f"/jobs/{job['id']}").json()["status"] == "cancelled"
    assert idle.delete(f"/recordings/{rid}").status_code == 204
    assert idle.get(f"/recordings/{rid}").status_code == 404


# -- jobs ------------------------------------------------------------------------------------------


def test_job_lifecycle_and_artifacts(client: TestClient, two_jobs: tuple[str, str, str]) -> None:
    """A succeeded job shows progress 1, metrics and manifest, and serves its rrd, metrics, manifest and log."""
    rid, a, _ = two_jobs
    job = client.get(f"/jobs/{a}").json()
    assert job["status"] == "succeeded" and job["progress"] == 1.0 and job["error"] is None
    assert job["metrics"]["poses_scored"] == 100.0 and job["manifest"]["run_id"] == a
    assert job["manifest"]["recording"]["sha256"] == rid and job["attempts"] == 1
    rrd = client.get(f"/jobs/{a}/rrd")
    assert rrd.status_code == 200 and len(rrd.content) > 1000
    assert client.get(f"/jobs/{a}/metrics").json()["metrics"]["ape_rmse_m"]["better"] == "lower"
    assert client.get(f"/jobs/{a}/manifest").json()["status"] == "succeeded"
    assert "odometry" in client.get(f"/jobs/{a}/log").text


def test_list_jobs_filters(client: TestClient, two_jobs: tuple[str, str, str]) -> None:
    """GET /jobs filters by recording, pipeline and status."""
    rid, a, b = two_jobs
    ids = {j["id"] for j in client.get("/jobs", params={"recording": rid, "pipeline": "odometry",
                                                         "status": "succeeded"}).json()}
    assert {a, b} <= ids
    assert client.get("/jobs", params={"pipeline": "dslam"}).json() == []
    assert client.get("/jobs", params={"status": "failed", "recording": rid}).json() == []
    assert client.get("/jobs", params={"status": "bogus"}).status_code == 422


def test_diff_of_two_jobs(client: TestClient, two_jobs: tuple[str, str, str]) -> None:
    """GET /diff compares two jobs (seed changed, metrics same); GET /diff.rrd serves the comparison recording."""
    _, a, b = two_jobs
    d = client.get("/diff", params={"a": a, "b": b}).json()
    assert d["a"] == a and d["b"] == b and d["worse"] == []
    assert {"field": "seed", "a": 0, "b": 1} in d["changes"]
    assert {m["verdict"] for m in d["metrics"]} == {"same"}
    r = client.get("/diff.rrd", params={"a": a, "b": b})
    assert r.status_code == 200 and len(r.content) > 1000
    assert client.get("/diff", params={"a": a, "b": b, "tolerance": "nope"}).status_code == 422


def test_unknown_pipeline_and_config_are_422_naming_them(client: TestClient, two_jobs: tuple[str, str, str]) -> None:
    """POST /jobs refuses an unknown pipeline, config key or value with 422 naming it, before queueing."""
    rid = two_jobs[0]
    before = len(client.get("/jobs").json())
    r = client.post("/jobs", json={"recording_id": rid, "pipeline": "slam9000"})
    assert r.status_code == 422 and "unknown pipeline 'slam9000'" in r.json()["detail"]
    r = client.post("/jobs", json={"recording_id": rid, "pipeline": "odometry", "config": {"gain": 2}})
    assert r.status_code == 422 and "unknown config key 'gain'" in r.json()["detail"]
    r = client.post("/jobs", json={"recording_id": rid, "pipeline": "ifmi", "config": {"min_pnr": "high"}})
    assert r.status_code == 422 and "min_pnr" in r.json()["detail"]
    assert len(client.get("/jobs").json()) == before


def test_bad_job_bodies_are_422(client: TestClient, two_jobs: tuple[str, str, str]) -> None:
    """Negative seeds, extra fields and a non-object config are refused with 422; a malformed recording id is a
    404 naming it (ids are checked by the service, which also takes the page's 8-digit prefixes)."""
    rid = two_jobs[0]
    bad_id = client.post("/jobs", json={"recording_id": "../../etc", "pipeline": "odometry"})
    assert bad_id.status_code == 404 and "'../../etc'" in bad_id.json()["detail"]
    for body in ({"recording_id": rid, "pipeline": "odometry", "seed": -1},
                 {"recording_id": rid, "pipeline": "odometry", "priority": 9},
                 {"recording_id": rid, "pipeline": "odometry", "config": [1, 2]},
                 {"pipeline": "odometry"}):
        assert client.post("/jobs", json=body).status_code == 422, body


def test_job_on_unknown_recording_is_404(client: TestClient) -> None:
    """POST /jobs naming a recording that was never uploaded answers 404."""
    r = client.post("/jobs", json={"recording_id": UNKNOWN_SHA, "pipeline": "odometry"})
    assert r.status_code == 404 and UNKNOWN_SHA in r.json()["detail"]


def test_cancel_queued_job_then_409(idle: TestClient, recording: Path) -> None:
    """DELETE /jobs/{id} cancels a queued job; cancelling it again is a 409; its artifacts are 404."""
    rid = upload(idle, recording.read_bytes()).json()["id"]
    job = idle.post("/jobs", json={"recording_id": rid, "pipeline": "odometry"})
    assert job.status_code == 202 and job.json()["status"] == "queued"
    job_id = job.json()["id"]
    assert idle.get(f"/jobs/{job_id}/rrd").json()["detail"].endswith("it has not started")
    r = idle.delete(f"/jobs/{job_id}")
    assert r.status_code == 200 and r.json()["status"] == "cancelled"
    again = idle.delete(f"/jobs/{job_id}")
    assert again.status_code == 409 and "already ended (cancelled)" in again.json()["detail"]
    assert idle.get(f"/jobs/{job_id}/log").status_code == 404


def test_diff_of_unfinished_job_is_409(idle: TestClient, recording: Path) -> None:
    """GET /diff with a job that has not succeeded answers 409."""
    rid = upload(idle, recording.read_bytes()).json()["id"]
    job_id = idle.post("/jobs", json={"recording_id": rid, "pipeline": "odometry"}).json()["id"]
    r = idle.get("/diff", params={"a": job_id, "b": job_id})
    assert r.status_code == 409 and "queued" in r.json()["detail"]
    assert idle.get("/diff.rrd", params={"a": job_id, "b": job_id}).status_code == 409


# -- ids and tokens ----------------------------------------------------------------------------


@pytest.mark.parametrize(("method", "path"), [
    ("GET", f"/recordings/{UNKNOWN_SHA}"), ("GET", f"/recordings/{UNKNOWN_SHA}/download"),
    ("DELETE", f"/recordings/{UNKNOWN_SHA}"), ("POST", f"/recordings/{UNKNOWN_SHA}/recover"),
    ("GET", f"/jobs/{UNKNOWN_JOB}"), ("DELETE", f"/jobs/{UNKNOWN_JOB}"), ("GET", f"/jobs/{UNKNOWN_JOB}/rrd"),
    ("GET", f"/jobs/{UNKNOWN_JOB}/metrics"), ("GET", f"/jobs/{UNKNOWN_JOB}/manifest"),
    ("GET", f"/jobs/{UNKNOWN_JOB}/log"), ("GET", f"/diff?a={UNKNOWN_JOB}&b={UNKNOWN_JOB}"),
    ("GET", f"/diff.rrd?a={UNKNOWN_JOB}&b={UNKNOWN_JOB}"),
])
def test_unknown_ids_are_404(client: TestClient, method: str, path: str) -> None:
    """Every route answers 404 naming an id that is well formed but unknown."""
    r = client.request(method, path)
    assert r.status_code == 404 and "0000" in r.json()["detail"], r.text


@pytest.mark.parametrize("path", ["/recordings/abc", "/recordings/..%2F..%2Fetc%2Fpasswd", f"/jobs/{'g' * 32}",
                                  f"/jobs/{UNKNOWN_SHA}", "/diff?a=..&b=x"])
def test_malformed_ids_never_reach_the_filesystem(client: TestClient, path: str) -> None:
    """Ids that are not lowercase hex of the right length are refused (422) or match no route (404)."""
    assert client.get(path).status_code in (404, 422)


@pytest.fixture(scope="module")
def guarded(tmp_path_factory: pytest.TempPathFactory) -> TestClient:
    """An app with SLAMREPLAY_TOKEN set (no scheduler)."""
    settings = Settings(allowed_hosts=("testserver",), data_dir=tmp_path_factory.mktemp("guarded"), token="s3cret")
    return TestClient(create_app(settings, executor=InlineExecutor()))


@pytest.mark.parametrize("path", ["/recordings", "/jobs", "/metrics", f"/jobs/{UNKNOWN_JOB}", "/openapi.json",
                                  f"/diff?a={UNKNOWN_JOB}&b={UNKNOWN_JOB}"])
def test_token_required_when_set(guarded: TestClient, path: str) -> None:
    """With a token set: no header or a wrong one is 401 (with WWW-Authenticate); the right one passes."""
    missing = guarded.get(path)
    assert missing.status_code == 401 and missing.headers["www-authenticate"] == "Bearer"
    assert "Authorization: Bearer" in missing.json()["detail"]
    wrong = guarded.get(path, headers={"Authorization": "Bearer nope"})
    assert wrong.status_code == 401 and wrong.json()["detail"] == "wrong bearer token"
    assert guarded.get(path, headers={"Authorization": "Basic czNjcmV0"}).status_code == 401
    assert guarded.get(path, headers={"Authorization": "Bearer s3cret"}).status_code in (200, 404)


def test_token_guards_uploads_and_jobs(guarded: TestClient, recording: Path) -> None:
    """Uploads and job submissions without the token are refused before anything is stored."""
    assert guarded.post("/recordings", content=recording.read_bytes()).status_code == 401
    assert guarded.post("/jobs", json={"recording_id": UNKNOWN_SHA, "pipeline": "odometry"}).status_code == 401
    ok = guarded.get("/recordings", headers={"Authorization": "Bearer s3cret"})
    assert ok.json() == []


def test_healthz_needs_no_token(guarded: TestClient) -> None:
    """/healthz stays open when a token is set."""
    assert guarded.get("/healthz").status_code == 200
