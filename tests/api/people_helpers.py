"""Helpers of the people tests: a team server (an admin, a runner, a viewer), signing in, CSRF tokens of pages."""

from __future__ import annotations

import re
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from service_helpers import InlineExecutor, wait_for

with warnings.catch_warnings():
    warnings.simplefilter("ignore", UserWarning)  # StarletteDeprecationWarning: it asks for httpx2; httpx works
    from fastapi.testclient import TestClient

from slamreplay.api.app import create_app
from slamreplay.api.service.auth import COOKIE, csrf_token
from slamreplay.api.service.settings import Settings
from slamreplay.api.service.store import Store

ROLES = ("viewer", "runner", "admin")
NAMES = {"viewer": "vic", "runner": "rui", "admin": "ada"}


@dataclass
class Team:
    """A served app with three people, a recording and two succeeded jobs."""

    app: Any
    store: Store
    tokens: dict[str, str]  # role -> token
    rid: str = ""
    jobs: list[str] = field(default_factory=list)

    def api(self, role: str | None) -> TestClient:
        """A client sending ``role``'s bearer token (None: no token)."""
        headers = {} if role is None else {"Authorization": f"Bearer {self.tokens[role]}"}
        return TestClient(self.app, headers=headers)

    def page(self, role: str) -> tuple[TestClient, str]:
        """A client signed in on the page as ``role`` (a session cookie), and its forms' CSRF token."""
        return sign_in(TestClient(self.app), self.tokens[role])


def sign_in(client: TestClient, token: str) -> tuple[TestClient, str]:
    r = client.post("/login", data={"token": token, "next": "/"}, follow_redirects=False)
    assert r.status_code == 303, r.text
    cookie = r.cookies[COOKIE]
    client.cookies.clear()  # some httpx versions keep the response's cookie beside a set() one
    client.cookies.set(COOKIE, cookie)
    return client, csrf_token(cookie)


def page_csrf(html: str) -> str | None:
    """The CSRF token the page's forms carry (the first one)."""
    m = re.search(r'name="csrf" value="([0-9a-f]+)"', html)
    return m.group(1) if m else None


def make_team(data: Path, recording: Path) -> tuple[Team, TestClient]:
    """The team's app (its scheduler started by the returned client, to be used as a context manager)."""
    app = create_app(Settings(allowed_hosts=("testserver",), data_dir=data, workers=1), executor=InlineExecutor())
    store: Store = app.state.jobs.store
    tokens = {role: store.add_user(NAMES[role], role) for role in ROLES}
    return Team(app, store, tokens), TestClient(app)


def seed(team: Team, recording: Path) -> None:
    """A recording and two succeeded odometry jobs, made by the runner."""
    runner = team.api("runner")
    team.rid = runner.post("/recordings?filename=tiny.mcap", content=recording.read_bytes()).json()["id"]
    for s in (0, 1):
        job = runner.post("/jobs", json={"recording_id": team.rid, "pipeline": "odometry", "seed": s}).json()
        assert wait_for(runner, job["id"])["status"] == "succeeded"
        team.jobs.append(job["id"])
