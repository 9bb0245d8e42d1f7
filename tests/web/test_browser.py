"""The web page in a real browser: Debian's headless chromium driven by Playwright (``make test-browser``).

One server (``slamreplay serve`` with a token, over a fresh data directory) and one browser for
the module; the tests run in order, as a person would: log in, upload through the form, run a
job and watch it finish, compare it with a worse one (a regression, in red), and open the job
in the Rerun web viewer the service serves.
"""

from __future__ import annotations

import os
import re
import shutil
import socket
import subprocess
import sys
import time
import urllib.request
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from conftest import write_tiny_recording
from patience import deadline as give_up_at
from web_site import readme_picture

pytestmark = pytest.mark.browser
CHROMIUM = os.environ.get("SLAMREPLAY_CHROMIUM", "/usr/bin/chromium")
TOKEN = "browser-test-token"
SHOTS = Path(os.environ.get("SLAMREPLAY_BROWSER_SHOTS", "")) if os.environ.get("SLAMREPLAY_BROWSER_SHOTS") else None


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port: int = s.getsockname()[1]
        return port


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[str]:
    """``slamreplay serve`` on a free loopback port with a token; its base URL."""
    data = tmp_path_factory.mktemp("web") / "data"  # not there yet: serve creates it
    port = _free_port()
    env = {**os.environ, "SLAMREPLAY_TOKEN": TOKEN}
    log = open(data.parent / "serve.log", "w")  # noqa: SIM115 (closed below)
    proc = subprocess.Popen([sys.executable, "-m", "slamreplay.api.cli", "serve", "--port", str(port),
                             "--data-dir", str(data),
                             "--workers", "1"], env=env, stdout=log, stderr=subprocess.STDOUT)
    base = f"http://127.0.0.1:{port}"
    try:
        deadline = give_up_at(60)
        while True:
            try:
                urllib.request.urlopen(base + "/healthz", timeout=2)
                break
            except OSError:
                if proc.poll() is not None or time.monotonic() > deadline:
                    log_text = (data.parent / "serve.log").read_text()
                    raise AssertionError(f"the server did not start: {log_text}") from None
                time.sleep(0.2)
        yield base
    finally:
        proc.terminate()
        proc.wait(20)
        log.close()


@pytest.fixture(scope="module")
def page(server: str) -> Iterator[Any]:
    """One headless chromium page (Debian's browser; Playwright downloads none)."""
    sync_api = pytest.importorskip("playwright.sync_api", reason="pip install -e '.[browser]' (make test-browser)")
    if not shutil.which(CHROMIUM):
        pytest.fail(f"{CHROMIUM} not found: apt-get install chromium (make test-browser does)")
    with sync_api.sync_playwright() as p:
        browser = p.chromium.launch(executable_path=CHROMIUM, args=["--no-sandbox"])
        context = browser.new_context(viewport={"width": 1400, "height": 900})
        pg = context.new_page()
        pg.set_default_timeout(30_000)
        yield pg
        context.close()
        browser.close()


def shot(page: Any, name: str) -> None:
    if SHOTS is not None:
        SHOTS.mkdir(parents=True, exist_ok=True)
        page.screenshot(path=str(SHOTS / f"{name}.png"), full_page=True)


def upload_and_run(page: Any, server: str, recording: Path) -> str:
    """Upload ``recording`` through the form, run odometry on it, wait (live status) for it to succeed; the job id."""
    page.goto(server + "/")
    page.set_input_files("#upload-form input[name=file]", str(recording))
    page.click("#upload-form button")
    page.wait_for_url(re.compile(r"/\?uploaded=[0-9a-f]{64}"))
    rid = page.url.split("uploaded=")[1][:64]
    assert rid in page.inner_text("#flash")
    assert recording.name in page.inner_text("#recordings-table")
    page.select_option("#job-form select[name=recording_id]", rid)
    page.select_option("#job-form select[name=pipeline]", "odometry")
    page.click("#job-form button")
    page.wait_for_url(re.compile(r"/ui/jobs/[0-9a-f]{32}$"))
    job_id = page.url.rsplit("/", 1)[1]
    # No reload: web.js swaps the live block until the job has ended.
    page.wait_for_function("() => document.querySelector('#job-status').textContent.trim() === 'succeeded'",
                           timeout=90_000)
    assert "ape_rmse_m" in page.inner_text("#metrics-table")
    return job_id


