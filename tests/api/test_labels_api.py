"""Labels and listing through the API (issue 40, item 4): name, tags and note at submit and by ``PATCH /jobs/ID``,
who made each job, ``GET /jobs`` filtered as the runs table and paged by a cursor; and the page's session reading
the API's files (the job page links to them)."""

from __future__ import annotations

import re
from collections.abc import Iterator

import pytest
from conftest import write_tiny_recording
from people_helpers import Team, make_team, seed
from service_helpers import wait_for


@pytest.fixture(scope="module")
def team(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Team]:
    recording = write_tiny_recording(tmp_path_factory.mktemp("rec") / "tiny.mcap")
    t, client = make_team(tmp_path_factory.mktemp("team"), recording)
    with client:
        seed(t, recording)
        yield t


def test_labels_at_submit_and_who_made_it(team: Team) -> None:
    runner = team.api("runner")
    spec = {"recording_id": team.rid[:8], "pipeline": "odometry", "seed": 7, "name": "  nightly baseline ",
            "tags": ["ci", "nightly", "ci"], "note": "from CI job 1234"}
    job = runner.post("/jobs", json=spec).json()
    assert (job["name"], job["tags"], job["note"], job["made_by"]) == ("nightly baseline", ["ci", "nightly"],
                                                                      "from CI job 1234", "rui")
    done = wait_for(runner, job["id"])
    assert done["status"] == "succeeded" and done["tags"] == ["ci", "nightly"]
    assert done["git_commit"] is None or re.fullmatch(r"[0-9a-f]{40}(-dirty)?", done["git_commit"])
    assert team.store.audit_entries(target=job["id"], action="submit", limit=1)[0].who == "rui"


@pytest.mark.parametrize(("field", "value", "words"), [
    ("tags", ["has space"], "tag 'has space'"), ("tags", [f"t{i}" for i in range(21)], "at most 20"),
    ("name", "x" * 121, "at most 120"), ("note", "y" * 2001, "at most 2000"),
])
def test_bad_labels_at_submit_are_a_422_saying_what(team: Team, field: str, value: object, words: str) -> None:
    before = len(team.store.list_jobs(limit=1000))
    r = team.api("runner").post("/jobs", json={"recording_id": team.rid, "pipeline": "odometry", field: value})
    assert r.status_code == 422 and words in r.text, r.text
    assert len(team.store.list_jobs(limit=1000)) == before


def test_patch_changes_only_the_fields_given(team: Team) -> None:
    runner, job = team.api("runner"), team.jobs[0]
    r = runner.patch(f"/jobs/{job}", json={"name": "first", "tags": ["a", "b"], "note": "kept"})
    assert r.status_code == 200 and (r.json()["name"], r.json()["tags"], r.json()["note"]) == ("first", ["a", "b"],
                                                                                               "kept")
    r = runner.patch(f"/jobs/{job}", json={"tags": ["c"]})
    assert (r.json()["name"], r.json()["tags"], r.json()["note"]) == ("first", ["c"], "kept")
    r = runner.patch(f"/jobs/{job}", json={"name": None, "note": ""})
    assert (r.json()["name"], r.json()["tags"], r.json()["note"]) == (None, ["c"], None)
    entry = team.store.audit_entries(target=job, action="label", limit=1)[0]
    assert entry.who == "rui" and "tags c" in (entry.detail or "")
    assert runner.patch(f"/jobs/{job}", json={"tags": ["bad tag"]}).status_code == 422
    assert runner.patch(f"/jobs/{job}", json={"colour": "red"}).status_code == 422  # never silently ignored
    assert runner.patch(f"/jobs/{'0' * 32}", json={"name": "x"}).status_code == 404


