"""People of a shared server: who they are (users with a role), how they sign in (tokens, sessions), what they
changed (the audit trail) and which runs they deleted (tombstones); the store's part of it.

A token is ``slr_<id>_<secret>``: the id (12 hex digits) finds its user's row, the secret is 32 random bytes.
The store keeps the id and a slow hash of the whole token (scrypt, a salt per user, its parameters beside
it), never the token: one check costs tens of milliseconds (``TOKEN_COST``), so a server's process keeps
the tokens it checked in memory for a few minutes (`TokenCache`), keyed by their SHA-256, never on disk.
A page session's cookie holds a random id; the store keeps its SHA-256 (the id is as random as a key, so a
fast hash suffices), the user and an expiry.

`PeopleMixin` is a base of `slamreplay.api.service.store.Store` (which provides the connections), like
`slamreplay.api.service.store_runs.RunsTableMixin`. A server with no row in ``users`` has no people: it keeps the
single-user modes (``slamreplay.api.service.auth``).
"""

from __future__ import annotations

import hashlib
import hmac
import re
import secrets
import sqlite3
import threading
import time
from contextlib import AbstractContextManager
from dataclasses import dataclass
from typing import Literal, get_args

Role = Literal["viewer", "runner", "admin"]
ROLES: tuple[Role, ...] = get_args(Role)
RANK: dict[str, int] = {r: i for i, r in enumerate(ROLES)}  # each role may do what the ones before it may
NAME_RE = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]{0,39}")
TOKEN_RE = re.compile(r"slr_(?P<id>[0-9a-f]{12})_(?P<secret>[A-Za-z0-9_-]{43})")
# scrypt's cost: n=2**14, r=8 (16 MiB, tens of ms per check); stored per user, so it can be raised later
TOKEN_COST = {"n": 1 << 14, "r": 8, "p": 1}
SESSION_TTL_S = 7 * 86400  # a page session lasts a week from sign-in; signing out, a new token or disabling ends it
CACHE_TTL_S = 300.0

SCHEMA = """
CREATE TABLE IF NOT EXISTS users (
    name TEXT PRIMARY KEY,
    role TEXT NOT NULL,             -- viewer | runner | admin
    token_id TEXT NOT NULL UNIQUE,  -- the public part of the token: finds the row
    token_salt BLOB NOT NULL,
    token_hash BLOB NOT NULL,       -- scrypt of the whole token under token_salt, with hash_params
    hash_params TEXT NOT NULL,      -- "scrypt n=16384 r=8 p=1"
    created REAL NOT NULL,
    disabled REAL                   -- when it was disabled; NULL: active
);
CREATE TABLE IF NOT EXISTS sessions (
    id_hash TEXT PRIMARY KEY,       -- sha256 (hex) of the cookie's value; the value itself is never stored
    user TEXT NOT NULL,
    created REAL NOT NULL,
    expires REAL NOT NULL,
    address TEXT
);
CREATE INDEX IF NOT EXISTS sessions_user ON sessions (user);
CREATE TABLE IF NOT EXISTS audit (
    seq INTEGER PRIMARY KEY AUTOINCREMENT,
    at REAL NOT NULL,
    who TEXT NOT NULL,
    address TEXT NOT NULL,
    action TEXT NOT NULL,
    target TEXT,                    -- a job, suite or recording id, or a user's name
    detail TEXT
);
CREATE INDEX IF NOT EXISTS audit_target ON audit (target, seq);
CREATE INDEX IF NOT EXISTS audit_who ON audit (who, seq);
CREATE INDEX IF NOT EXISTS audit_action ON audit (action, seq);
CREATE TABLE IF NOT EXISTS tombstones (
    job_id TEXT PRIMARY KEY,
    who TEXT NOT NULL,
    at REAL NOT NULL,
    address TEXT NOT NULL,
    pipeline TEXT NOT NULL,
    recording_id TEXT NOT NULL,
    seed INTEGER NOT NULL,
    name TEXT
);
CREATE TABLE IF NOT EXISTS server_secrets (
    name TEXT PRIMARY KEY,
    value BLOB NOT NULL
);
"""
# Every action the trail records, in the words the audit page filters by.
ACTIONS = ("upload", "recover", "record", "delete-recording", "submit", "push", "cancel", "label", "delete", "suite",
           "run-on-commit", "sign-in", "sign-in-failed", "sign-out", "user-add", "user-disable", "user-enable",
           "user-role", "user-token")


