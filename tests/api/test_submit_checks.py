"""Submit-time checks: topics a pipeline needs, topic_map on jobs and suites, id prefixes, malformed ids, file names."""

from __future__ import annotations

import warnings
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from conftest import write_tiny_recording
from service_helpers import InlineExecutor, wait_for

with warnings.catch_warnings():
    warnings.simplefilter("ignore", UserWarning)  # StarletteDeprecationWarning: it asks for httpx2; httpx works
    from fastapi.testclient import TestClient

from slamreplay.api.app import create_app
from slamreplay.api.service.settings import Settings
from slamreplay.api.service.store import Store


def wheel_recording(path: Path, n: int = 40) -> Path:
    """Odometry and ground truth on a straight line, the odometry under another name: /wheel/odom."""
    from slamreplay.recorder import GroundTruthPose, OdometryPose, Recorder

    with Recorder(path, source={"test": "wheel"}, seed=0) as rec:
        for k in range(n):
            t = 1_000_000_000 + k * 100_000_000
            rec.write("/ground_truth/pose", GroundTruthPose(t, 0.1 * k, 0.0, 0.0))
            rec.write("/wheel/odom", OdometryPose(t, 0.1 * k * 1.02, 0.0, 0.0))
    return path


@pytest.fixture(scope="module")
def client(tmp_path_factory: pytest.TempPathFactory) -> Iterator[TestClient]:
    """A running app (in-thread jobs) over a fresh data directory."""
    app = create_app(Settings(allowed_hosts=("testserver",), data_dir=tmp_path_factory.mktemp("data"), workers=1),
                     executor=InlineExecutor())
    with TestClient(app) as c:
        yield c


@pytest.fixture(scope="module")
def recs(client: TestClient, tmp_path_factory: pytest.TempPathFactory) -> dict[str, str]:
    """Ids of a landmarks recording uploaded as sim.mcap and of a /wheel/odom one uploaded as wheel.mcap."""
    d = tmp_path_factory.mktemp("rec")
    sim = write_tiny_recording(d / "tiny.mcap", n=40)
    wheel = wheel_recording(d / "w.mcap")
    up = {name: client.post("/recordings", content=p.read_bytes(), params={"filename": name}).json()
          for name, p in (("sim.mcap", sim), ("wheel.mcap", wheel))}
    return {"sim": up["sim.mcap"]["id"], "wheel": up["wheel.mcap"]["id"]}


def test_pipeline_missing_topics_is_422_naming_them_and_what_fits(client: TestClient, recs: dict[str, str]) -> None:
    """ifmi on a landmarks recording: 422 naming /camera/image and the pipelines that fit; nothing is queued."""
    before = len(client.get("/jobs").json())
    r = client.post("/jobs", json={"recording_id": recs["sim"], "pipeline": "ifmi"})
    assert r.status_code == 422
    detail = r.json()["detail"]
    assert isinstance(detail, str) and "\n" not in detail
    assert "/camera/image" in detail and "sim.mcap" in detail and "--topic-map" not in detail
    fits = detail[detail.index("pipelines this recording fits:"):]
    for name in ("odometry", "dslam", "ekfslam"):
        assert name in fits
    assert "topometric" not in fits
    assert len(client.get("/jobs").json()) == before
    page = client.post("/ui/jobs", data={"recording_id": recs["sim"], "pipeline": "ifmi", "seed": "0"})
    assert page.status_code == 422 and "/camera/image" in page.text


def test_topic_map_makes_a_renamed_topic_usable(client: TestClient, recs: dict[str, str]) -> None:
    """/wheel/odom alone does not fit odometry (422 suggesting the map); with topic_map it runs and succeeds."""
    r = client.post("/jobs", json={"recording_id": recs["wheel"], "pipeline": "odometry"})
    assert r.status_code == 422 and "/odom" in r.json()["detail"]
    assert '{"/wheel/odom": "/odom"}' in r.json()["detail"]
    job = client.post("/jobs", json={"recording_id": recs["wheel"], "pipeline": "odometry",
                                     "topic_map": {"/wheel/odom": "/odom"}})
    assert job.status_code == 202, job.text
    assert job.json()["topic_map"] == {"/wheel/odom": "/odom"}
    done = wait_for(client, job.json()["id"])
    assert done["status"] == "succeeded", done["error"]
    assert done["metrics"]["ape_rmse_m"] > 0
    page = client.post("/ui/jobs", data={"recording_id": recs["wheel"], "pipeline": "odometry", "seed": "1",
                                         "topic_map": '{"/wheel/odom": "/odom"}'}, follow_redirects=False)
    assert page.status_code == 303


def test_topic_map_errors_are_one_line(client: TestClient, recs: dict[str, str]) -> None:
    """A map naming a topic the file lacks, or a target that is no slamreplay topic, is a 422 saying so."""
    r = client.post("/jobs", json={"recording_id": recs["wheel"], "pipeline": "odometry",
                                   "topic_map": {"/nope": "/odom"}})
    assert r.status_code == 422 and "/nope" in r.json()["detail"] and "wheel.mcap" in r.json()["detail"]
    r = client.post("/jobs", json={"recording_id": recs["wheel"], "pipeline": "odometry",
                                   "topic_map": {"/wheel/odom": "/wheels"}})
    assert r.status_code == 422 and "not a slamreplay topic" in r.json()["detail"]
    page = client.post("/ui/jobs", data={"recording_id": recs["wheel"], "pipeline": "odometry", "topic_map": "{x"})
    assert page.status_code == 422 and "topic_map is not JSON" in page.text


