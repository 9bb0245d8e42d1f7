"""The runs view in headless chromium (issue 41): results first, groups, phone cards and dark mode.

One served app (tests/web/web_site.py) holds two real runs of a tiny recording (a job page with plots, a
comparison) and a sweep written straight into its store: dslam and ekfslam on two recordings, range_sigma_m
of 5 values x 3 seeds, on two commits, some pushed, some with long names. Screenshots go to
results/web-shots/runs-view-*.png.
"""

from __future__ import annotations

import json
import re
import sqlite3
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from web_site import LAPTOP, PHONE, SHOTS, call, chromium, readme_picture, served, wait_until

pytestmark = pytest.mark.browser
SIGMAS = (0.05, 0.1, 0.2, 0.4, 0.8)
COMMITS = ("3f2a9c1" + "0" * 33, "8be41d7" + "1" * 33)
GROUPED = "/runs?group=pipeline,recording&cols=ape_rmse_m,landmark_rmse_m,landmark_nees_mean&sort=m.ape_rmse_m"
GROUP_CHART = GROUPED + "&chart=ape_rmse_m"
SCATTER = "/runs?pipeline=ekfslam&recording=corridor-loop.mcap&chart=landmark_rmse_m&x=config.range_sigma_m"
PARALLEL = "/runs?pipeline=ekfslam&recording=corridor-loop.mcap&cols=ape_rmse_m&chart=landmark_rmse_m&x=parallel"
FLAT = "/runs?pipeline=dslam&cols=ape_rmse_m,landmark_rmse_m&show=status,recording,seed,config,commit,made_by,tags,note"


def fill_sweep(db: Path, recordings: list[str]) -> None:
    """The sweep's runs, as the store keeps ended jobs (their metric values included)."""
    now = time.time() - 86400
    jobs, tags = [], []
    k = 0
    for pipeline, base in (("dslam", 0.04), ("ekfslam", 0.022)):
        for r, rec in enumerate(recordings):
            for sigma in SIGMAS:
                for seed in (1, 2, 3):
                    k += 1
                    jid = f"{0xABC000 + k:032x}"
                    ape = base * (1 + r) * (1 + 2 * abs(sigma - 0.2)) + 0.001 * seed
                    metrics = {"ape_rmse_m": ape, "landmark_rmse_m": ape * 0.8 + sigma / 50,
                               "landmark_nees_mean": 2.0 + 4 * abs(sigma - 0.2) + 0.1 * seed, "landmarks_mapped": 40}
                    name = (f"{pipeline} range-noise sweep sigma {sigma} seed {seed}: re-run after the data "
                            "association fix on the long corridor recording" if k % 7 == 0
                            else f"{pipeline} s={sigma} #{seed}")
                    source = json.dumps({"pushed_by": "ci", "origin": "ci-runner-7"}) if k % 5 == 0 else None
                    jobs.append((jid, rec, pipeline, json.dumps({"range_sigma_m": sigma}), seed, "succeeded", 1.0,
                                 None, "a note long enough to be cut in the table, whole on the job page" if k % 6 == 0
                                 else None, 1, now + k, now + k + 1, now + k + 30, name, json.dumps(metrics),
                                 COMMITS[k % 2], "ci" if source else "ana", source))
                    if k % 4 == 0:
                        tags.append((jid, "sweep"))
    conn = sqlite3.connect(db)
    with conn:
        conn.executemany("INSERT INTO jobs (id, recording_id, pipeline, config, seed, status, progress, error, note, "
                         "attempts, created, started, finished, name, metrics, git_commit, made_by, source) "
                         "VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?)", jobs)
        conn.executemany("INSERT INTO job_tags VALUES (?, ?)", tags)
    conn.close()