def test_login_asks_for_the_token(page: Any, server: str) -> None:
    page.goto(server + "/")
    assert "/login" in page.url and "needs its token" in page.content()
    page.fill("input[name=token]", "wrong")
    page.click("form button")
    assert page.is_visible("#login-error")
    page.fill("input[name=token]", TOKEN)
    page.click("form button")
    page.wait_for_url(server + "/")
    assert page.is_visible("#upload-form")


def test_upload_run_compare_and_view(page: Any, server: str, tmp_path: Path) -> None:
    """Two recordings, the second with 8x the odometry drift: job B's ATE is a regression, shown red."""
    good = upload_and_run(page, server, write_tiny_recording(tmp_path / "good.mcap", drift=0.05))
    shot(page, "job")
    worse = upload_and_run(page, server, write_tiny_recording(tmp_path / "drifting.mcap", drift=0.4))

    page.goto(server + "/")
    shot(page, "index")
    page.select_option("#compare-form select[name=a]", good)
    page.select_option("#compare-form select[name=b]", worse)
    page.click("#compare-form button")
    page.wait_for_url(re.compile(r"/ui/compare\?"))
    row = page.locator("tr.regression", has_text="ape_rmse_m").first
    assert row.is_visible()
    colour = row.evaluate("el => getComputedStyle(el).color")
    background = row.evaluate("el => getComputedStyle(el).backgroundColor")
    r, g, b = map(int, re.findall(r"\d+", colour)[:3])
    assert r > 120 and g < 40 and b < 40, colour  # dark red text
    br, bg, bb = map(int, re.findall(r"\d+", background)[:3])
    assert br > bg + 15 and br > bb + 15, background  # on a red tint
    assert "1 regression" in page.inner_text("body") or "regression(s)" in page.inner_text("body")
    shot(page, "compare")

    # Open in Rerun: the viewer (served here) loads the job's .rrd by URL and draws into its canvas.
    page.goto(f"{server}/ui/jobs/{good}")
    href = page.get_attribute("#open-rerun", "href")
    assert href is not None and href.startswith("/viewer/?url=")
    errors: list[str] = []
    page.on("console", lambda m: errors.append(m.text) if "Data source failed" in m.text else None)
    with page.expect_response(lambda resp: resp.url.endswith(f"/jobs/{good}/run.rrd"), timeout=90_000) as got:
        page.goto(server + href)
    assert got.value.status == 200
    page.wait_for_selector("#the_canvas_id.visible", timeout=90_000)
    page.wait_for_timeout(5000)  # let it draw the recording
    assert errors == []
    png = page.locator("#the_canvas_id").screenshot()
    shot(page, "viewer")
    assert _distinct_colours(png) > 50  # the run drawn: map, labels, plots; a blank canvas has a handful


