"""A served slamreplay with runs of every kind, for the page tests in headless chromium (tests/web/test_pages.py).

The app runs in this process under uvicorn (as ``slamreplay serve`` runs it), with a ``LocalExecutor``
whose job is ``web_job``: the real job, except for two seeds that stand for what a test cannot wait for
or provoke through the API: a job that runs for minutes (to see it running and cancel it) and a job whose
recording was damaged on disk after its upload (a failure at run time, whatever is checked at submit time).
"""

from __future__ import annotations

import dataclasses
import json
import os
import shutil
import threading
import time
import urllib.parse
import urllib.request
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from patience import deadline as give_up_at

from slamreplay.api.service.executor import Outcome, Report, Task, run_task

CHROMIUM = os.environ.get("SLAMREPLAY_CHROMIUM", "/usr/bin/chromium")
SLOW_SEED = 7007  # runs for LONG_S in short naps, reporting progress, until cancelled
DAMAGED_SEED = 6006  # its recording is cut short on disk before the run: fails at run time
LONG_S = 600.0
LAPTOP, PHONE = {"width": 1366, "height": 768}, {"width": 390, "height": 844}
SHOTS = Path(os.environ.get("SLAMREPLAY_BROWSER_SHOTS") or Path(__file__).parents[2] / "results" / "web-shots")
# e.g. docs/images (make test-browser README_IMAGES=docs/images): the README's and docs/web.md's screenshots, rewritten
README_IMAGES = os.environ.get("SLAMREPLAY_README_IMAGES")


