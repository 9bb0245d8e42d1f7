"""Watching a run as it runs (issue 41 item 4): a running job's page shows its metrics and trajectory so far, updated
while it runs, and "Open in Rerun" opens the viewer following the run's .rrd as it grows, keeping it all at the end.

The job is a real replay (dslam on a small recording) slowed down per message (``LIVE_SEED``), so that it runs
for about half a minute: long enough to see it update, short enough for a test.
"""

from __future__ import annotations

import asyncio
import os
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from web_site import LAPTOP, SHOTS, call, chromium, readme_picture, served, shoot, wait_until

from slamreplay.api.service.executor import Outcome, Report, Task, run_task

LIVE_SEED = 8008  # a real dslam replay, STEP_S slower per message
STEP_S = 0.015
MESSAGES = 1600  # odometry and ground truth at 10 Hz (and a scan every 5th): about 30 s at STEP_S


def live_job(task: Task, report: Report | None = None) -> Outcome:
    """The real job, but for LIVE_SEED: the pipeline sleeps STEP_S before each message (a slow run, watched)."""
    if task.seed != LIVE_SEED:
        return run_task(task, report)
    from slamreplay.api.service.store import set_progress
    from slamreplay.replay.engine.pipeline import get_pipeline
    from slamreplay.replay.runs.run import run_recording

    base = get_pipeline(task.pipeline)

    class Slow(base):  # type: ignore[valid-type,misc]
        def step(self, env: Any) -> None:
            time.sleep(STEP_S)
            super().step(env)

    def progress(done: int, total: int) -> None:
        (report or (lambda f: set_progress(task.db_path, task.job_id, f)))(done / max(total, 1))

    run_recording(task.recording, Slow, task.run_dir, seed=1, progress=progress, run_id=task.job_id)
    return Outcome("succeeded")


