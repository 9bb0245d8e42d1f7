"""People of a shared server: tokens kept only as slow hashes, sign-in and sign-out, sessions, CSRF tokens on forms,
the single-user modes kept, and `slamreplay users` (issue 40, items 1 and 3's CSRF)."""

from __future__ import annotations

import hashlib
import re
import sqlite3
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
from conftest import write_tiny_recording
from people_helpers import Team, TestClient, make_team, page_csrf, seed, sign_in
from service_helpers import InlineExecutor

from slamreplay.api.app import create_app
from slamreplay.api.cli.command import main
from slamreplay.api.service.auth import COOKIE, RECORD_PREFIX, RULES, STATE_CHANGING
from slamreplay.api.service.people import TOKEN_RE, PeopleError, hash_token
from slamreplay.api.service.settings import Settings
from slamreplay.api.service.store import Store


@pytest.fixture(scope="module")
def recording(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_tiny_recording(tmp_path_factory.mktemp("rec") / "tiny.mcap")


@pytest.fixture(scope="module")
def team(tmp_path_factory: pytest.TempPathFactory, recording: Path) -> Iterator[Team]:
    t, client = make_team(tmp_path_factory.mktemp("team"), recording)
    with client:
        seed(t, recording)
        yield t


# -- tokens ----------------------------------------------------------------------------------------


def test_tokens_are_never_stored_in_clear(tmp_path: Path) -> None:
    """The database (and its WAL) holds no token nor its secret part: a salted scrypt hash, a salt per user."""
    store = Store(tmp_path / "jobs.sqlite")
    tokens = [store.add_user(n, "runner") for n in ("alice", "bob")]
    store.new_user_token("bob")
    tokens.append(store.new_user_token("alice"))
    raw = b"".join(p.read_bytes() for p in tmp_path.iterdir() if p.is_file())
    for token in tokens:
        assert TOKEN_RE.fullmatch(token), token
        assert token.encode() not in raw and TOKEN_RE.fullmatch(token)["secret"].encode() not in raw  # type: ignore[index]
        assert hashlib.sha256(token.encode()).hexdigest().encode() not in raw
    with sqlite3.connect(tmp_path / "jobs.sqlite") as conn:
        rows = conn.execute("SELECT token_salt, token_hash, hash_params FROM users").fetchall()
    assert len({r[0] for r in rows}) == 2 and all(r[2] == "scrypt n=16384 r=8 p=1" for r in rows)
    assert store.user_of_token(tokens[-1]) is not None and store.user_of_token(tokens[0]) is None  # replaced


def test_a_token_check_costs_a_slow_hash_once(tmp_path: Path) -> None:
    """One check is a scrypt (tens of ms); the process then remembers the token for minutes, not the disk."""
    store = Store(tmp_path / "jobs.sqlite")
    token = store.add_user("alice", "viewer")
    t0 = time.perf_counter()
    assert store.user_of_token(token) is not None
    first = time.perf_counter() - t0
    t0 = time.perf_counter()
    for _ in range(20):
        assert store.user_of_token(token) is not None
    cached = (time.perf_counter() - t0) / 20
    slow = min(_timed(lambda: hash_token(token, b"s" * 16, n=1 << 14, r=8, p=1)) for _ in range(3))
    print(f"\nscrypt n=2^14 r=8 p=1: {slow * 1000:.1f} ms per check; cached: {cached * 1000:.2f} ms")
    assert first > 0.01 and cached < first / 5
    assert store.user_of_token(token[:-1] + ("A" if token[-1] != "A" else "B")) is None
    assert store.user_of_token("slr_000000000000_" + "x" * 43) is None and store.user_of_token("s3cret") is None


def _timed(f: object) -> float:
    t0 = time.perf_counter()
    f()  # type: ignore[operator]
    return time.perf_counter() - t0


def test_people_errors_say_what_to_do(tmp_path: Path) -> None:
    store = Store(tmp_path / "jobs.sqlite")
    store.add_user("alice", "admin")
    with pytest.raises(PeopleError, match="user alice exists: `users token alice`"):
        store.add_user("alice", "viewer")
    with pytest.raises(PeopleError, match="'a b' is not a user name"):
        store.add_user("a b", "viewer")
    with pytest.raises(PeopleError, match="'boss' is not a role: choose viewer"):
        store.add_user("bob", "boss")
    with pytest.raises(PeopleError, match="no user 'carol'"):
        store.set_disabled("carol", True)


# -- sign-in, sessions, sign-out ---------------------------------------------------------------------


def test_sign_in_sets_an_http_only_session_cookie_stored_hashed(team: Team) -> None:
    """The cookie is a random session id (HttpOnly, SameSite=Lax, Secure over https, a week); only its SHA-256 is
    stored, with the user and an expiry; the token itself never leaves the form."""
    client = TestClient(team.app)
    r = client.post("/login", data={"token": team.tokens["runner"], "next": "/runs"}, follow_redirects=False)
    assert r.status_code == 303 and r.headers["location"] == "/runs"
    header = r.headers["set-cookie"].lower()
    assert "httponly" in header and "samesite=lax" in header and "max-age=604800" in header
    assert "secure" not in header and team.tokens["runner"].lower() not in header
    cookie = r.cookies[COOKIE]
    with sqlite3.connect(team.store.path) as conn:
        row = conn.execute("SELECT user, expires - created FROM sessions WHERE id_hash = ?",
                           (hashlib.sha256(cookie.encode()).hexdigest(),)).fetchone()
        assert conn.execute("SELECT COUNT(*) FROM sessions WHERE id_hash = ?", (cookie,)).fetchone()[0] == 0
    assert row == ("rui", 7 * 86400)
    again = TestClient(team.app)
    again.cookies.set(COOKIE, cookie)
    assert again.post("/login", data={"token": team.tokens["admin"]}, follow_redirects=False).status_code == 303
    assert team.store.user_of_session(cookie) is None  # signing in over a session ends the old one
    https = TestClient(team.app, base_url="https://testserver")
    r = https.post("/login", data={"token": team.tokens["viewer"]}, follow_redirects=False)
    assert "secure" in r.headers["set-cookie"].lower()


def test_wrong_token_is_a_401_page_and_an_audit_entry(team: Team) -> None:
    client = TestClient(team.app)
    r = client.post("/login", data={"token": team.tokens["admin"][:-2] + "zz", "next": "/"}, follow_redirects=False)
    assert r.status_code == 401 and 'id="login-error"' in r.text and COOKIE not in r.cookies
    assert team.store.audit_entries(action="sign-in-failed", limit=1)[0].address == "testclient"
    assert "Sign in" in client.get("/login").text and "your own token" in client.get("/login").text


def test_pages_need_a_session_and_sign_out_ends_it(team: Team) -> None:
    """Without a session a page redirects to /login; sign-out (a form with its CSRF token) deletes the session on
    the server, so the old cookie no longer works; a sign-out without the token is refused."""
    client = TestClient(team.app)
    assert client.get("/", follow_redirects=False).headers["location"] == "/login?next=%2F"
    client, csrf = sign_in(client, team.tokens["viewer"])
    home = client.get("/")
    assert home.status_code == 200 and 'id="who">vic (viewer)' in home.text and page_csrf(home.text) == csrf
    cookie = client.cookies[COOKIE]
    assert client.post("/logout", data={}, follow_redirects=False).status_code == 403
    assert "Sign out" in client.get("/logout").text  # GET: a page with the button, no sign-out by a link
    r = client.post("/logout", data={"csrf": csrf}, follow_redirects=False)
    assert r.status_code == 303 and r.headers["location"] == "/login"
    stale = TestClient(team.app)
    stale.cookies.set(COOKIE, cookie)
    assert stale.get("/", follow_redirects=False).status_code == 303
    assert team.store.audit_entries(action="sign-out", limit=1)[0].who == "vic"


def test_expired_disabled_and_replaced_sessions_end(tmp_path: Path, recording: Path) -> None:
    """A session past its expiry, a disabled person and a replaced token are signed out at once, page and API."""
    t, _ = make_team(tmp_path, recording)
    page, _ = t.page("runner")
    assert page.get("/").status_code == 200
    with sqlite3.connect(t.store.path) as conn:
        conn.execute("UPDATE sessions SET expires = 1")
    assert page.get("/", follow_redirects=False).status_code == 303
    page, _ = t.page("runner")
    api = t.api("runner")
    assert api.get("/jobs").status_code == 200
    t.store.set_disabled("rui", True)
    assert page.get("/", follow_redirects=False).status_code == 303 and api.get("/jobs").status_code == 401
    t.store.set_disabled("rui", False)
    assert api.get("/jobs").status_code == 200
    page, _ = t.page("runner")
    new = t.store.new_user_token("rui")
    assert api.get("/jobs").status_code == 401 and page.get("/", follow_redirects=False).status_code == 303
    assert TestClient(t.app, headers={"Authorization": f"Bearer {new}"}).get("/jobs").status_code == 200


# -- CSRF ----------------------------------------------------------------------------------------------


def test_forms_posted_with_a_session_need_its_csrf_token(team: Team) -> None:
    """A form without the token, with another session's, or with a made-up one is a 403 page; the right one
    passes. Bearer calls need none."""
    job = team.jobs[0]
    runner, csrf = team.page("runner")
    _, other = team.page("runner")
    assert csrf != other
    page = runner.get(f"/ui/jobs/{job}/edit")
    assert page_csrf(page.text) == csrf
    for sent in ({}, {"csrf": other}, {"csrf": "0" * 64}):
        r = runner.post(f"/ui/jobs/{job}/edit", data={"name": "forged", **sent}, follow_redirects=False)
        assert r.status_code == 403 and "CSRF token" in r.text and "<h2>Not allowed (403)" in r.text, sent
    assert team.store.get_job(job).name != "forged"  # type: ignore[union-attr]
    ok = runner.post(f"/ui/jobs/{job}/edit", data={"name": "baseline", "csrf": csrf}, follow_redirects=False)
    assert ok.status_code == 303 and team.store.get_job(job).name == "baseline"  # type: ignore[union-attr]
    api = team.api("runner")
    assert api.post("/jobs", json={"recording_id": team.rid, "pipeline": "odometry", "seed": 9}).status_code == 202


def test_the_upload_form_checks_its_csrf_token_before_storing(team: Team, tmp_path: Path) -> None:
    runner, csrf = team.page("runner")
    other = write_tiny_recording(tmp_path / "other.mcap", seed=3)
    files = {"file": ("other.mcap", other.read_bytes(), "application/octet-stream")}
    before = len(team.store.list_recordings())
    assert runner.post("/ui/recordings", files=files, follow_redirects=False).status_code == 403
    assert runner.post("/ui/recordings", data={"csrf": "1" * 64}, files=files,
                       follow_redirects=False).status_code == 403
    assert len(team.store.list_recordings()) == before
    r = runner.post("/ui/recordings", data={"csrf": csrf}, files=files, follow_redirects=False)
    assert r.status_code == 303 and len(team.store.list_recordings()) == before + 1


def test_the_shared_token_mode_keeps_working_with_csrf(tmp_path: Path) -> None:
    """No people, SLAMREPLAY_TOKEN set: sign-in with it as before; its forms carry a CSRF token too."""
    app = create_app(Settings(allowed_hosts=("testserver",), data_dir=tmp_path, token="s3cret"),
                     executor=InlineExecutor())
    client = TestClient(app)
    assert "This server needs its token" in client.get("/login").text
    client, csrf = sign_in(client, "s3cret")
    home = client.get("/")
    assert "single user, shared token" in home.text and page_csrf(home.text) == csrf
    assert client.post("/ui/suites", data={"suite": "x"}, follow_redirects=False).status_code == 403
    r = client.post("/ui/suites", data={"suite": "x", "csrf": csrf}, follow_redirects=False)
    assert r.status_code == 422  # past the CSRF check: the suite itself is wrong


def test_an_open_server_says_so_and_needs_no_csrf(tmp_path: Path, recording: Path) -> None:
    """No people, no token: everything is open as before, the page says so, and the trail names anonymous."""
    with TestClient(create_app(Settings(allowed_hosts=("testserver",), data_dir=tmp_path, workers=1),
                               executor=InlineExecutor())) as client:
        home = client.get("/")
        assert "single user, no sign-in" in home.text and 'name="csrf"' not in home.text
        assert "Nothing to sign in to" in client.get("/login").text
        rid = client.post("/recordings", content=recording.read_bytes()).json()["id"]
        r = client.post("/ui/jobs", data={"recording_id": rid, "pipeline": "odometry", "seed": "0"},
                        follow_redirects=False)
        assert r.status_code == 303
        entries = app_store(client).audit_entries()
        assert [(e.who, e.action) for e in entries] == [("anonymous", "submit"), ("anonymous", "upload")]


def app_store(client: TestClient) -> Store:
    store: Store = client.app.state.jobs.store  # type: ignore[attr-defined]
    return store


def test_people_take_over_from_the_shared_token(tmp_path: Path) -> None:
    """Once someone is added (even while the server runs) the shared token no longer opens anything."""
    app = create_app(Settings(allowed_hosts=("testserver",), data_dir=tmp_path, token="s3cret"),
                     executor=InlineExecutor())
    shared = TestClient(app, headers={"Authorization": "Bearer s3cret"})
    assert shared.get("/jobs").status_code == 200
    token = app.state.jobs.store.add_user("ada", "admin")
    r = shared.get("/jobs")
    assert r.status_code == 401 and r.json()["detail"] == "wrong bearer token"
    assert TestClient(app).get("/jobs").json()["detail"].startswith("this server knows its people")
    assert TestClient(app, headers={"Authorization": f"Bearer {token}"}).get("/jobs").status_code == 200


def test_every_state_changing_route_has_a_rule(team: Team) -> None:
    """Each POST/PUT/PATCH/DELETE route is named in auth.RULES (or is a record route, or sign-in/out): a new one
    is seen here, not left to the default (admin only)."""
    found = []

    def walk(routes: list[object]) -> None:
        for r in routes:
            inner = getattr(r, "original_router", None)
            if inner is not None:
                walk(inner.routes)
            for method in getattr(r, "methods", None) or ():
                if method in STATE_CHANGING:
                    found.append((method, r.path))  # type: ignore[attr-defined]

    walk(team.app.routes)
    unnamed = [(m, p) for m, p in found if (m, p) not in RULES and not p.startswith(RECORD_PREFIX)
               and p not in ("/login", "/logout")]
    assert found and unnamed == []


# -- the people page ---------------------------------------------------------------------------------


def test_an_admin_manages_people_on_the_page(tmp_path: Path, recording: Path) -> None:
    """Add someone (their token shown once, not cached), change a role, disable, enable, a new token; each in the
    trail by the admin; the last active admin cannot be demoted or disabled."""
    t, _ = make_team(tmp_path, recording)
    admin, csrf = t.page("admin")
    r = admin.post("/ui/people", data={"name": "eve", "role": "runner", "csrf": csrf})
    token = re.search(r'id="token-value">(slr_[^<]+)<', r.text)
    assert r.status_code == 200 and token and r.headers["cache-control"] == "no-store"
    eve = TestClient(t.app, headers={"Authorization": f"Bearer {token.group(1)}"})
    assert eve.get("/jobs").status_code == 200 and "eve" in admin.get("/ui/people").text
    assert admin.post("/ui/people", data={"name": "eve", "role": "viewer", "csrf": csrf}).status_code == 422
    assert admin.post("/ui/people/eve", data={"do": "role", "role": "viewer", "csrf": csrf}).status_code == 200
    assert eve.post("/jobs", json={"recording_id": "0" * 64, "pipeline": "odometry"}).status_code == 403
    assert admin.post("/ui/people/eve", data={"do": "disable", "csrf": csrf}).status_code == 200
    assert eve.get("/jobs").status_code == 401
    assert admin.post("/ui/people/eve", data={"do": "enable", "csrf": csrf}).status_code == 200
    r = admin.post("/ui/people/eve", data={"do": "token", "csrf": csrf})
    assert eve.get("/jobs").status_code == 401 and 'id="token-value">slr_' in r.text
    last = admin.post("/ui/people/ada", data={"do": "role", "role": "runner", "csrf": csrf})
    assert last.status_code == 422 and "ada is the last active admin" in last.text
    assert admin.post("/ui/people/ada", data={"do": "disable", "csrf": csrf}).status_code == 422
    assert t.store.user("ada").role == "admin"  # type: ignore[union-attr]
    assert admin.post("/ui/people/eve", data={"do": "role", "role": "admin"}).status_code == 403  # no CSRF token
    trail = [(e.who, e.action, e.target) for e in reversed(t.store.audit_entries(who="ada"))
             if e.action.startswith("user-")]
    assert trail == [("ada", "user-add", "eve"), ("ada", "user-role", "eve"), ("ada", "user-disable", "eve"),
                     ("ada", "user-enable", "eve"), ("ada", "user-token", "eve")]
    text = "".join(p.read_bytes().decode("latin-1") for p in (tmp_path / "runs").glob("jobs.sqlite*"))
    assert token.group(1) not in text


def test_a_server_without_people_says_how_to_get_them(tmp_path: Path) -> None:
    client = TestClient(create_app(Settings(allowed_hosts=("testserver",), data_dir=tmp_path),
                                   executor=InlineExecutor()))
    assert 'id="no-people"' in client.get("/ui/people").text
    assert client.post("/ui/people", data={"name": "ada", "role": "admin"}).status_code == 409
    assert not Store(tmp_path / "runs" / "jobs.sqlite").has_people()


# -- slamreplay users -----------------------------------------------------------------------------------


def test_users_commands(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """add prints the token once (alone on stdout); list never shows tokens; disable, enable, role, token; each
    change in the audit trail by the account that ran it; errors are one line, exit 2."""
    data = str(tmp_path / "srv")
    assert main(["users", "list", "--data-dir", data]) == 2
    assert "no server data in" in capsys.readouterr().err
    assert main(["users", "add", "ada", "--role", "admin", "--data-dir", data]) == 0
    out, err = capsys.readouterr()
    token = out.strip()
    assert TOKEN_RE.fullmatch(token) and "shown once" in err
    assert main(["users", "add", "vic", "--role", "viewer", "--data-dir", data]) == 0
    capsys.readouterr()
    assert main(["users", "list", "--data-dir", data]) == 0
    listing = capsys.readouterr().out
    assert "ada" in listing and "admin" in listing and "slr_" not in listing and "active" in listing
    assert main(["users", "disable", "vic", "--data-dir", data]) == 0
    assert main(["users", "role", "vic", "runner", "--data-dir", data]) == 0
    assert main(["users", "enable", "vic", "--data-dir", data]) == 0
    assert main(["users", "token", "ada", "--data-dir", data]) == 0
    new = capsys.readouterr().out.strip()
    store = Store(Path(data) / "runs" / "jobs.sqlite")
    assert store.user_of_token(token) is None and store.user_of_token(new).name == "ada"  # type: ignore[union-attr]
    assert store.user("vic").role == "runner" and store.user("vic").active  # type: ignore[union-attr]
    actions = [e.action for e in reversed(store.audit_entries())]
    assert actions == ["user-add", "user-add", "user-disable", "user-role", "user-enable", "user-token"]
    assert all(e.address == "command line" and e.who.endswith("(command line)") for e in store.audit_entries())
    assert main(["users", "add", "ada", "--role", "viewer", "--data-dir", data]) == 2
    assert capsys.readouterr().err.strip() == ("slamreplay: error: user ada exists: `users token ada` gives them a "
                                               "new token, `users role ada ROLE` another role")
    assert main(["users", "disable", "nobody", "--data-dir", data]) == 2
    assert main(["users", "add", "x y", "--role", "viewer", "--data-dir", data]) == 2
