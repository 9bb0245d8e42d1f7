"""Every page of slamreplay's own in headless chromium, at laptop (1366x768) and phone (390x844) size.

Each page: a mobile viewport and the favicon, no console error, no sideways scroll on a phone,
no serious or critical accessibility violation (axe-core, from axe-playwright-python), and a
screenshot at both sizes in results/web-shots/ (kept by CI). Then a running job cancelled from its
page, and the embedded Rerun viewer at its quiet console level.
"""

from __future__ import annotations

import re
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
from web_site import LAPTOP, PHONE, README_IMAGES, call, chromium, readme_picture, seed_runs, served, shoot, wait_until

pytestmark = pytest.mark.browser
PAGES: dict[str, Callable[[dict[str, str]], str]] = {
    "login": lambda ids: "/login",
    "home": lambda ids: "/",
    "runs": lambda ids: "/runs?cols=ape_rmse_m,rpe_step_trans_rmse_m",
    "job-succeeded": lambda ids: f"/ui/jobs/{ids['baseline']}",
    "job-dslam": lambda ids: f"/ui/jobs/{ids['dslam_tuned']}",
    "job-failed": lambda ids: f"/ui/jobs/{ids['failed']}",
    "job-running": lambda ids: f"/ui/jobs/{ids['running']}",
    "job-edit": lambda ids: f"/ui/jobs/{ids['baseline']}/edit",
    "suite": lambda ids: f"/ui/suites/{ids['suite']}",
    "suite-history": lambda ids: "/ui/history/nightly%20odometry",  # the suite's metrics over the versions it ran on
    "suite-history-by-date": lambda ids: "/ui/history/nightly%20odometry?by=date",  # ... over the days it ran
    "compare": lambda ids: f"/ui/compare?a={ids['baseline']}&b={ids['worn']}",
    "compare-runs": lambda ids: f"/ui/compare?runs={ids['baseline']},{ids['worn']}",
    "compare-selected": lambda ids: f"/ui/runs/compare?sel={ids['baseline']}&sel={ids['dslam']}",
}
README = {"runs": "web-runs", "job-dslam": "web-job", "compare-runs": "web-compare"}


@pytest.fixture(scope="module")
def site(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[str, dict[str, str]]]:
    """The served app with runs of every kind (tests/web/web_site.py): its base URL and the ids."""
    folder = tmp_path_factory.mktemp("site")
    with served(folder / "data") as base:
        yield base, seed_runs(base, folder)


@pytest.fixture(scope="module")
def context() -> Iterator[Any]:
    with chromium() as browser:
        ctx = browser.new_context(viewport=LAPTOP)
        ctx.set_default_timeout(30_000)
        yield ctx
        ctx.close()


@pytest.fixture
def page(context: Any) -> Iterator[Any]:
    """A fresh tab; ``page.problems`` collects console errors and uncaught exceptions."""
    pg = context.new_page()
    pg.problems = []
    pg.on("console", lambda m: pg.problems.append(f"console.{m.type}: {m.text}") if m.type == "error" else None)
    pg.on("pageerror", lambda e: pg.problems.append(f"uncaught: {e}"))
    yield pg
    pg.close()


def open_page(page: Any, site: tuple[str, dict[str, str]], name: str) -> None:
    base, ids = site
    response = page.goto(base + PAGES[name](ids))
    assert response is not None and response.ok, (name, response and response.status)
    page.wait_for_load_state("load")


@pytest.mark.parametrize("name", list(PAGES))
def test_page_works_at_laptop_and_phone_size(page: Any, site: tuple[str, dict[str, str]], name: str) -> None:
    """A mobile viewport and a favicon that loads; no console error; at 390 px nothing scrolls sideways."""
    open_page(page, site, name)
    head = page.evaluate("""() => ({viewport: document.querySelector('meta[name=viewport]')?.content,
                                     icon: document.querySelector('link[rel~=icon]')?.getAttribute('href')})""")
    assert "width=device-width" in (head["viewport"] or ""), f"{name}: no mobile viewport"
    assert head["icon"] and page.request.get(site[0] + head["icon"]).ok, f"{name}: no favicon"
    for path in shoot(page, name):
        assert path.stat().st_size > 1000
    page.set_viewport_size(PHONE)
    wide = page.evaluate("document.documentElement.scrollWidth")
    assert wide <= PHONE["width"], f"{name}: {wide} px wide at {PHONE['width']} px: the page scrolls sideways"
    if README_IMAGES and name in README:
        readme_images(page, README[name])
    page.wait_for_timeout(300)  # a late error (a live refresh) is still caught
    assert page.problems == [], page.problems


def readme_images(page: Any, name: str) -> None:
    """The docs' screenshots of this page: what fits the screen at laptop and phone size (``NAME-laptop``...)."""
    for size, tag in ((LAPTOP, "laptop"), (PHONE, "phone")):
        page.set_viewport_size(size)
        page.wait_for_timeout(50)
        readme_picture(page, f"{name}-{tag}")
    page.set_viewport_size(LAPTOP)