@pytest.fixture(scope="module")
def site(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[str, dict[str, str]]]:
    """The served app with two real runs and the sweep: its base URL and the real runs' ids."""
    import sys

    sys.path.insert(0, str(Path(__file__).parents[1]))
    from conftest import write_tiny_recording

    folder = tmp_path_factory.mktemp("runs-view")
    with served(folder / "data") as base:
        rec = write_tiny_recording(folder / "corridor-loop.mcap", drift=0.05)
        other = write_tiny_recording(folder / "hall-2.mcap", drift=0.2, seed=1)
        ids = {"rec": call(base, "POST", "/recordings?filename=corridor-loop.mcap", rec.read_bytes())["id"],
               "rec2": call(base, "POST", "/recordings?filename=hall-2.mcap", other.read_bytes())["id"]}
        for key, pipeline in (("odometry", "odometry"), ("dslam", "dslam")):
            ids[key] = call(base, "POST", "/jobs", {"recording_id": ids["rec"], "pipeline": pipeline})["id"]
        for key in ("odometry", "dslam"):
            assert wait_until(base, ids[key])["status"] == "succeeded", key
        fill_sweep(folder / "data" / "runs" / "jobs.sqlite", [ids["rec"], ids["rec2"]])
        yield base, ids


@pytest.fixture(scope="module")
def browser() -> Iterator[Any]:
    with chromium() as b:
        yield b


@pytest.fixture
def page(browser: Any) -> Iterator[Any]:
    """A tab at laptop size in light mode; ``page.problems`` collects console errors (CSP violations included)."""
    ctx = browser.new_context(viewport=LAPTOP, color_scheme="light")
    pg = ctx.new_page()
    pg.problems = []
    pg.on("console", lambda m: pg.problems.append(f"console.{m.type}: {m.text}") if m.type == "error" else None)
    pg.on("pageerror", lambda e: pg.problems.append(f"uncaught: {e}"))
    yield pg
    ctx.close()


def shot(page: Any, name: str, full: bool = False) -> None:
    SHOTS.mkdir(parents=True, exist_ok=True)
    page.screenshot(path=str(SHOTS / f"runs-view-{name}.png"), full_page=full)


def on_screen(page: Any, selector: str, size: dict[str, int]) -> bool:
    """Whether the element is wholly inside the viewport."""
    box = page.locator(selector).first.bounding_box()
    return box is not None and box["x"] >= 0 and box["y"] >= 0 and box["x"] + box["width"] <= size["width"] \
        and box["y"] + box["height"] <= size["height"]


def test_best_group_is_on_screen_with_its_value(page: Any, site: tuple[str, dict[str, str]]) -> None:
    """A grouped view sorted by a metric: the best group is the first row, its name and its mean both on screen
    at 1366x768, the best mean marked; the groups' spread is in the cells and min/max in their tooltips."""
    base, _ = site
    page.goto(base + GROUPED)
    first = "#groups-table tbody tr:first-child"
    name = page.inner_text(f"{first} .group-name")
    assert name == "ekfslam, corridor-loop.mcap", name  # the lower base error, on the first recording
    assert on_screen(page, f"{first} .group-name", LAPTOP)
    assert on_screen(page, f"{first} td.metric", LAPTOP)
    cell = page.locator(f"{first} td.metric").first
    assert re.fullmatch(r"0\.\d+ ± 0\.\d+", cell.inner_text().strip()), cell.inner_text()
    assert "min" in (cell.get_attribute("title") or "") and "best" in (cell.get_attribute("class") or "")
    assert page.locator("#groups-table tbody tr").count() == 5  # 4 sweep groups and the real odometry run's
    shot(page, "grouped-laptop")
    readme_picture(page, "web-groups-laptop")
    page.click(f"{first} .group-name")  # its runs, inside the row
    assert page.locator(f"{first} ul.group-runs li").count() == 5  # the newest; all 15 a link away
    page.click(f"{first} a.all-runs")
    page.wait_for_url(re.compile(r"/runs\?.*where="))
    assert page.locator("#runs-table tbody tr").count() == 15
    assert page.problems == [], page.problems


