"""The API docs work offline: /docs and /redoc render in headless chromium with every other host unreachable."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any
from urllib.parse import urlsplit

import pytest
from web_site import LAPTOP, chromium, served

pytestmark = pytest.mark.browser
LOOPBACK = ("127.0.0.1", "localhost", "[::1]", "::1")


@pytest.fixture(scope="module")
def base(tmp_path_factory: pytest.TempPathFactory) -> Iterator[str]:
    with served(tmp_path_factory.mktemp("offline") / "data", workers=1) as url:
        yield url


@pytest.fixture
def offline(base: str) -> Iterator[Any]:
    """A page for which every host but this machine is cut off; ``page.elsewhere`` lists what it tried to reach."""
    with chromium() as browser:
        context = browser.new_context(viewport=LAPTOP)
        pg = context.new_page()
        pg.elsewhere, pg.problems = [], []

        def route(r: Any) -> None:
            if urlsplit(r.request.url).hostname in LOOPBACK:
                r.continue_()
            else:
                pg.elsewhere.append(r.request.url)
                r.abort("internetdisconnected")

        context.route("**/*", route)
        pg.on("console", lambda m: pg.problems.append(m.text) if m.type == "error" else None)
        pg.on("pageerror", lambda e: pg.problems.append(str(e)))
        yield pg
        context.close()


def test_swagger_ui_lists_the_operations_offline(offline: Any, base: str) -> None:
    """/docs draws every operation (POST /jobs among them) from files this server serves."""
    offline.goto(base + "/docs")
    offline.wait_for_selector(".opblock-summary", timeout=30_000)
    paths = offline.eval_on_selector_all(".opblock-summary-path", "els => els.map(e => e.textContent.trim())")
    assert "/jobs" in paths and "/recordings" in paths and len(paths) >= 15, paths
    assert offline.elsewhere == [], offline.elsewhere
    assert offline.problems == [], offline.problems


def test_redoc_lists_the_operations_offline(offline: Any, base: str) -> None:
    """/redoc draws the same API, also from files this server serves."""
    offline.goto(base + "/redoc")
    offline.locator("h2", has_text="Submit Job").wait_for(timeout=30_000)  # an operation's heading
    assert offline.locator("h2", has_text="Upload Recording").count() == 1
    assert offline.elsewhere == [], offline.elsewhere
    assert offline.problems == [], offline.problems


def test_favicon_is_served(offline: Any, base: str) -> None:
    """/favicon.ico (what browsers ask for by default) is the page's SVG icon."""
    r = offline.request.get(base + "/favicon.ico")
    assert r.ok and r.headers["content-type"].startswith("image/svg+xml") and b"<svg" in r.body()