@pytest.mark.parametrize("scheme", ["light", "dark"])
@pytest.mark.parametrize("name", list(PAGES))
def test_page_has_no_serious_accessibility_violation(page: Any, site: tuple[str, dict[str, str]], name: str,
                                                     scheme: str) -> None:
    """axe-core finds no violation of impact "serious" or "critical" (contrast, names, labels, landmarks...), in the
    light and the dark scheme (the page follows the system's)."""
    axe = pytest.importorskip("axe_playwright_python.sync_playwright", reason="pip install -e '.[browser]'")
    page.emulate_media(color_scheme=scheme)
    open_page(page, site, name)
    # no live refresh during the scan (a running job's block is swapped every 2 s): axe would lose its nodes
    page.evaluate("document.querySelectorAll('[data-live]').forEach(el => el.removeAttribute('data-live'))")
    results = axe.Axe().run(page)
    bad = [f"{v['id']} ({v['impact']}): {v['help']}: " + "; ".join(" ".join(n["target"]) for n in v["nodes"][:5])
           for v in results.response["violations"] if v["impact"] in ("serious", "critical")]
    assert bad == [], "\n".join(bad)


def test_cancel_a_running_job_from_its_page(page: Any, site: tuple[str, dict[str, str]]) -> None:
    """A running job shows its percent and elapsed time; Cancel asks first, then the job is cancelled."""
    base, ids = site
    job = ids["running"]
    open_page(page, site, "job-running")
    assert page.inner_text("#job-status").strip() == "running"
    assert re.fullmatch(r"\d+ %", page.inner_text("#job-progress").strip())
    page.click("#cancel-job")
    page.wait_for_url(re.compile(rf"/ui/jobs/{job}/cancel\?"))
    assert "Cancel this job?" in page.inner_text("#job-action")
    page.click("#confirm-form button[type=submit]")
    page.wait_for_url(re.compile(rf"/ui/jobs/{job}$"))
    assert page.inner_text("#job-status").strip() == "cancelled"
    assert not page.is_visible("#cancel-job")
    assert wait_until(base, job, ("cancelled",), timeout_s=10)["status"] == "cancelled"
    assert call(base, "GET", f"/jobs/{job}")["status"] == "cancelled"
    assert page.problems == [], page.problems


def test_embedded_viewer_logs_quietly(page: Any, site: tuple[str, dict[str, str]]) -> None:
    """Open in Rerun: the viewer draws the run and logs warnings only (it logged about 11,000 debug lines)."""
    base, ids = site
    page.goto(f"{base}/ui/jobs/{ids['baseline']}")
    href = page.get_attribute("#open-rerun", "href")
    assert href is not None
    lines: list[tuple[str, str]] = []
    page.on("console", lambda m: lines.append((m.type, m.text)))
    page.goto(base + href)
    page.wait_for_selector("#the_canvas_id.visible", timeout=90_000)
    page.wait_for_timeout(3000)  # it loads and draws the recording
    chatter = [text for kind, text in lines if kind not in ("warning", "error")]
    assert chatter == [] and len(lines) < 50, (len(lines), chatter[:5])
    assert page.problems == [], page.problems  # its usage statistics and version check no longer fail in the console


def test_only_the_servers_own_scripts_run(page: Any, site: tuple[str, dict[str, str]]) -> None:
    """The pages' Content-Security-Policy (issue 40): markup that reached a page with an inline script or event
    handler (as text a user wrote would, were escaping ever to fail) does not run, while the page's own script does
    (web.js, the live refresh, loads)."""
    base, _ = site
    page.goto(base + "/runs")
    page.evaluate("""() => {
        window.ran = [];
        document.body.insertAdjacentHTML('beforeend', '<img src="/nothing.png" onerror="window.ran.push(1)">');
        const s = document.createElement('script'); s.textContent = 'window.ran.push(2)'; document.body.append(s);
    }""")
    page.wait_for_timeout(500)
    assert page.evaluate("window.ran") == []
    assert any("Content Security Policy" in p for p in page.problems), page.problems  # chromium says why
    assert page.evaluate("performance.getEntriesByName(location.origin + '/static/web.js').length") == 1


def test_another_site_cannot_frame_the_delete_page(page: Any, site: tuple[str, dict[str, str]],
                                                   tmp_path: Path) -> None:
    """Clickjacking (issue 40): a page on another origin frames /ui/jobs/ID/delete under a decoy button; chromium
    refuses to show it (frame-ancestors 'none'), so the click lands on nothing of ours and the job stays."""
    import http.server
    import threading

    base, ids = site
    job = ids["worn"]
    (tmp_path / "decoy.html").write_text(
        "<!doctype html><title>free GPU hours</title><button id=decoy>Click HERE for free GPU hours</button>"
        f"<iframe id=victim src='{base}/ui/jobs/{job}/delete' style='opacity:0.01;position:absolute;top:0;"
        "left:0;width:800px;height:600px'></iframe>")
    handler = lambda *a: http.server.SimpleHTTPRequestHandler(*a, directory=str(tmp_path))  # noqa: E731
    decoy = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
    threading.Thread(target=decoy.serve_forever, daemon=True).start()
    try:
        page.goto(f"http://127.0.0.1:{decoy.server_address[1]}/decoy.html")
        page.wait_for_load_state("load")
        victim = next(f for f in page.frames if f != page.main_frame)
        assert "/ui/jobs/" not in victim.url or victim.evaluate("document.body.innerText") == "", victim.url
        assert victim.query_selector("#confirm-form") is None
        page.mouse.click(400, 300)
        page.wait_for_timeout(500)
    finally:
        decoy.shutdown()
    assert call(base, "GET", f"/jobs/{job}")["status"] == "succeeded"