def test_metrics_first_and_name_pinned(page: Any, site: tuple[str, dict[str, str]]) -> None:
    """The flat view: metric columns right after the name, on screen at 1366x768; scrolling the table sideways
    keeps the names in view; a long name is cut, whole in its tooltip."""
    base, _ = site
    page.goto(base + FLAT + ",created,started,finished,duration")
    assert on_screen(page, "#runs-table tbody tr:first-child td.metric", LAPTOP)
    link = page.locator("#runs-table a.run-name").filter(has_text="data association").first
    box = link.bounding_box()
    assert box is not None and box["width"] < 260 and "long corridor recording" in (link.get_attribute("title") or "")
    shot(page, "flat-laptop")
    scroller = page.locator("#runs-table").locator("xpath=..")
    before = page.locator("#runs-table tbody tr:first-child td.name").bounding_box()
    scroller.evaluate("e => { e.scrollLeft = e.scrollWidth; }")
    page.wait_for_timeout(100)
    after = page.locator("#runs-table tbody tr:first-child td.name").bounding_box()
    assert scroller.evaluate("e => e.scrollLeft") > 0 and abs(after["x"] - before["x"]) < 2, (before, after)
    shot(page, "flat-laptop-scrolled")
    assert page.problems == [], page.problems


def test_column_menu_orders_columns_in_the_url(page: Any, site: tuple[str, dict[str, str]]) -> None:
    """The column menu: tick a metric, move it up, Apply: the URL keeps the order and the headings follow it."""
    base, _ = site
    page.goto(base + "/runs?pipeline=dslam&cols=ape_rmse_m")
    page.click("#column-menu summary")
    items = page.locator("#metric-menu li")
    assert "landmark_rmse_m" in page.inner_text("#metric-menu") and "pnr_median" not in page.inner_text("#metric-menu")
    page.check("#metric-menu input[value=landmark_rmse_m]")
    for _ in range(items.count()):  # to the top, above ape_rmse_m
        page.click("#metric-menu button[aria-label='move landmark_rmse_m up']")
    assert items.first.inner_text().startswith("landmark_rmse_m")
    shot(page, "column-menu")
    page.click("#runs-filter button[type=submit]")
    page.wait_for_url(re.compile(r"cols=.*landmark_rmse_m.*ape_rmse_m"))
    heads = page.eval_on_selector_all("#runs-table thead th", "els => els.map(e => e.innerText.trim())")
    assert heads[1].startswith("landmark_rmse_m") and heads[2].startswith("ape_rmse_m"), heads
    assert page.problems == [], page.problems


def test_phone_shows_a_card_per_run(page: Any, site: tuple[str, dict[str, str]]) -> None:
    """At 390x844: a card per run (and per group) with its metrics; nothing scrolls sideways."""
    base, _ = site
    page.set_viewport_size(PHONE)
    for path, name in ((FLAT, "flat"), (GROUPED, "grouped")):
        page.goto(base + path)
        wide = page.evaluate("document.documentElement.scrollWidth")
        assert wide <= PHONE["width"], (path, wide)
        table = "#groups-table" if "group=" in path else "#runs-table"
        assert page.eval_on_selector(f"{table} tbody tr", "e => getComputedStyle(e).display") == "grid"
        assert page.evaluate(f"(e => e.scrollWidth <= e.clientWidth)(document.querySelector('{table}'))")
        assert on_screen(page, f"{table} tbody tr:first-child td.metric", PHONE) or \
            page.locator(f"{table} tbody tr:first-child td.metric").first.is_visible()
        shot(page, f"{name}-phone")
        page.evaluate("window.scrollTo(0, document.querySelector('table').getBoundingClientRect().top + scrollY)")
        shot(page, f"{name}-phone-cards")
        if name == "grouped":
            readme_picture(page, "web-grouped-phone-cards")
    assert page.problems == [], page.problems