def test_suite_topic_map_reaches_its_jobs(client: TestClient, recs: dict[str, str]) -> None:
    """A suite's recording with topic_map queues jobs that carry it; without it the suite is refused whole."""
    toml = 'seeds = [0]\n[recordings.w]\nid = "{rid}"\n{extra}[pipelines.odometry]\n'
    bad = client.post("/suites", content=toml.format(rid=recs["wheel"][:8], extra=""))
    assert bad.status_code == 422 and "/odom" in bad.json()["detail"]
    ok = client.post("/suites", content=toml.format(rid=recs["wheel"][:8],
                                                    extra='topic_map = {"/wheel/odom" = "/odom"}\n'))
    assert ok.status_code == 202, ok.text
    job = client.get(f"/jobs/{ok.json()['cells'][0]['job_id']}").json()
    assert job["topic_map"] == {"/wheel/odom": "/odom"}


def test_ids_by_prefix_everywhere(client: TestClient, recs: dict[str, str]) -> None:
    """The page's 8-digit ids work in API and page routes, and in POST /jobs; the answers carry the whole id."""
    job = client.post("/jobs", json={"recording_id": recs["sim"][:8], "pipeline": "odometry"})
    assert job.status_code == 202 and job.json()["recording_id"] == recs["sim"]
    jid = job.json()["id"]
    wait_for(client, jid)
    assert client.get(f"/jobs/{jid[:8]}").json()["id"] == jid
    assert client.get(f"/jobs/{jid[:8]}/metrics").status_code == 200
    assert client.get(f"/recordings/{recs['sim'][:8]}").json()["id"] == recs["sim"]
    assert client.get("/jobs", params={"recording": recs["sim"][:8]}).json()[0]["recording_id"] == recs["sim"]
    assert client.get(f"/ui/jobs/{jid[:8]}").status_code == 200
    assert client.get("/diff", params={"a": jid[:8], "b": jid[:8]}).json()["a"] == jid


def test_ambiguous_prefix_names_the_candidates(client: TestClient, recs: dict[str, str]) -> None:
    """A prefix that starts two job ids is a 409 (API) or an error page (page) naming both."""
    store: Store = client.app.state.jobs.store  # type: ignore[attr-defined]
    twins = ["abcd" + "0" * 28, "abcd" + "1" * 28]
    for t in twins:
        store.add_job(t, recs["sim"], "odometry", {}, 7)
        store.cancel_job(t)
    r = client.get("/jobs/abcd")
    assert r.status_code == 409 and all(t in r.json()["detail"] for t in twins) and "ambiguous" in r.json()["detail"]
    page = client.get("/ui/jobs/abcd")
    assert page.status_code == 409 and twins[0] in page.text
    assert client.get(f"/jobs/{twins[1][:5]}").json()["id"] == twins[1]


@pytest.mark.parametrize("path", ["/jobs/xyz", "/jobs/ABCDEF12", f"/jobs/{'f' * 40}", "/recordings/hello!",
                                  "/ui/jobs/nothex", "/diff?a=zz&b=zz", "/jobs/abc"])
def test_malformed_ids_are_404_with_the_id(client: TestClient, path: str) -> None:
    """Not hex, too long or too short: a 404 naming the id in one line, never a pattern error."""
    r = client.get(path)
    assert r.status_code == 404, r.text
    shown = path.split("/")[-1].split("=")[-1]
    assert shown[:20] in r.text and "pattern" not in r.text


def test_malformed_recording_id_in_a_job_is_404(client: TestClient) -> None:
    """POST /jobs with a recording id that is not hex: 404 naming it."""
    r = client.post("/jobs", json={"recording_id": "../../etc", "pipeline": "odometry"})
    assert r.status_code == 404 and "'../../etc'" in r.json()["detail"]


def test_prefix_answers_need_the_token(tmp_path: Path) -> None:
    """With a token, an ambiguous or unknown prefix from a request without it is the usual 401 (no ids leak)."""
    app = create_app(Settings(allowed_hosts=("testserver",), data_dir=tmp_path, token="s3cret"),
                     executor=InlineExecutor())
    c = TestClient(app)
    assert c.get("/jobs/abcd").status_code == 401
    assert c.get("/jobs/abcd", headers={"Authorization": "Bearer s3cret"}).status_code == 404


def test_runs_name_the_uploaded_file(client: TestClient, recs: dict[str, str]) -> None:
    """A run's log, manifest-facing messages and viewer title say sim.mcap, not the sha256 file name."""
    job = client.post("/jobs", json={"recording_id": recs["sim"], "pipeline": "odometry", "seed": 3}).json()
    wait_for(client, job["id"])
    log = client.get(f"/jobs/{job['id']}/log").text
    assert "odometry on sim.mcap" in log and f"{recs['sim']}.mcap" not in log.splitlines()[1]
    assert np.isfinite(client.get(f"/jobs/{job['id']}").json()["metrics"]["ape_rmse_m"])


def test_run_errors_speak_of_topic_map_not_the_cli_flag() -> None:
    """A failure that would tell a CLI user to pass --topic-map names the job's topic_map field instead."""
    from slamreplay.api.service.executor import service_words

    said = service_words("sim.mcap has no /odom topic; map it with --topic-map FILE_TOPIC=/odom")
    assert "--topic-map" not in said and 'topic_map {"FILE_TOPIC": "/odom"}' in said
