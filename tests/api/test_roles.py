"""Roles x actions on a team server, API and page; the audit trail (who, when, from where) and tombstones of
deleted runs on suite and compare pages (issue 40, items 1 and 2)."""

from __future__ import annotations

import re
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from conftest import write_tiny_recording
from people_helpers import NAMES, ROLES, Team, make_team, page_csrf, seed
from service_helpers import wait_for

UNKNOWN_JOB = "0" * 32
SUITE = 'name = "nightly"\nseeds = [1, 2]\n[recordings.tiny]\nid = "{rid}"\n[pipelines.odometry]\n'


@pytest.fixture(scope="module")
def recording(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_tiny_recording(tmp_path_factory.mktemp("rec") / "tiny.mcap")


@pytest.fixture(scope="module")
def team(tmp_path_factory: pytest.TempPathFactory, recording: Path) -> Iterator[Team]:
    t, client = make_team(tmp_path_factory.mktemp("team"), recording)
    with client:
        seed(t, recording)
        yield t


def allowed(role: str, need: str) -> bool:
    return ROLES.index(role) >= ROLES.index(need)


def api_actions(t: Team, extra: Path) -> list[tuple[str, str, str, dict[str, Any]]]:
    """(action, need, method, request kwargs) for every API route that changes something, and reads."""
    return [
        ("read jobs", "viewer", "GET", {"url": "/jobs"}),
        ("read a job", "viewer", "GET", {"url": f"/jobs/{t.jobs[0]}"}),
        ("read suites", "viewer", "GET", {"url": "/suites"}),
        ("upload", "runner", "POST", {"url": "/recordings?filename=extra.mcap", "content": extra.read_bytes()}),
        ("recover", "runner", "POST", {"url": f"/recordings/{'0' * 64}/recover"}),
        ("record", "runner", "POST", {"url": "/recordings/record/sim-landmarks", "json": {"duration_s": -1}}),
        ("submit", "runner", "POST", {"url": "/jobs", "json": {"recording_id": t.rid, "pipeline": "odometry",
                                                               "seed": 5}}),
        ("cancel", "runner", "DELETE", {"url": f"/jobs/{t.jobs[0]}"}),
        ("suite", "runner", "POST", {"url": "/suites", "content": SUITE.format(rid=t.rid).encode()}),
        ("run on commit", "runner", "POST", {"url": "/history/suites/nope/runs", "json": {"rev": "HEAD"}}),
        ("delete a recording", "admin", "DELETE", {"url": f"/recordings/{'0' * 64}"}),
        ("audit trail", "admin", "GET", {"url": "/audit"}),
    ]


@pytest.mark.parametrize("role", [None, *ROLES])
def test_api_role_by_action(team: Team, role: str | None, tmp_path: Path) -> None:
    """No token: 401 everywhere. A role below the action's: 403 with a one-line JSON detail naming the role
    needed, before anything happens. Otherwise the route runs (its own answer: 2xx, 404, 409 or 422)."""
    extra = write_tiny_recording(tmp_path / "extra.mcap", seed=4)
    client = team.api(role)
    for action, need, method, kwargs in api_actions(team, extra):
        r = client.request(method, **kwargs)
        if role is None:
            assert r.status_code == 401, (action, r.text)
        elif allowed(role, need):
            assert r.status_code not in (401, 403), (role, action, r.text)
        else:
            detail = r.json()["detail"]
            assert r.status_code == 403 and "\n" not in detail, (role, action, r.text)
            assert detail.startswith(f"{NAMES[role]} is a {role} and may not ") and f"the role {need}" in detail


def page_actions(t: Team, job: str) -> list[tuple[str, str, str, str, dict[str, Any]]]:
    """(action, need, method, url, form) of the page's forms and the pages that lead to them."""
    return [
        ("runs table", "viewer", "GET", "/runs", {}),
        ("job page", "viewer", "GET", f"/ui/jobs/{job}", {}),
        ("submit", "runner", "POST", "/ui/jobs", {"recording_id": t.rid, "pipeline": "odometry", "seed": "6"}),
        ("label form", "runner", "GET", f"/ui/jobs/{job}/edit", {}),
        ("label", "runner", "POST", f"/ui/jobs/{job}/edit", {"name": "named", "tags": "a b"}),
        ("cancel form", "runner", "GET", f"/ui/jobs/{job}/cancel", {}),
        ("cancel", "runner", "POST", f"/ui/jobs/{job}/cancel", {}),
        ("suite", "runner", "POST", "/ui/suites", {"suite": SUITE.format(rid=t.rid)}),
        ("run on commit", "runner", "POST", "/ui/history/nightly/runs", {"rev": "no-such-rev"}),
        ("delete form", "admin", "GET", f"/ui/jobs/{job}/delete", {}),
        ("audit trail", "admin", "GET", "/ui/audit", {}),
        ("people page", "admin", "GET", "/ui/people", {}),
        ("add a person", "admin", "POST", "/ui/people", {"name": "bad name", "role": "viewer"}),
        ("change a person", "admin", "POST", "/ui/people/vic", {"do": "nothing"}),
    ]


@pytest.mark.parametrize("role", ROLES)
def test_page_role_by_action(team: Team, role: str) -> None:
    """On the page: a role below the action's gets a readable 403 page (who, what, who can change it); its
    buttons are not shown. The forms carry the session's CSRF token."""
    client, csrf = team.page(role)
    job = team.jobs[1]
    for action, need, method, url, form in page_actions(team, job):
        r = client.request(method, url, data={**form, "csrf": csrf} if method == "POST" else None,
                           follow_redirects=False)
        if allowed(role, need):
            assert r.status_code not in (401, 403), (role, action, r.text[:500])
        else:
            assert r.status_code == 403, (role, action, r.status_code)
            assert "<h2>Not allowed (403)</h2>" in r.text and f"{NAMES[role]} is a {role} and may not" in r.text
            assert f"Signed in as {NAMES[role]} ({role})" in r.text
    home, page = client.get("/").text, client.get(f"/ui/jobs/{job}").text
    shown = {"upload": 'id="upload-form"' in home, "job form": 'id="job-form"' in home,
             "suite form": 'id="suite-form"' in home, "edit": 'id="edit-job"' in page,
             "delete": 'id="delete-job"' in page, "row delete": f"/ui/jobs/{job}/delete?next" in home,
             "row edit": f"/ui/jobs/{job}/edit?next" in home, "audit link": 'id="nav-audit"' in home,
             "people link": 'id="nav-people"' in home}
    want_run, want_admin = allowed(role, "runner"), role == "admin"
    assert shown == {"upload": want_run, "job form": want_run, "suite form": want_run, "edit": want_run,
                     "delete": want_admin, "row delete": want_admin, "row edit": want_run,
                     "audit link": want_admin, "people link": want_admin}, role
    assert page_csrf(home) == (csrf if want_run else page_csrf(home))  # a viewer's page may have no form at all
    if not want_run:
        assert "read what is here" in home


def test_only_an_admin_deletes_a_run_and_it_leaves_a_tombstone(team: Team) -> None:
    """A runner's delete is a 403 and the run stays; an admin's deletes it and says who did, in the trail, on the
    job's 404 and in the API."""
    api = team.api("runner")
    job = api.post("/jobs", json={"recording_id": team.rid, "pipeline": "odometry", "seed": 21}).json()["id"]
    wait_for(api, job)
    runner, rcsrf = team.page("runner")
    assert runner.post(f"/ui/jobs/{job}/delete", data={"csrf": rcsrf}, follow_redirects=False).status_code == 403
    assert team.store.get_job(job) is not None
    admin, acsrf = team.page("admin")
    r = admin.post(f"/ui/jobs/{job}/delete", data={"csrf": acsrf, "next": "/runs"}, follow_redirects=False)
    assert r.status_code == 303 and team.store.get_job(job) is None
    stone = team.store.tombstone(job)
    assert stone is not None and (stone.who, stone.address, stone.seed) == ("ada", "testclient", 21)
    gone = admin.get(f"/ui/jobs/{job}")
    assert gone.status_code == 404 and re.search(r"was deleted by ada at \d{4}-\d\d-\d\d \d\d:\d\d UTC", gone.text)
    assert "was deleted by ada" in api.get(f"/jobs/{job}").json()["detail"]
    entry = team.store.audit_entries(action="delete", limit=1)[0]
    assert (entry.who, entry.target, entry.address) == ("ada", job, "testclient")


def test_every_change_is_in_the_audit_trail_with_who_when_and_where(team: Team, tmp_path: Path) -> None:
    """Upload, submit, cancel, label, suite (and each job it queued): who, when, the address; the job page says
    who submitted and who cancelled; /ui/audit filters by who, action and since, and only an admin reads it."""
    api = team.api("runner")
    extra = write_tiny_recording(tmp_path / "audit.mcap", seed=7)
    rid = api.post("/recordings?filename=audit.mcap", content=extra.read_bytes()).json()["id"]
    job = api.post("/jobs", json={"recording_id": rid, "pipeline": "odometry", "seed": 31}).json()["id"]
    wait_for(api, job)
    admin, csrf = team.page("admin")
    admin.post(f"/ui/jobs/{job}/edit", data={"name": "audited", "tags": "x", "csrf": csrf})
    suite = api.post("/suites", content=SUITE.format(rid=rid).encode()).json()
    entries = team.store.audit_entries(limit=50)
    mine = [(e.who, e.action, e.target) for e in entries if e.target in (rid, job, suite["id"])]
    assert ("rui", "upload", rid) in mine and ("rui", "submit", job) in mine and ("ada", "label", job) in mine
    assert ("rui", "suite", suite["id"]) in mine
    new_cells = {c["job_id"] for c in suite["cells"] if not c["reused"]}
    assert new_cells <= {e.target for e in entries if e.action == "submit" and "suite nightly" in (e.detail or "")}
    assert all(e.address == "testclient" and e.at > 0 for e in entries)
    page = admin.get(f"/ui/jobs/{job}").text
    assert re.search(r"Submitted by <strong>rui</strong> at [\d: -]+ UTC from <code>testclient</code>", page)
    page = admin.get("/ui/audit", params={"who": "rui", "action": "upload"}).text
    trail = page[page.index('id="audit-table"'):]
    assert rid[:8] in trail and "audit.mcap" in trail and "<td>ada</td>" not in trail and "<td>rui</td>" in trail
    assert "No entry matches" in admin.get("/ui/audit", params={"since": "2999-01-01"}).text
    assert admin.get("/ui/audit", params={"since": "yesterday"}).status_code == 422
    got = team.api("admin").get("/audit", params={"action": "suite"}).json()
    assert got[0]["who"] == "rui" and got[0]["target"] == suite["id"] and got[0]["address"] == "testclient"


def test_a_cancelled_job_says_who_cancelled_it(team: Team) -> None:
    """Cancel from the page and from the API: the job page names who cancelled it."""
    idle_job = team.store.add_job("c" * 32, team.rid, "odometry", {}, 41)  # queued, never claimed by a worker
    assert idle_job is not None
    runner, csrf = team.page("runner")
    team.store.add_audit("rui", "testclient", "submit", idle_job.id, "by hand")
    r = runner.post(f"/ui/jobs/{idle_job.id}/cancel", data={"csrf": csrf, "next": "/"}, follow_redirects=False)
    assert r.status_code in (303, 409), r.text
    page = team.page("viewer")[0].get(f"/ui/jobs/{idle_job.id}").text
    assert re.search(r"Cancelled by <strong>rui</strong> at", page) and 'id="cancel-job"' not in page


def test_deleted_runs_show_as_deleted_on_suite_and_compare_pages(team: Team, tmp_path: Path) -> None:
    """A suite whose cell's run was deleted lists it as deleted (who, when), its JSON too; comparing it names the
    deleted runs and counts them as not succeeded; comparing the run itself says who deleted it."""
    api = team.api("runner")
    worn = write_tiny_recording(tmp_path / "worn.mcap", drift=0.3, seed=5)  # the same cells, other jobs
    other_rid = api.post("/recordings?filename=worn.mcap", content=worn.read_bytes()).json()["id"]
    a = api.post("/suites", content=SUITE.format(rid=team.rid).replace("[1, 2]", "[3, 4]").encode()).json()
    b = api.post("/suites", content=SUITE.format(rid=other_rid).replace("[1, 2]", "[3, 4]").encode()).json()
    loose = api.post("/suites", content=SUITE.format(rid=other_rid).replace("[1, 2]", "[3, 4]").replace(
        "[pipelines.odometry]", "[pipelines.odometry.variants]\nloose = {}").encode()).json()  # pairs with none
    for s in (a, b):
        for c in s["cells"]:
            wait_for(api, c["job_id"])
    victim = b["cells"][0]["job_id"]
    admin, csrf = team.page("admin")
    assert admin.post(f"/ui/jobs/{victim}/delete", data={"csrf": csrf}, follow_redirects=False).status_code == 303
    suite_page = admin.get(f"/ui/suites/{b['id']}").text
    assert '<span class="status deleted">deleted</span>' in suite_page and "deleted by ada at" in suite_page
    cells = api.get(f"/suites/{b['id']}").json()["cells"]
    assert [c["status"] for c in cells].count("deleted") == 1 and "deleted by ada" in str(cells)
    assert api.get(f"/suites/{b['id']}").json()["progress"]["ended"] == 2
    report = admin.get("/ui/compare", params={"a": a["id"], "b": b["id"]})
    assert report.status_code == 200, re.findall(r"id=\"error\">(.*?)<", report.text)
    assert 'id="deleted-runs"' in report.text and f"run {victim[:8]} deleted by ada at" in report.text
    assert "deleted by ada" in api.get("/compare", params={"a": a["id"], "b": b["id"]}).text
    unpaired = admin.get("/ui/compare", params={"a": a["id"], "b": loose["id"]})
    assert unpaired.status_code == 200 and f"run {victim[:8]} deleted by ada at" in unpaired.text
    other = a["cells"][0]["job_id"]
    runs = admin.get("/ui/compare", params={"runs": f"{other},{victim}"})
    assert runs.status_code == 404 and f"job {victim} was deleted by ada at" in runs.text
    paired = admin.get("/ui/compare", params={"a": other, "b": victim})
    assert paired.status_code == 404 and "was deleted by ada" in paired.text


def test_a_run_on_a_commit_is_in_the_trail(team: Team, monkeypatch: pytest.MonkeyPatch) -> None:
    """POST /history/suites/NAME/runs: the suite sent again is recorded as run-on-commit, by whom, with the commit
    (the commit's build is stood in for by the suite sent as it is: tests/api/test_history_rev.py builds one)."""
    from slamreplay.api.service import history_routes

    api = team.api("runner")
    api.post("/suites", content=SUITE.format(rid=team.rid).encode())
    monkeypatch.setattr(history_routes, "run_on_revision",
                        lambda suites, name, rev: suites.submit(SUITE.format(rid=team.rid), "toml"))
    r = api.post("/history/suites/nightly/runs", json={"rev": "0123456789abcdef"})
    assert r.status_code == 202, r.text
    entry = team.store.audit_entries(action="run-on-commit", limit=1)[0]
    assert (entry.who, entry.target) == ("rui", r.json()["id"]) and "commit 0123456789" in (entry.detail or "")
