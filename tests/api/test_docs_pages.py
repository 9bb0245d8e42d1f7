"""The API docs pages (/docs, /redoc) load only files this server serves, from the installed package."""

from __future__ import annotations

import re
import warnings
from pathlib import Path

import pytest

with warnings.catch_warnings():
    warnings.simplefilter("ignore", UserWarning)  # StarletteDeprecationWarning: it asks for httpx2; httpx works
    from fastapi.testclient import TestClient

from slamreplay.api.app import create_app
from slamreplay.api.service.settings import Settings

REFERENCE = re.compile(r"""(?:src|href)\s*=\s*["']([^"']+)["']|url:\s*["']([^"']+)["']|spec-url=["']([^"']+)["']""")


@pytest.fixture(scope="module")
def client(tmp_path_factory: pytest.TempPathFactory) -> TestClient:
    return TestClient(create_app(Settings(allowed_hosts=("testserver",), data_dir=tmp_path_factory.mktemp("d"))))


def references(html: str) -> list[str]:
    """Every URL a page loads: src and href attributes, Swagger UI's ``url:`` and ReDoc's ``spec-url``."""
    return [next(g for g in m.groups() if g) for m in REFERENCE.finditer(html)]


@pytest.mark.parametrize("page", ["/docs", "/redoc"])
def test_docs_pages_reference_this_server_only(client: TestClient, page: str) -> None:
    """No CDN, no web fonts, no favicon from fastapi.tiangolo.com: every URL is a path on this server."""
    r = client.get(page)
    assert r.status_code == 200 and r.headers["content-type"].startswith("text/html")
    urls = references(r.text)
    assert urls, r.text
    assert all(u.startswith("/") and not u.startswith("//") for u in urls), urls
    assert "http://" not in r.text and "https://" not in r.text
    assert "/openapi.json" in urls and "/favicon.ico" in urls


@pytest.mark.parametrize(("page", "assets"), [
    ("/docs", {"swagger-ui-bundle.js": "javascript", "swagger-ui.css": "text/css"}),
    ("/redoc", {"redoc.standalone.js": "javascript"}),
])
def test_docs_assets_are_served_with_their_types(client: TestClient, page: str, assets: dict[str, str]) -> None:
    """Each script and style sheet the page names answers 200, with a JavaScript or CSS content type."""
    urls = references(client.get(page).text)
    for name, kind in assets.items():
        (url,) = [u for u in urls if u.endswith("/" + name)]
        r = client.get(url)
        assert r.status_code == 200, url
        assert kind in r.headers["content-type"], (url, r.headers["content-type"])
        assert len(r.content) > 100_000  # the real bundle, not a stub
        assert b"https://cdn." not in r.content  # ReDoc's logo, from its CDN, is an empty image here
    assert client.get("/openapi.json").json()["info"]["title"] == "slamreplay"
    assert client.get("/favicon.ico").status_code == 200


def test_docs_are_off_with_a_token(tmp_path: Path) -> None:
    """A browser cannot send the bearer token from the docs page, so a guarded server has none."""
    guarded = TestClient(create_app(Settings(allowed_hosts=("testserver",), data_dir=tmp_path, token="s3cret")))
    assert guarded.get("/docs").status_code == 404
    assert guarded.get("/redoc").status_code == 404
    assert guarded.get("/docs/assets/swagger-ui.css").status_code == 404