def web_job(task: Task, report: Report | None = None) -> Outcome:
    """The real job, but for SLOW_SEED (long, with progress) and DAMAGED_SEED (a truncated recording)."""
    if task.seed == SLOW_SEED:
        from slamreplay.api.service.store import set_progress

        steps = int(LONG_S / 0.1)
        for i in range(steps):
            if i % 10 == 0:
                (report or (lambda f: set_progress(task.db_path, task.job_id, f)))(i / steps)
            time.sleep(0.1)
        return Outcome("succeeded")
    if task.seed == DAMAGED_SEED:
        data = Path(task.recording).read_bytes()
        cut = Path(task.db_path).parents[1] / "field-test-0412.mcap"  # in the data directory: the test's own
        cut.write_bytes(data[: len(data) * 2 // 3])
        return run_task(dataclasses.replace(task, recording=str(cut)), report)
    return run_task(task, report)


@contextmanager
def served(data_dir: Path, workers: int = 2, job: Any = web_job) -> Iterator[str]:
    """The app over ``data_dir`` on a free loopback port (jobs run by ``job``, a module-level function); its base
    URL."""
    import uvicorn

    from slamreplay.api.app import create_app
    from slamreplay.api.cli.listen import listen
    from slamreplay.api.service.executor import LocalExecutor
    from slamreplay.api.service.settings import Settings

    sock = listen("127.0.0.1", 0)
    port = sock.getsockname()[1]
    app = create_app(Settings(data_dir=data_dir, workers=workers), executor=LocalExecutor(workers, job=job))
    server = uvicorn.Server(uvicorn.Config(app, log_level="warning"))
    thread = threading.Thread(target=server.run, kwargs={"sockets": [sock]}, daemon=True)
    thread.start()
    base = f"http://127.0.0.1:{port}"
    try:
        deadline = give_up_at(60)
        while not server.started:
            if not thread.is_alive() or time.monotonic() > deadline:
                raise AssertionError("the server did not start")
            time.sleep(0.05)
        yield base
    finally:
        server.should_exit = True
        thread.join(30)
        sock.close()


def call(base: str, method: str, path: str, body: Any = None, form: dict[str, str] | None = None) -> Any:
    """One request to the API (JSON in and out; ``form``: a form post, its answer not read)."""
    data, headers = None, {}
    if isinstance(body, bytes):
        data = body
    elif body is not None:
        data, headers = json.dumps(body).encode(), {"content-type": "application/json"}
    elif form is not None:
        data = urllib.parse.urlencode(form).encode()
        headers = {"content-type": "application/x-www-form-urlencoded"}
    req = urllib.request.Request(base + path, data=data, headers=headers, method=method)
    with urllib.request.urlopen(req, timeout=60) as r:
        text = r.read()
    return json.loads(text) if r.headers.get("content-type", "").startswith("application/json") else text


def wait_until(base: str, job_id: str, done: tuple[str, ...] = ("succeeded", "failed", "cancelled"),
               timeout_s: float = 120) -> dict[str, Any]:
    deadline = time.monotonic() + timeout_s
    while True:
        job: dict[str, Any] = call(base, "GET", f"/jobs/{job_id}")
        if job["status"] in done or time.monotonic() > deadline:
            return job
        time.sleep(0.2)


def seed_runs(base: str, folder: Path) -> dict[str, str]:
    """Two recordings, named and tagged runs of two pipelines, a failed run, a suite and a running job; their ids."""
    import sys

    sys.path.insert(0, str(Path(__file__).parents[1]))  # tests/conftest.py: the tiny recordings
    from conftest import write_tiny_recording

    good = write_tiny_recording(folder / "corridor-loop.mcap", drift=0.05)
    worse = write_tiny_recording(folder / "corridor-loop-worn-wheel.mcap", drift=0.4, seed=1)
    ids = {"rec_good": call(base, "POST", "/recordings?filename=corridor-loop.mcap", good.read_bytes())["id"],
           "rec_worse": call(base, "POST", "/recordings?filename=corridor-loop-worn-wheel.mcap",
                             worse.read_bytes())["id"]}

    def job(rec: str, pipeline: str, seed: int = 0, config: dict[str, Any] | None = None) -> str:
        spec = {"recording_id": ids[rec], "pipeline": pipeline, "seed": seed, "config": config or {}}
        job_id: str = call(base, "POST", "/jobs", spec)["id"]
        return job_id

    ids["baseline"] = job("rec_good", "odometry")
    ids["worn"] = job("rec_worse", "odometry")
    ids["dslam"] = job("rec_good", "dslam")
    ids["dslam_tuned"] = job("rec_good", "dslam", config={"range_sigma_m": 0.05})
    ids["failed"] = job("rec_good", "odometry", DAMAGED_SEED)
    suite = (b'name = "nightly odometry"\nseeds = [1, 2]\n[recordings.corridor]\nid = "%s"\n[pipelines.odometry]\n'
             % ids["rec_good"].encode())
    ids["suite"] = call(base, "POST", "/suites", suite)["id"]
    for key in ("baseline", "worn", "dslam", "dslam_tuned", "failed"):
        assert wait_until(base, ids[key])["status"] in ("succeeded", "failed"), key
    labels = {"baseline": ("baseline", "paper v1", "the reference run: a new wheel"),
              "worn": ("worn wheel", "regression", "left wheel 3 mm smaller: odometry drifts"),
              "dslam_tuned": ("dslam, tighter range noise", "tuning", "")}
    for key, (name, tags, note) in labels.items():
        call(base, "POST", f"/ui/jobs/{ids[key]}/edit", form={"name": name, "tags": tags, "note": note, "next": "/"})
    for cell in call(base, "GET", f"/suites/{ids['suite']}")["cells"]:
        wait_until(base, cell["job_id"])
    ids["running"] = job("rec_good", "odometry", SLOW_SEED)
    assert wait_until(base, ids["running"], ("running",))["status"] == "running"
    return ids


@contextmanager
def chromium() -> Iterator[Any]:
    """Debian's headless chromium under Playwright (which downloads no browser)."""
    import pytest

    sync_api = pytest.importorskip("playwright.sync_api", reason="pip install -e '.[browser]' (make test-browser)")
    if not shutil.which(CHROMIUM):
        pytest.fail(f"{CHROMIUM} not found: apt-get install chromium (make test-browser does)")
    with sync_api.sync_playwright() as p:
        browser = p.chromium.launch(executable_path=CHROMIUM, args=["--no-sandbox"])
        try:
            yield browser
        finally:
            browser.close()


def shoot(page: Any, name: str) -> list[Path]:
    """Screenshots of the whole page at laptop and phone size, into SHOTS (make test-browser: results/web-shots/)."""
    SHOTS.mkdir(parents=True, exist_ok=True)
    paths = []
    for size, tag in ((LAPTOP, "laptop"), (PHONE, "phone")):
        page.set_viewport_size(size)
        page.wait_for_timeout(50)
        path = SHOTS / f"page-{name}-{tag}.png"  # page-: apart from test_browser.py's shots in the same folder
        page.screenshot(path=str(path), full_page=True)
        paths.append(path)
    page.set_viewport_size(LAPTOP)
    return paths


def readme_picture(target: Any, name: str) -> None:
    """With SLAMREPLAY_README_IMAGES: the docs' picture ``name`` (``web-job-live``) of what ``target`` shows (a page:
    what fits its screen; a locator: that element), in 256 colours; nothing without it."""
    if not README_IMAGES:
        return
    from PIL import Image

    out = Path(README_IMAGES) / f"{name}.png"
    target.screenshot(path=str(out))
    Image.open(out).convert("RGB").quantize(256, dither=Image.Dither.NONE).save(out, optimize=True)
