"""Other sites and rebound names: a Host the server does not answer to is a 400, a state-changing request from
another origin is a 403 and changes nothing; the server's own pages and clients without Origin are served."""

from __future__ import annotations

import re
import warnings
from pathlib import Path

import pytest
from conftest import write_tiny_recording
from service_helpers import InlineExecutor

with warnings.catch_warnings():
    warnings.simplefilter("ignore", UserWarning)  # StarletteDeprecationWarning: it asks for httpx2; httpx works
    from fastapi.testclient import TestClient

from pydantic import ValidationError

from slamreplay.api.app import create_app
from slamreplay.api.service.settings import Settings
from slamreplay.api.service.siteguard import same_origin, served_hosts, split_host

EVIL = "http://evil.example"


def client_for(tmp_path: Path, *hosts: str, token: str | None = None) -> TestClient:
    """An app (no scheduler: jobs stay queued) serving TestClient's host ``testserver`` and ``hosts``."""
    settings = Settings(allowed_hosts=("testserver", *hosts), data_dir=tmp_path, workers=1, token=token)
    return TestClient(create_app(settings, executor=InlineExecutor()))


@pytest.fixture
def client(tmp_path: Path) -> TestClient:
    return client_for(tmp_path)


@pytest.fixture
def rid(client: TestClient, tmp_path: Path) -> str:
    """A stored recording (uploaded by a client without Origin, as curl)."""
    data = write_tiny_recording(tmp_path / "tiny.mcap", n=20).read_bytes()
    r = client.post("/recordings", content=data)
    assert r.status_code == 201
    return str(r.json()["id"])


@pytest.mark.parametrize("path", ["/", "/healthz", "/jobs", "/recordings", "/docs"])
def test_other_host_is_400_on_every_route(client: TestClient, path: str) -> None:
    """``Host: evil.example`` (a rebound name) gets a one-line 400 naming the host and the option to allow it."""
    r = client.get(path, headers={"Host": "evil.example"})
    assert r.status_code == 400
    detail = r.json()["detail"]
    assert "'evil.example'" in detail and "--allowed-host" in detail and "\n" not in detail


@pytest.mark.parametrize("host", ["testserver", "127.0.0.1:8000", "localhost", "LOCALHOST:80", "[::1]:8000",
                                  "[0:0::1]"])
def test_loopback_and_configured_hosts_are_served(client: TestClient, host: str) -> None:
    r = client.get("/healthz", headers={"Host": host})
    assert r.status_code == 200


@pytest.mark.parametrize("host", ["", "127.0.0.1.evil.example", "localhost.evil.example", "evil.example:8000"])
def test_lookalike_and_missing_hosts_are_400(client: TestClient, host: str) -> None:
    assert client.get("/healthz", headers={"Host": host}).status_code == 400


def test_configured_patterns(tmp_path: Path) -> None:
    """``*.example.org`` serves its subdomains only; ``*`` serves any name (the user's explicit choice)."""
    c = client_for(tmp_path, "*.example.org", "slam.lan")
    codes = {h: c.get("/healthz", headers={"Host": h}).status_code
             for h in ("a.example.org", "example.org", "a.example.org.evil", "slam.lan:8000", "evil.example")}
    assert codes == {"a.example.org": 200, "example.org": 400, "a.example.org.evil": 400, "slam.lan:8000": 200,
                     "evil.example": 400}
    assert client_for(tmp_path, "*").get("/healthz", headers={"Host": "evil.example"}).status_code == 200


def test_cross_site_job_form_is_403_and_creates_nothing(client: TestClient, rid: str) -> None:
    """The form post another page would make (Origin evil.example) is refused; no job is created. The same
    form from this server's own page (same Origin) or with no Origin (curl) creates its job."""
    form = {"recording_id": rid, "pipeline": "odometry", "seed": "0"}
    r = client.post("/ui/jobs", data=form, headers={"Origin": EVIL}, follow_redirects=False)
    assert r.status_code == 403
    assert "cross-site request refused" in r.json()["detail"] and EVIL in r.json()["detail"]
    assert client.get("/jobs").json() == []
    own = client.post("/ui/jobs", data=form, headers={"Origin": "http://testserver"}, follow_redirects=False)
    plain = client.post("/ui/jobs", data=form, follow_redirects=False)
    assert (own.status_code, plain.status_code) == (303, 303)
    assert len(client.get("/jobs").json()) == 2


@pytest.mark.parametrize("headers", [{"Origin": EVIL}, {"Referer": f"{EVIL}/page.html"}, {"Origin": "null"},
                                     {"Origin": "http://testserver:8080"}, {"Origin": "http://testserver.evil"},
                                     {"Origin": EVIL, "Referer": "http://testserver/"}])