def test_patch_needs_a_runner_token_not_a_cookie(team: Team) -> None:
    """A viewer may not label (403); the page's session may read through the API but not change through it (a
    cookie alone is what another site's form would send)."""
    job = team.jobs[1]
    assert team.api("viewer").patch(f"/jobs/{job}", json={"name": "x"}).status_code == 403
    client, _ = team.page("admin")
    assert client.patch(f"/jobs/{job}", json={"name": "x"}).status_code == 401
    assert client.delete(f"/jobs/{job}").status_code == 401
    for path in (f"/jobs/{job}", f"/jobs/{job}/manifest", f"/jobs/{job}/log", "/jobs", "/recordings"):
        assert client.get(path).status_code == 200, path  # the job page links to these
    assert team.api(None).get(f"/jobs/{job}/manifest").status_code == 401


def test_list_is_filtered_and_paged_by_a_cursor(team: Team) -> None:
    runner = team.api("runner")
    made = []
    for s in range(20, 25):
        made.append(runner.post("/jobs", json={"recording_id": team.rid, "pipeline": "odometry", "seed": s,
                                               "tags": ["sweep"]}).json()["id"])
    for j in made:
        wait_for(runner, j)
    r = runner.get("/jobs", params={"tag": "sweep", "limit": 2})
    assert r.status_code == 200 and r.headers["x-total-count"] == "5"
    seen = [j["id"] for j in r.json()]
    runner.post("/jobs", json={"recording_id": team.rid, "pipeline": "odometry", "seed": 30, "tags": ["sweep"]})
    while "link" in r.headers:  # a job added meanwhile neither repeats nor shifts a page
        url = re.fullmatch(r'<([^>]+)>; rel="next"', r.headers["link"])
        assert url is not None
        r = runner.get(url.group(1))
        seen += [j["id"] for j in r.json()]
    assert seen == made[::-1]
    assert r.headers["x-total-count"] == "6"
    assert runner.get("/jobs", params={"q": "tiny.mcap sweep", "limit": 1000}).headers["x-total-count"] == "6"
    worst = runner.get("/jobs", params={"where": "ape_rmse_m > 1e9"})
    assert worst.json() == [] and worst.headers["x-total-count"] == "0"
    assert runner.get("/jobs", params={"where": "ape_rmse_m >= 0 and seed_no = 3"}).status_code == 422
    bad = runner.get("/jobs", params={"where": "ape_rmse < 1"})
    assert bad.status_code == 422 and "unknown metric 'ape_rmse'" in bad.json()["detail"], bad.text
    assert runner.get("/jobs", params={"cursor": "abc"}).status_code == 422


def test_suite_jobs_carry_the_suites_tags(team: Team) -> None:
    suite = f'name = "tagged"\nseeds = [41]\n[recordings.r]\nid = "{team.rid}"\n[pipelines.odometry]\n'
    r = team.api("runner").post("/suites", params={"tags": "ci,pr-12", "note": "PR 12"}, content=suite)
    assert r.status_code == 202, r.text
    job = team.api("viewer").get(f"/jobs/{r.json()['cells'][0]['job_id']}").json()
    assert (job["tags"], job["note"], job["made_by"]) == (["ci", "pr-12"], "PR 12", "rui")
    bad = team.api("runner").post("/suites", params={"tags": "bad tag!"}, content=suite)
    assert bad.status_code == 422 and "tag 'bad tag!'" in bad.json()["detail"], bad.text


def test_failed_sign_ins_are_limited_per_address(tmp_path_factory: pytest.TempPathFactory) -> None:
    """Ten wrong tokens from one address in 15 minutes: the eleventh try, even with the right token, is a 429 page
    saying how long to wait; the failures are in the trail."""
    from people_helpers import TestClient

    from slamreplay.api.service.auth import SIGN_IN_ATTEMPTS

    recording = write_tiny_recording(tmp_path_factory.mktemp("rec2") / "tiny.mcap")
    t, _ = make_team(tmp_path_factory.mktemp("limited"), recording)
    client = TestClient(t.app)
    for _ in range(SIGN_IN_ATTEMPTS):
        assert client.post("/login", data={"token": "slr_wrong"}, follow_redirects=False).status_code == 401
    r = client.post("/login", data={"token": t.tokens["admin"]}, follow_redirects=False)
    assert r.status_code == 429 and "try again in 15 minutes" in r.text, r.text
    assert len(t.store.audit_entries(action="sign-in-failed")) == SIGN_IN_ATTEMPTS