class PeopleError(ValueError):
    """A bad name or role, an unknown user, a name taken: the message says what to do."""


@dataclass(frozen=True, slots=True)
class User:
    name: str
    role: Role
    token_id: str
    created: float
    disabled: float | None

    @property
    def active(self) -> bool:
        return self.disabled is None


@dataclass(frozen=True, slots=True)
class AuditEntry:
    seq: int
    at: float
    who: str
    address: str
    action: str
    target: str | None
    detail: str | None


@dataclass(frozen=True, slots=True)
class Tombstone:
    """What is left of a deleted run: who deleted it, when and from where, and what it was."""

    job_id: str
    who: str
    at: float
    address: str
    pipeline: str
    recording_id: str
    seed: int
    name: str | None

    @property
    def text(self) -> str:
        """``deleted by alice at 2025-05-01 12:00 UTC``."""
        return f"deleted by {self.who} at {time.strftime('%Y-%m-%d %H:%M', time.gmtime(self.at))} UTC"


def check_name(name: str) -> str:
    if not NAME_RE.fullmatch(name):
        raise PeopleError(f"{name!r} is not a user name: 1 to 40 letters, digits, '.', '_' or '-', starting with a "
                          "letter or digit")
    return name


def check_role(role: str) -> Role:
    if role not in ROLES:
        raise PeopleError(f"{role!r} is not a role: choose viewer (reads), runner (uploads, submits, cancels, labels) "
                          "or admin (also deletes and manages people)")
    return role


def new_token() -> tuple[str, str]:
    """(token, its id): ``slr_<12 hex>_<43 characters of base64url>`` (256 random bits)."""
    token_id = secrets.token_hex(6)
    return f"slr_{token_id}_{secrets.token_urlsafe(32)}", token_id


def hash_token(token: str, salt: bytes, n: int, r: int, p: int) -> bytes:
    """scrypt of the token (the slow hash the store keeps)."""
    return hashlib.scrypt(token.encode(), salt=salt, n=n, r=r, p=p, dklen=32, maxmem=(n * r * 128) * 2)


def _params_text(cost: dict[str, int]) -> str:
    return f"scrypt n={cost['n']} r={cost['r']} p={cost['p']}"


def _parse_params(text: str) -> dict[str, int]:
    kind, *pairs = text.split()
    if kind != "scrypt":
        raise ValueError(f"unknown token hash {kind!r}")
    return {k: int(v) for k, v in (p.split("=", 1) for p in pairs)}


def session_hash(session_id: str) -> str:
    return hashlib.sha256(session_id.encode()).hexdigest()


def _user(row: sqlite3.Row) -> User:
    return User(row["name"], row["role"], row["token_id"], row["created"], row["disabled"])


class TokenCache:
    """Tokens this process checked recently: SHA-256 of the token -> (stored hash it matched, until when).

    A hit still needs the user's current row to hold that same stored hash (a new token or a disabled user
    takes effect at once); only the slow hash is skipped. Memory only, at most ``size`` entries."""

    def __init__(self, size: int = 1024, ttl_s: float = CACHE_TTL_S) -> None:
        self.size, self.ttl_s = size, ttl_s
        self._lock = threading.Lock()
        self._seen: dict[str, tuple[bytes, float]] = {}

    def hit(self, token: str, stored: bytes) -> bool:
        key = hashlib.sha256(token.encode()).hexdigest()
        with self._lock:
            got = self._seen.get(key)
        return got is not None and got[1] > time.monotonic() and hmac.compare_digest(got[0], stored)

    def add(self, token: str, stored: bytes) -> None:
        key = hashlib.sha256(token.encode()).hexdigest()
        with self._lock:
            if len(self._seen) >= self.size:
                now = time.monotonic()
                self._seen = {k: v for k, v in self._seen.items() if v[1] > now}
                if len(self._seen) >= self.size:
                    self._seen.clear()
            self._seen[key] = (stored, time.monotonic() + self.ttl_s)