def _distinct_colours(png: bytes) -> int:
    import cv2
    import numpy as np

    img = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)
    return len(np.unique(img.reshape(-1, 3) // 8, axis=0))


# -- the runs table and the job page (issue 25) ------------------------------------------------------------

LAPTOP, PHONE = {"width": 1366, "height": 768}, {"width": 390, "height": 844}


def both_sizes(page: Any, name: str) -> None:
    """Screenshots of the page at laptop and phone size (the phone one must not scroll sideways)."""
    for size, tag in ((LAPTOP, "laptop"), (PHONE, "phone")):
        page.set_viewport_size(size)
        page.wait_for_timeout(100)
        if tag == "phone":
            width = page.evaluate("document.documentElement.scrollWidth")
            assert width <= PHONE["width"], f"{name}: the page scrolls sideways at 390 px ({width} px wide)"
        if SHOTS is not None:
            SHOTS.mkdir(parents=True, exist_ok=True)
            page.screenshot(path=str(SHOTS / f"{name}-{tag}.png"), full_page=False)
    page.set_viewport_size(LAPTOP)


def option_starting(page: Any, select: str, text: str) -> str:
    """The value of the option of ``select`` whose label starts with ``text``."""
    value: str = page.eval_on_selector(select, "(s, t) => [...s.options].find(o => o.text.startsWith(t)).value", text)
    return value


def listed_ids(page: Any) -> list[str]:
    ids: list[str] = page.eval_on_selector_all("#runs-table input[name=sel]", "els => els.map(e => e.value)")
    return ids


def test_find_an_old_run_rename_and_tag_it(page: Any, server: str) -> None:
    """Filter the table by recording, rename and tag the run found, then find it again by its tag."""
    page.set_viewport_size(LAPTOP)
    page.goto(server + "/runs")
    assert len(listed_ids(page)) >= 2
    sel = "#runs-filter select[name=recording]"
    page.select_option(sel, option_starting(page, sel, "good.mcap"))
    page.click("#runs-filter button[type=submit]")
    page.wait_for_url(re.compile(r"/runs\?.*recording="))
    (found,) = listed_ids(page)
    page.click(f"#run-{found} .row-actions a:has-text('edit')")
    page.fill("#edit-form input[name=name]", "baseline with little drift")
    page.fill("#edit-form input[name=tags]", "paper, v1")
    page.click("#edit-form button[type=submit]")
    page.wait_for_url(re.compile(r"/runs\?.*recording="))  # back to the same view
    row = page.inner_text(f"#run-{found}")
    assert "baseline with little drift" in row and "paper" in row and "v1" in row
    page.goto(server + "/runs?tag=paper")
    assert listed_ids(page) == [found]
    both_sizes(page, "runs-filtered")


def test_select_two_runs_and_compare(page: Any, server: str) -> None:
    """Two runs of different recordings lead to the comparison's URL and the diff; two of one kind to the report."""
    page.goto(server + "/runs")
    ids = listed_ids(page)
    for job_id in ids[:2]:
        page.check(f"#run-{job_id} input[name=sel]")
    page.click("#compare-selected")  # straight to the comparison (issue 41): no page between
    page.wait_for_url(re.compile(rf"/ui/compare\?runs={ids[0]},{ids[1]}$"))
    # The same inputs again: a run of one kind with the first, compared in the report page.
    page.goto(server + f"/ui/jobs/{ids[-1]}")
    recording = page.inner_text("#job-head strong")
    page.goto(server + "/")
    page.select_option("#job-form select[name=recording_id]",
                       option_starting(page, "#job-form select[name=recording_id]", recording))
    page.select_option("#job-form select[name=pipeline]", "odometry")
    page.click("#job-form button")
    page.wait_for_url(re.compile(r"/ui/jobs/[0-9a-f]{32}$"))
    again = page.url.rsplit("/", 1)[1]
    page.wait_for_function("() => document.querySelector('#job-status').textContent.trim() === 'succeeded'",
                           timeout=90_000)
    page.goto(server + "/runs")
    page.check(f"#run-{again} input[name=sel]")
    page.check(f"#run-{ids[-1]} input[name=sel]")
    page.click("#compare-selected")
    page.wait_for_url(re.compile(r"/ui/compare\?a="))
    assert "ape_rmse_m" in page.inner_text("body")
    both_sizes(page, "compare-selected")


def test_failed_job_error_is_readable_at_every_width(page: Any, server: str) -> None:
    """ifmi made to run on a recording without a camera (odometry poses mapped onto /camera/image: the submit check,
    tests/api/test_submit_checks.py, refuses it without the map) fails: its whole error is a block below the
    status, with the log."""
    page.goto(server + "/")
    page.select_option("#job-form select[name=pipeline]", "ifmi")
    page.fill("#job-form input[name=topic_map]", '{"/odom": "/camera/image"}')
    page.click("#job-form button")
    page.wait_for_url(re.compile(r"/ui/jobs/[0-9a-f]{32}$"))
    page.wait_for_function("() => document.querySelector('#job-status').textContent.trim() === 'failed'",
                           timeout=90_000)
    for size in (LAPTOP, PHONE):
        page.set_viewport_size(size)
        status, error = page.locator("#job-status").bounding_box(), page.locator("#job-error").bounding_box()
        assert error["y"] >= status["y"] + status["height"], (status, error)  # below it, not over it
        assert error["x"] + error["width"] <= size["width"]
        # every line of the error is in the box, none cut off
        assert page.evaluate("(e => e.scrollWidth <= e.clientWidth)(document.querySelector('#job-error'))")
    assert page.is_visible("#log-link") and page.is_visible("#log-tail")
    both_sizes(page, "job-failed")


def test_phone_width_pages_do_not_scroll_sideways(page: Any, server: str) -> None:
    """At 390x844 the runs table scrolls inside its own box; no page is wider than the screen."""
    page.goto(server + "/runs")
    job_id = listed_ids(page)[-1]
    page.set_viewport_size(PHONE)
    for path in ("/", "/runs", "/runs?cols=ape_rmse_m,rpe_step_trans_rmse_m&sort=-m.ape_rmse_m",
                 f"/ui/jobs/{job_id}", f"/ui/jobs/{job_id}/edit", "/runs?where=ape_rmse_m+%3C%3C+1"):
        page.goto(server + path)
        width = page.evaluate("document.documentElement.scrollWidth")
        assert width <= PHONE["width"], (path, width)
    page.goto(server + "/runs")
    cards = page.eval_on_selector("#runs-table tbody tr", "e => getComputedStyle(e).display")
    assert cards == "grid"  # a card per run (issue 41), no wider than the phone
    page.goto(server + f"/ui/jobs/{job_id}")
    both_sizes(page, "job")
    page.goto(server + "/runs?cols=ape_rmse_m,rpe_step_trans_rmse_m")
    both_sizes(page, "runs")
    page.goto(server + "/runs?where=ape_rmse_m+%3C%3C+1")
    both_sizes(page, "runs-bad-condition")


# -- compare anything (issue 25, part 3) ---------------------------------------------------------------------


def _log_in(page: Any, server: str) -> None:
    """Log in unless the session already is (the tests share one browser context)."""
    page.goto(server + "/")
    if "/login" in page.url:
        page.fill("input[name=token]", TOKEN)
        page.click("form button")
        page.wait_for_url(server + "/")


def _run_on(page: Any, server: str, recording_id: str, pipeline: str) -> str:
    """Run ``pipeline`` on a recording through the job form; the job id once it has succeeded."""
    page.goto(server + "/")
    page.select_option("#job-form select[name=recording_id]", recording_id)
    page.select_option("#job-form select[name=pipeline]", pipeline)
    page.click("#job-form button")
    page.wait_for_url(re.compile(r"/ui/jobs/[0-9a-f]{32}$"))
    page.wait_for_function("() => document.querySelector('#job-status').textContent.trim() === 'succeeded'",
                           timeout=90_000)
    return str(page.url.rsplit("/", 1)[1])


def test_compare_two_runs_of_different_pipelines(page: Any, server: str, tmp_path: Path) -> None:
    """Odometry and dslam on one recording, ticked in the runs table: What changed names the pipeline, and the
    ATE's verdict (better, green) is read by its direction; a third run gives three paths on one plot."""
    _log_in(page, server)
    page.set_viewport_size(LAPTOP)
    page.set_input_files("#upload-form input[name=file]", str(write_tiny_recording(tmp_path / "pair.mcap", n=80)))
    page.click("#upload-form button")
    page.wait_for_url(re.compile(r"/\?uploaded=[0-9a-f]{64}"))
    rid = page.url.split("uploaded=")[1][:64]
    assert "pair.mcap" in page.inner_text("#flash")
    odo, dslam = _run_on(page, server, rid, "odometry"), _run_on(page, server, rid, "dslam")

    page.goto(server + f"/runs?recording={rid}")
    assert set(listed_ids(page)) == {odo, dslam}
    page.check(f"#run-{odo} input[name=sel]")
    page.check(f"#run-{dslam} input[name=sel]")
    page.click("#compare-selected")
    page.wait_for_url(re.compile(r"/ui/compare\?runs="))
    if f"runs={odo}" not in page.url:  # the table lists the newest first: make odometry the baseline (A)
        page.click("#swap")
        page.wait_for_url(re.compile(rf"/ui/compare\?runs={odo},{dslam}$"))
    changes = page.inner_text("#changes-table")
    assert re.search(r"pipeline\s+odometry\s+dslam", changes), changes
    row = page.locator("#delta-table tr", has_text="ape_rmse_m").first
    assert "better" in row.inner_text() and "lower is better" in row.inner_text()
    verdict = row.locator(".verdict")
    r, g, b = map(int, re.findall(r"\d+", verdict.evaluate("el => getComputedStyle(el).color"))[:3])
    assert g > r + 40 and g > b + 20  # green text
    assert page.locator("#plots figure:first-of-type svg polyline").count() >= 3  # A, B and ground truth
    assert page.locator("#error-over-time svg polyline").count() == 2  # A's and B's position error over time
    assert page.locator("#nees-over-time svg polyline").count() == 1  # B's (dslam's) NEES: odometry has none
    assert page.locator("#nees-over-time svg rect.band").count() == 1
    assert page.inner_text("#no-nees").startswith("A: ") and "odometry reports no robot pose NEES" in \
        page.inner_text("#no-nees")
    both_sizes(page, "compare-two-runs")
    if SHOTS is not None:
        page.screenshot(path=str(SHOTS / "compare-two-runs-full.png"), full_page=True)

    third = _run_on(page, server, rid, "ekfslam")
    page.goto(server + f"/ui/compare?runs={odo[:8]},{dslam[:8]},{third[:8]}")  # the page's short ids do
    assert page.locator("#plots figure:first-of-type svg polyline").count() == 4  # three runs and the truth
    assert page.locator("#error-over-time svg polyline").count() == 3  # each run's position error over time
    strokes = "els => els.map(e => e.getAttribute('stroke'))"
    paths = page.locator("#plots figure:first-of-type svg polyline").evaluate_all(strokes)
    nees = page.locator("#nees-over-time svg polyline").evaluate_all(strokes)
    assert nees == paths[-2:] and len(set(nees)) == 2  # dslam's and ekfslam's NEES in their paths' colours
    assert page.locator("#nees-over-time svg rect.band").count() == 1  # both 3-dof against the truth: one band
    assert page.locator("#no-nees li").count() == 1 and page.inner_text("#no-nees").startswith("1: ")
    page.set_viewport_size(PHONE)
    box = page.locator("#nees-over-time svg").bounding_box()
    assert box is not None and box["width"] / 420 * 11 >= 9  # its 11-unit text at least 9 px on a phone
    page.set_viewport_size(LAPTOP)
    readme_picture(page.locator("#nees-over-time"), "web-compare-nees-laptop")
    assert page.locator("#metrics-side-table tr").first.locator("th.n").count() == 3
    assert page.locator("#pairs li").count() == 3
    both_sizes(page, "compare-three-runs")
    if SHOTS is not None:
        page.screenshot(path=str(SHOTS / "compare-three-runs-full.png"), full_page=True)