@pytest.fixture(scope="module")
def site(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[str, str]]:
    """The served app and a recording uploaded to it (its id)."""
    import sys

    sys.path.insert(0, str(Path(__file__).parents[1]))
    from conftest import write_tiny_recording

    folder = tmp_path_factory.mktemp("live")
    rec = write_tiny_recording(folder / "corridor-long.mcap", n=MESSAGES // 2, drift=0.05)
    with served(folder / "data", workers=1, job=live_job) as base:
        rid = call(base, "POST", "/recordings?filename=corridor-long.mcap", rec.read_bytes())["id"]
        yield base, rid


@pytest.mark.browser
def test_watch_a_running_job(site: tuple[str, str]) -> None:
    """A running suite cell links to its job page, which shows 3+ successive values of a metric while the job runs
    and its trajectory so far; the live viewer draws the run before it ends and still holds it after."""
    base, rid = site
    # a suite of one cell: its page links the running cell to the cell's job page, the live one
    suite = call(base, "POST", "/suites", b'name = "live"\nseeds = [%d]\n[recordings.corridor]\nid = "%s"\n'
                                          b'[pipelines.dslam]\n' % (LIVE_SEED, rid.encode()))["id"]
    job = call(base, "GET", f"/suites/{suite}")["cells"][0]["job_id"]
    assert wait_until(base, job, ("running",))["status"] == "running"
    with chromium() as browser:
        ctx = browser.new_context(viewport=LAPTOP)
        ctx.set_default_timeout(60_000)
        page = ctx.new_page()
        problems: list[str] = []
        page.on("console", lambda m: problems.append(m.text) if m.type == "error" else None)
        page.on("pageerror", lambda e: problems.append(f"uncaught: {e}"))
        page.goto(f"{base}/ui/suites/{suite}")
        cell = page.locator(f'table.cells a[href="/ui/jobs/{job}"]')
        assert "running" in page.inner_text("table.cells")
        cell.click()
        page.wait_for_url(f"{base}/ui/jobs/{job}")
        # Open in Rerun, while it runs: the viewer follows /ui/shared/KEY/jobs/ID/live.rrd (it loads in its own tab
        # while the page is watched).
        href = page.get_attribute("#open-rerun", "href")
        assert href is not None and "live.rrd" in href and "Open in Rerun (live)" in page.inner_text("#open-rerun")
        viewer = ctx.new_page()
        viewer.goto(base + href)
        page.bring_to_front()
        page.wait_for_selector("#live-metrics tr[data-metric=position_error_m]")
        # Successive values of the position error, each read while the job is running (the block is swapped
        # every 2 s by web.js; the live file is rewritten every second).
        values: list[str] = []
        steps: list[int] = []
        deadline = time.monotonic() + 40
        while len(values) < 3 and time.monotonic() < deadline:
            page.wait_for_function("""(seen) => {
                const td = document.querySelector('#live-metrics tr[data-metric=position_error_m] .live-value');
                return td && td.textContent.trim() !== seen; }""", arg=values[-1] if values else "")
            text = page.inner_text("#live-metrics tr[data-metric=position_error_m] .live-value").strip()
            assert page.inner_text("#job-status").strip() == "running"
            values.append(text)
            steps.append(int(page.inner_text("#live-steps").split()[0]))
        assert len(values) >= 3, values
        assert steps == sorted(steps) and len(set(steps)) == len(steps), steps
        assert page.locator("#live-plots svg").count() == 2  # the trajectory so far, the error so far
        assert "estimate" in page.inner_text("#live-plots")
        shoot(page, "job-live")
        readme_picture(page, "web-job-live")  # what fits a laptop's screen of a job watched while it runs
        _no_serious_axe_violation(ctx, f"{base}/ui/jobs/{job}")

        viewer.bring_to_front()
        viewer.wait_for_selector("#the_canvas_id.visible", timeout=90_000)
        viewer.wait_for_timeout(3000)  # it draws what has arrived (the observer sends 256 rows of an entity at a time)
        assert call(base, "GET", f"/jobs/{job}")["status"] == "running"
        running_png = viewer.locator("#the_canvas_id").screenshot()
        SHOTS.mkdir(parents=True, exist_ok=True)
        (SHOTS / "page-viewer-live-running.png").write_bytes(running_png)
        assert call(base, "GET", f"/jobs/{job}")["status"] == "running"  # the shot was taken before it ended
        assert _distinct_colours(running_png) > 50
        assert wait_until(base, job, timeout_s=90)["status"] == "succeeded"
        viewer.wait_for_timeout(3000)
        after = viewer.locator("#the_canvas_id").screenshot()
        (SHOTS / "page-viewer-live-ended.png").write_bytes(after)
        assert _distinct_colours(after) > 50
        # the page, once the job has ended: the finished view (its plots and metrics), no live block
        page.wait_for_selector("#metrics-table", timeout=30_000)
        assert page.locator("#live").count() == 0
        assert [p for p in problems if "live.rrd" not in p] == [], problems
        ctx.close()


def _no_serious_axe_violation(ctx: Any, url: str) -> None:
    """axe-core on the live job page (in its own tab, its refresh stopped so the scan keeps its nodes)."""
    axe = pytest.importorskip("axe_playwright_python.sync_playwright", reason="pip install -e '.[browser]'")
    tab = ctx.new_page()
    tab.goto(url)
    tab.wait_for_selector("#live-metrics")
    tab.evaluate("() => document.querySelectorAll('[data-live]').forEach(el => el.removeAttribute('data-live'))")
    results = axe.Axe().run(tab)
    bad = [f"{v['id']} ({v['impact']}): {v['help']}" for v in results.response["violations"]
           if v["impact"] in ("serious", "critical")]
    tab.close()
    assert bad == [], bad


def _distinct_colours(png: bytes) -> int:
    import cv2
    import numpy as np

    img = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)
    return len(np.unique(img.reshape(-1, 3) // 8, axis=0))


def test_follow_rrd_sends_the_whole_file(tmp_path: Path) -> None:
    """follow_rrd sends a file written in pieces, renamed when complete, byte for byte, and ends with the run."""
    from slamreplay.api.web.live_view import RRD_PARTIAL, follow_rrd

    pieces = [os.urandom(50_000) for _ in range(5)]
    running = threading.Event()
    running.set()

    def write() -> None:
        with open(tmp_path / RRD_PARTIAL, "wb") as f:
            for p in pieces:
                f.write(p)
                f.flush()
                time.sleep(0.05)
        os.replace(tmp_path / RRD_PARTIAL, tmp_path / "run.rrd")
        running.clear()

    async def read() -> bytes:
        return b"".join([b async for b in follow_rrd(tmp_path, running.is_set, poll_s=0.01)])

    writer = threading.Thread(target=write)
    writer.start()
    got = asyncio.run(read())
    writer.join()
    assert got == b"".join(pieces)


def test_a_running_jobs_stream_follows_the_newest_step(tmp_path: Path, tiny_recording: Path) -> None:
    """A running job's live.rrd starts with a layout whose time cursor follows the newest step (the viewer once
    stood at step 0 while the run went on), then the run's own file: Rerun's decoder reads both, the run's
    layout (sent at its end, active) after the following one. An ended job's stream is its file alone."""
    import subprocess

    from slamreplay.api.web.live_view import follow_rrd
    from slamreplay.replay.engine.views import following_layout_rrd
    from slamreplay.replay.runs.rrd_compare import rerun_cli
    from slamreplay.replay.runs.run import run_recording

    cli = rerun_cli()
    if cli is None:
        pytest.skip("the rerun command is not installed with rerun-sdk")
    run_recording(tiny_recording, "odometry", tmp_path / "run", seed=0, run_id="f" * 32)
    following = following_layout_rrd("odometry", "f" * 32)

    async def read(prefix: bytes) -> bytes:
        return b"".join([b async for b in follow_rrd(tmp_path / "run", lambda: False, prefix=prefix)])

    whole = (tmp_path / "run" / "run.rrd").read_bytes()
    assert asyncio.run(read(b"")) == whole
    live = asyncio.run(read(following))
    assert live == following + whole
    (tmp_path / "live.rrd").write_bytes(live)
    done = subprocess.run([cli, "rrd", "print", str(tmp_path / "live.rrd")], capture_output=True, text=True,
                          timeout=120)
    assert done.returncode == 0, done.stderr
    lines = done.stdout.splitlines()
    follow = next(i for i, x in enumerate(lines) if "TimePanelBlueprint:play_state" in x)
    activations = [i for i, x in enumerate(lines) if x.startswith("BlueprintActivationCommand") and
                   "make_active: true" in x]
    assert len(activations) == 2 and follow < activations[0]  # ours first, the run's own last
    assert any("/trajectory/estimate" in x for x in lines[activations[0]:])  # then the run's data
    recordings = {lines[i + 2].strip().strip('",') for i, x in enumerate(lines) if x.strip() == "Recording,"}
    assert recordings == {"f" * 32}  # one recording, the run's: no empty one beside it in the viewer