class PeopleMixin:
    """Store methods of people, sessions, the audit trail and tombstones; ``Store`` provides the connections."""

    token_cache: TokenCache

    def _read(self) -> AbstractContextManager[sqlite3.Connection]:
        raise NotImplementedError

    def _tx(self) -> AbstractContextManager[sqlite3.Connection]:
        raise NotImplementedError

    # -- users ---------------------------------------------------------------------------------

    def has_people(self) -> bool:
        """Whether anyone was ever added: then every request needs a person's token or session."""
        with self._read() as conn:
            return conn.execute("SELECT 1 FROM users LIMIT 1").fetchone() is not None

    def users(self) -> list[User]:
        with self._read() as conn:
            return [_user(r) for r in conn.execute("SELECT * FROM users ORDER BY name")]

    def user(self, name: str) -> User | None:
        with self._read() as conn:
            row = conn.execute("SELECT * FROM users WHERE name = ?", (name,)).fetchone()
        return None if row is None else _user(row)

    def _set_token(self, conn: sqlite3.Connection, name: str, role: Role | None) -> str:
        token, token_id = new_token()
        salt = secrets.token_bytes(16)
        digest = hash_token(token, salt, **TOKEN_COST)
        if role is None:
            conn.execute("UPDATE users SET token_id = ?, token_salt = ?, token_hash = ?, hash_params = ? "
                         "WHERE name = ?", (token_id, salt, digest, _params_text(TOKEN_COST), name))
        else:
            conn.execute("INSERT INTO users (name, role, token_id, token_salt, token_hash, hash_params, created) "
                         "VALUES (?, ?, ?, ?, ?, ?, ?)",
                         (name, role, token_id, salt, digest, _params_text(TOKEN_COST), time.time()))
        conn.execute("DELETE FROM sessions WHERE user = ?", (name,))  # a new token: sessions of the old one end
        return token

    def add_user(self, name: str, role: str) -> str:
        """Add a person; their token (shown once: only its hash is kept). PeopleError for a bad or taken name."""
        name, checked = check_name(name), check_role(role)
        with self._tx() as conn:
            if conn.execute("SELECT 1 FROM users WHERE name = ?", (name,)).fetchone() is not None:
                raise PeopleError(f"user {name} exists: `users token {name}` gives them a new token, "
                                  f"`users role {name} ROLE` another role")
            return self._set_token(conn, name, checked)

    def new_user_token(self, name: str) -> str:
        """A new token for ``name`` (the old one stops working, their page sessions end)."""
        with self._tx() as conn:
            self._known(conn, name)
            return self._set_token(conn, name, None)

    def set_disabled(self, name: str, disabled: bool) -> None:
        """Disable (their token and sessions stop working at once) or enable a person."""
        with self._tx() as conn:
            self._known(conn, name)
            conn.execute("UPDATE users SET disabled = ? WHERE name = ?", (time.time() if disabled else None, name))
            if disabled:
                conn.execute("DELETE FROM sessions WHERE user = ?", (name,))

    def set_role(self, name: str, role: str) -> None:
        checked = check_role(role)
        with self._tx() as conn:
            self._known(conn, name)
            conn.execute("UPDATE users SET role = ? WHERE name = ?", (checked, name))

    def _known(self, conn: sqlite3.Connection, name: str) -> None:
        if conn.execute("SELECT 1 FROM users WHERE name = ?", (name,)).fetchone() is None:
            raise PeopleError(f"no user {name!r}: `slamreplay users list` lists them")

    def user_of_token(self, token: str) -> User | None:
        """The active user whose token this is, or None (unknown, wrong, or disabled). Slow (scrypt) unless this
        process checked the same token in the last minutes."""
        token = token.strip()
        m = TOKEN_RE.fullmatch(token)
        if m is None:
            return None
        with self._read() as conn:
            row = conn.execute("SELECT * FROM users WHERE token_id = ? AND disabled IS NULL",
                               (m["id"],)).fetchone()
        if row is None:
            return None
        stored = bytes(row["token_hash"])
        if self.token_cache.hit(token, stored):
            return _user(row)
        try:
            digest = hash_token(token, bytes(row["token_salt"]), **_parse_params(row["hash_params"]))
        except ValueError:
            return None
        if not hmac.compare_digest(digest, stored):
            return None
        self.token_cache.add(token, stored)
        return _user(row)

    # -- sessions ------------------------------------------------------------------------------

    def open_session(self, name: str, address: str, ttl_s: float = SESSION_TTL_S) -> str:
        """A new page session of ``name``: the cookie's value (only its hash is stored). Ended ones are swept."""
        session_id = secrets.token_urlsafe(32)
        now = time.time()
        with self._tx() as conn:
            conn.execute("DELETE FROM sessions WHERE expires < ?", (now,))
            conn.execute("INSERT INTO sessions (id_hash, user, created, expires, address) VALUES (?, ?, ?, ?, ?)",
                         (session_hash(session_id), name, now, now + ttl_s, address))
        return session_id

    def user_of_session(self, session_id: str) -> User | None:
        """The active user of an unexpired session, or None."""
        if not session_id or len(session_id) > 100:
            return None
        with self._read() as conn:
            row = conn.execute("SELECT u.* FROM sessions s JOIN users u ON u.name = s.user WHERE s.id_hash = ? "
                               "AND s.expires > ? AND u.disabled IS NULL",
                               (session_hash(session_id), time.time())).fetchone()
        return None if row is None else _user(row)

    def close_session(self, session_id: str) -> None:
        with self._tx() as conn:
            conn.execute("DELETE FROM sessions WHERE id_hash = ?", (session_hash(session_id),))

    def server_secret(self, name: str) -> bytes:
        """A random secret of this data directory (made on first use), e.g. the key of the viewer's .rrd links."""
        with self._read() as conn:
            row = conn.execute("SELECT value FROM server_secrets WHERE name = ?", (name,)).fetchone()
        if row is not None:
            return bytes(row[0])
        with self._tx() as conn:
            conn.execute("INSERT OR IGNORE INTO server_secrets (name, value) VALUES (?, ?)",
                         (name, secrets.token_bytes(32)))
            return bytes(conn.execute("SELECT value FROM server_secrets WHERE name = ?", (name,)).fetchone()[0])

    # -- the audit trail -------------------------------------------------------------------------

    def add_audit(self, who: str, address: str, action: str, target: str | None = None,
                  detail: str | None = None) -> None:
        with self._tx() as conn:
            conn.execute("INSERT INTO audit (at, who, address, action, target, detail) VALUES (?, ?, ?, ?, ?, ?)",
                         (time.time(), who, address, action, target, None if detail is None else detail[:2000]))

    def audit_entries(self, *, who: str | None = None, action: str | None = None, since: float | None = None,
                      target: str | None = None, before: int | None = None, limit: int = 200) -> list[AuditEntry]:
        """Newest first, filtered by whichever arguments are given (``before``: entries older than that seq)."""
        where, args = [], []
        for clause, value in (("who = ?", who), ("action = ?", action), ("at >= ?", since), ("target = ?", target),
                              ("seq < ?", before)):
            if value is not None:
                where.append(clause)
                args.append(value)
        sql = "SELECT * FROM audit" + (" WHERE " + " AND ".join(where) if where else "") + " ORDER BY seq DESC LIMIT ?"
        with self._read() as conn:
            rows = conn.execute(sql, (*args, limit)).fetchall()
        return [AuditEntry(r["seq"], r["at"], r["who"], r["address"], r["action"], r["target"], r["detail"])
                for r in rows]

    def failed_sign_ins(self, address: str, since: float) -> tuple[int, float | None]:
        """How many sign-ins failed from ``address`` since ``since``, and when the oldest of them was."""
        with self._read() as conn:
            row = conn.execute("SELECT COUNT(*), MIN(at) FROM audit WHERE action = 'sign-in-failed' AND address = ? "
                               "AND at >= ?", (address, since)).fetchone()
        return int(row[0]), row[1]

    def audit_people(self) -> list[str]:
        """Everyone the trail names, by name."""
        with self._read() as conn:
            return [r[0] for r in conn.execute("SELECT DISTINCT who FROM audit ORDER BY who")]

    # -- tombstones ------------------------------------------------------------------------------

    def tombstone(self, job_id: str) -> Tombstone | None:
        with self._read() as conn:
            row = conn.execute("SELECT * FROM tombstones WHERE job_id = ?", (job_id,)).fetchone()
        return None if row is None else Tombstone(row["job_id"], row["who"], row["at"], row["address"],
                                                   row["pipeline"], row["recording_id"], row["seed"], row["name"])