def test_other_origins_cannot_change_anything(client: TestClient, rid: str, headers: dict[str, str]) -> None:
    """Every state-changing method from another origin (by Origin, else Referer; ``null``, another port or a
    look-alike name included) is 403: no job, no upload, no delete, no suite, no login."""
    job = {"recording_id": rid, "pipeline": "odometry"}
    answers = [client.post("/jobs", json=job, headers=headers),
               client.post("/recordings", content=b"\x89MCAP0\r\n", headers=headers),
               client.delete(f"/recordings/{rid}", headers=headers),
               client.post("/suites", content=b"seeds = [0]\n", headers=headers),
               client.post("/login", data={"token": "x"}, headers=headers),
               client.request("PUT", "/jobs", headers=headers), client.request("PATCH", "/jobs", headers=headers)]
    assert [a.status_code for a in answers] == [403] * len(answers)
    assert client.get("/jobs").json() == [] and [r["id"] for r in client.get("/recordings").json()] == [rid]


def test_reads_from_other_origins_are_served(client: TestClient) -> None:
    """A GET carries no change: served whatever its Origin (the browser keeps the answer from the other page)."""
    assert client.get("/jobs", headers={"Origin": EVIL}).status_code == 200


def test_with_a_token_cross_site_posts_are_refused_before_the_token(tmp_path: Path, rid: str) -> None:
    """With a token the Origin check comes first: even a request with the right token is 403 from another site."""
    c = client_for(tmp_path / "t", token="s3cret")
    auth = {"Authorization": "Bearer s3cret"}
    r = c.post("/jobs", json={"recording_id": rid, "pipeline": "odometry"}, headers={**auth, "Origin": EVIL})
    assert r.status_code == 403


def test_same_origin_rules() -> None:
    """Ports default by scheme, IPv6 in brackets, scheme not compared (a TLS proxy), garbage never matches."""
    assert same_origin("http://127.0.0.1:8000", "127.0.0.1:8000", "http")
    assert same_origin("https://slam.example.org", "slam.example.org", "http")
    assert same_origin("http://[::1]:8000/ui/jobs", "[::1]:8000", "http")
    assert same_origin("http://localhost/x", "localhost:80", "http")
    assert not same_origin("http://127.0.0.1:8001", "127.0.0.1:8000", "http")
    assert not same_origin("null", "127.0.0.1:8000", "http")
    assert not same_origin("http://127.0.0.1:99999", "127.0.0.1:8000", "http")


def test_served_hosts_and_split() -> None:
    """A wildcard bind adds no name (only an explicit setting serves other names); a specific bind is served."""
    assert served_hosts((), "0.0.0.0") == ("127.0.0.1", "localhost", "::1")
    assert served_hosts(("Slam.LAN",), "192.168.1.5") == ("127.0.0.1", "localhost", "::1", "192.168.1.5", "slam.lan")
    assert [split_host(h) for h in ("[::1]:8000", "::1", "a.b:80", "a.b")] == [
        ("::1", 8000), ("::1", None), ("a.b", 80), ("a.b", None)]


def test_allowed_hosts_setting() -> None:
    """SLAMREPLAY_ALLOWED_HOSTS is comma-separated; a URL instead of a name is refused naming it."""
    assert Settings.from_env({"SLAMREPLAY_ALLOWED_HOSTS": "slam.lan, 10.0.0.5,"}).allowed_hosts == ("slam.lan",
                                                                                                   "10.0.0.5")
    with pytest.raises(ValidationError, match="'http://slam.lan' is not a host name"):
        Settings.from_env({"SLAMREPLAY_ALLOWED_HOSTS": "http://slam.lan"})


@pytest.mark.parametrize("path", ["/", "/runs", "/ui/jobs/0123456789abcdef/delete", "/jobs", "/docs",
                                  "/static/favicon.svg", "/no/such/page"])
def test_no_page_can_be_framed_by_another_site(client: TestClient, path: str) -> None:
    """Clickjacking: every answer (pages, forms, JSON, static files, errors) forbids framing by any site."""
    r = client.get(path)
    policy = r.headers["content-security-policy"]
    assert "frame-ancestors 'none'" in policy and "object-src 'none'" in policy, policy
    assert re.search(r"script-src 'self'( 'sha256-[A-Za-z0-9+/=]+')*;", policy), policy  # never 'unsafe-inline'
    assert r.headers["x-frame-options"] == "DENY" and r.headers["x-content-type-options"] == "nosniff"
    assert r.headers["referrer-policy"] == "same-origin"
    refused = client.get(path, headers={"Host": "evil.example"})
    assert refused.status_code == 400 and refused.headers["x-frame-options"] == "DENY"
