"""A job's page: config with sources, metrics with meaning, plots, files (no traversal), log tail, failures."""

from __future__ import annotations

import html
import re
import time
import warnings
from collections.abc import Iterator
from pathlib import Path

import pytest
from conftest import write_tiny_recording
from service_helpers import InlineExecutor, wait_for

with warnings.catch_warnings():
    warnings.simplefilter("ignore", UserWarning)  # StarletteDeprecationWarning: it asks for httpx2; httpx works
    from fastapi.testclient import TestClient

from slamreplay.api.app import create_app
from slamreplay.api.service.settings import Settings
from slamreplay.api.service.store import Store
from slamreplay.api.web.svg_plots import nice_ticks


@pytest.fixture(scope="module")
def served(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[TestClient, str, str]]:
    """(client, a succeeded dslam job with one user config value, a failed job) over one data directory."""
    data = tmp_path_factory.mktemp("data")
    rec = write_tiny_recording(tmp_path_factory.mktemp("rec") / "tiny.mcap")
    app = create_app(Settings(allowed_hosts=("testserver",), data_dir=data, workers=1), executor=InlineExecutor())
    with TestClient(app) as client:
        rid = client.post("/recordings", content=rec.read_bytes(), params={"filename": "tiny.mcap"}).json()["id"]
        good = client.post("/jobs", json={"recording_id": rid, "pipeline": "dslam", "seed": 4,
                                          "config": {"range_sigma_m": 0.07}}).json()["id"]
        assert wait_for(client, good)["status"] == "succeeded"
        # A topic map that passes the submit-time check (the topic has messages) but maps odometry onto the camera
        # topic: the replay cannot decode it, so the job fails when it runs.
        bad = client.post("/jobs", json={"recording_id": rid, "pipeline": "ifmi",
                                         "topic_map": {"/odom": "/camera/image"}}).json()["id"]
        assert wait_for(client, bad)["status"] == "failed"
        yield client, good, bad


def test_config_with_sources_and_metrics_with_meaning(served: tuple[TestClient, str, str]) -> None:
    """The resolved config lists every key with where its value came from; metrics have unit, direction, meaning."""
    client, good, _ = served
    page = client.get(f"/ui/jobs/{good}").text
    config = page.split('id="config-table"')[1].split("</table>")[0]
    assert len(re.findall(r"<tr><td>", config)) >= 10 and ">default<" in config
    assert re.search(r"<td>range_sigma_m</td><td><code>0.07</code></td><td><span class=\"source user\">user<", config)
    metrics = page.split('id="metrics-table"')[1].split("</table>")[0]
    assert "ape_rmse_m" in metrics and "lower is better" in metrics and "absolute position error RMSE" in metrics
    assert "tiny.mcap" in page  # the recording by its file name
    assert 'name="viewport"' in page


def test_plots_are_inline_svg_with_axes_and_legend(served: tuple[TestClient, str, str]) -> None:
    """A run with trajectory.tum, truth.tum and nees.json: its path over truth, the error over time and its robot
    NEES over time over its chi2(3) band, as inline SVG."""
    client, good, _ = served
    page = client.get(f"/ui/jobs/{good}").text
    svgs = re.findall(r"<svg .*?</svg>", page, re.S)
    assert len(svgs) == 3
    path, error, nees = svgs
    assert "x (m)" in path and "y (m)" in path and "ground truth" in path and "estimate" in path
    assert 'stroke="#7f7f7f"' in path and 'stroke="#1f77b4"' in path  # truth grey, estimate blue
    assert "position error (m)" in error and "(s)" in error
    assert "robot pose NEES" in nees and nees.count('class="band"') == 1 and "of chi2(3): 0.216 to 9.35" in nees
    assert re.findall(r'<polyline [^>]*stroke="([^"]+)"', nees) == ["#1f77b4"]  # the estimate's NEES, blue
    assert "http" not in page.split('id="plots"')[1].split("</section>")[0].replace("http://www.w3.org/2000/svg", "")