def test_charts_across_runs(page: Any, site: tuple[str, dict[str, str]]) -> None:
    """A metric per group (a row each, linked to its runs) and a scatter of range_sigma_m against
    landmark_rmse_m over the 5 x 3 sweep (5 columns of dots, each linked to its run), readable at 390 px: the
    chart as wide as the screen, its text at least 9 px, nothing scrolling sideways."""
    base, _ = site
    page.goto(base + GROUP_CHART)
    assert page.locator("#runs-chart a.mark").count() == 5
    shot(page, "group-chart-laptop", full=True)
    page.goto(base + SCATTER)
    dots = page.eval_on_selector_all("#runs-chart circle", "els => els.map(e => e.getAttribute('cx'))")
    assert len(dots) == 15 and len(set(dots)) == 5
    href = page.get_attribute("#runs-chart a.mark", "href")
    assert href is not None and re.fullmatch(r"/ui/jobs/[0-9a-f]{32}", href)
    shot(page, "scatter-laptop")
    page.locator("#runs-chart").scroll_into_view_if_needed()
    readme_picture(page, "web-scatter-laptop")
    page.set_viewport_size(PHONE)
    for path, name in ((SCATTER, "scatter"), (GROUP_CHART, "group-chart")):
        page.goto(base + path)
        assert page.evaluate("document.documentElement.scrollWidth") <= PHONE["width"]
        box = page.locator("#runs-chart svg").bounding_box()
        assert box is not None and box["width"] >= 300 and box["x"] + box["width"] <= PHONE["width"]
        size = page.evaluate("""() => Math.min(...[...document.querySelectorAll('#runs-chart svg text')]
                                .map(t => t.getBoundingClientRect().height))""")
        assert size >= 9, (name, size)
        page.locator("#runs-chart").scroll_into_view_if_needed()
        shot(page, f"{name}-phone")
        if name == "group-chart":
            readme_picture(page, "web-group-chart-phone")
    page.click("#runs-chart a.mark")  # a group's row: its runs
    page.wait_for_url(re.compile(r"/runs\?.*where="))
    for size, tag in ((LAPTOP, "laptop"), (PHONE, "phone")):  # parallel coordinates: a line per run, linked
        page.set_viewport_size(size)
        page.goto(base + PARALLEL)
        assert page.locator("#runs-chart a.mark polyline").count() >= 15
        assert page.evaluate("document.documentElement.scrollWidth") <= size["width"]
        page.locator("#runs-chart").scroll_into_view_if_needed()
        shot(page, f"parallel-{tag}")
    assert page.problems == [], page.problems


@pytest.mark.parametrize("scheme", ["dark", "light"])
def test_axe_clean_in_both_schemes(browser: Any, site: tuple[str, dict[str, str]], scheme: str) -> None:
    """No serious or critical axe violation (contrast included) on the runs views, a job page with plots and a
    comparison, in the dark and the light scheme; the dark page is dark and the palette keeps its colours."""
    axe = pytest.importorskip("axe_playwright_python.sync_playwright", reason="pip install -e '.[browser]'")
    base, ids = site
    ctx = browser.new_context(viewport=LAPTOP, color_scheme=scheme)
    pg = ctx.new_page()
    problems: list[str] = []
    pg.on("console", lambda m: problems.append(m.text) if m.type == "error" else None)
    try:
        for name, path in (("flat", FLAT), ("grouped", GROUP_CHART), ("scatter", SCATTER), ("parallel", PARALLEL),
                           ("job", f"/ui/jobs/{ids['dslam']}"),
                           ("compare", f"/ui/compare?runs={ids['odometry']},{ids['dslam']}")):
            pg.goto(base + path)
            pg.evaluate("document.querySelectorAll('[data-live]').forEach(el => el.removeAttribute('data-live'))")
            results = axe.Axe().run(pg)
            bad = [f"{v['id']} ({v['impact']}): " + "; ".join(" ".join(n["target"]) for n in v["nodes"][:4])
                   for v in results.response["violations"] if v["impact"] in ("serious", "critical")]
            assert bad == [], (scheme, name, bad)
            bg = pg.evaluate("getComputedStyle(document.body).backgroundColor")
            level = sum(map(int, re.findall(r"\d+", bg)[:3])) / 3
            assert (level < 40) if scheme == "dark" else (level > 230), (scheme, bg)
            if scheme == "dark":
                shot(pg, f"{name}-dark")
                if name in ("grouped", "job"):
                    readme_picture(pg, f"web-{name}-dark")
                if name == "job":  # the estimate stays blue and the truth grey
                    strokes = pg.eval_on_selector_all("#plots polyline",
                                                      "els => els.map(e => getComputedStyle(e).stroke)")
                    assert "rgb(31, 119, 180)" in strokes and "rgb(127, 127, 127)" in strokes, strokes
        assert problems == [], problems
    finally:
        ctx.close()