def test_files_are_listed_and_served_from_the_run_only(served: tuple[TestClient, str, str], tmp_path: Path) -> None:
    """Every run file is listed and downloadable; names that leave the run directory are 404 or refused."""
    client, good, _ = served
    page = client.get(f"/ui/jobs/{good}").text
    listed = re.findall(rf'href="/ui/jobs/{good}/files/([^"]+)"', page)
    assert {"trajectory.tum", "truth.tum", "metrics.json", "manifest.json", "log.txt", "run.rrd"} <= set(listed)
    tum = client.get(f"/ui/jobs/{good}/files/trajectory.tum")
    assert tum.status_code == 200 and tum.headers["content-type"].startswith("text/plain")
    assert client.get(f"/ui/jobs/{good}/files/run.rrd").content[:4] == b"RRF2"
    runs = Path(client.app.state.settings.runs_dir)  # type: ignore[attr-defined]
    (runs / good / "escape").symlink_to(runs / "jobs.sqlite")
    for name in ("..%2Fjobs.sqlite", "..%2F..%2Fjobs.sqlite", ".hidden", "escape", "nope.txt", "%2Fetc%2Fpasswd"):
        assert client.get(f"/ui/jobs/{good}/files/{name}").status_code in (404, 422), name
    assert "escape" not in re.findall(rf'href="/ui/jobs/{good}/files/([^"]+)"', client.get(f"/ui/jobs/{good}").text)


def test_failed_job_shows_its_whole_error_and_log(served: tuple[TestClient, str, str]) -> None:
    """A failed job: the whole error in a block of its own, a log link and the log's last lines."""
    client, _, bad = served
    job = client.get(f"/jobs/{bad}").json()
    page = client.get(f"/ui/jobs/{bad}").text
    block = re.search(r'<pre class="error" id="job-error">(.*?)</pre>', page, re.S)
    assert block is not None and html.unescape(block.group(1)) == job["error"]
    assert f'href="/ui/jobs/{bad}/files/log.txt" id="log-link"' in page
    assert 'id="log-tail"' in page and "FAILED" in page
    assert 'id="delete-job"' in page and 'id="cancel-job"' not in page


def test_running_job_shows_percent_elapsed_eta_and_cancel(tmp_path: Path) -> None:
    """A running job at 25 % after 30 s: "25 %", elapsed 30 s, about 1.5 min left, and a Cancel button."""
    import sqlite3

    client = TestClient(create_app(Settings(allowed_hosts=("testserver",), data_dir=tmp_path, workers=1),
                                   executor=InlineExecutor()))
    store: Store = client.app.state.jobs.store  # type: ignore[attr-defined]
    from slamreplay.api.service.store import RecordingRow

    store.add_recording(RecordingRow("a" * 64, "sim.mcap", 1, [], 0, 0, 0, 0.0))
    job_id = "c" * 32
    store.add_job(job_id, "a" * 64, "odometry", {"range_sigma_m": 0.1}, 0)
    store.claim_next()
    with sqlite3.connect(store.path) as conn:
        conn.execute("UPDATE jobs SET progress = 0.25, started = ? WHERE id = ?", (time.time() - 30, job_id))
    page = client.get(f"/ui/jobs/{job_id}").text
    assert '<span id="job-progress">25 %</span>' in page
    assert re.search(r"elapsed 3\d\.\d s, about 1 min 3\d s left", page)  # 30 s for 25 %: 90 s more
    assert f'href="/ui/jobs/{job_id}/cancel?next=/ui/jobs/{job_id}"' in page
    assert "range_sigma_m" in page.split('id="config-table"')[1] and ">user<" in page


def test_nice_ticks() -> None:
    """Ticks are round numbers covering the range."""
    assert nice_ticks(0.0, 1.0) == [0.0, 0.2, 0.4, 0.6, 0.8, 1.0]
    assert nice_ticks(-3.2, 7.9) == [-2.0, 0.0, 2.0, 4.0, 6.0]
    assert nice_ticks(5.0, 5.0) == [5.0]
