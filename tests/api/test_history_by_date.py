"""History over the days the runs started: `slamreplay history --by date`, and ?by=date on the service."""

from __future__ import annotations

import json
import subprocess
import warnings
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from conftest import write_tiny_recording
from service_helpers import InlineExecutor
from test_cli import assert_bad_input, run_cli
from test_suites_routes import wait_suite

with warnings.catch_warnings():
    warnings.simplefilter("ignore", UserWarning)
    from fastapi.testclient import TestClient

from slamreplay.api.app import create_app
from slamreplay.api.service.settings import Settings
from slamreplay.replay.runs import history as hist
from slamreplay.replay.runs.revisions import Revision
from slamreplay.replay.runs.suite_run import CellJob


def git(repo: Path, *args: str) -> str:
    return subprocess.run(["git", "-c", "user.name=t", "-c", "user.email=t@t", "-C", str(repo), *args],
                          check=True, capture_output=True, text=True).stdout.strip()


class Nights:
    """Stands in for a revision's `slamreplay run`: a run started on night ``night`` (2024-05-<night>), its
    landmark_rmse_m ``level[night] + 0.001 * seed``."""

    def __init__(self, level: dict[int, float]) -> None:
        self.level, self.night = level, 1

    def __call__(self, revision: Revision, job: CellJob) -> str | None:
        job.run_dir.mkdir(parents=True, exist_ok=True)
        (job.run_dir / "manifest.json").write_text(json.dumps({"status": "succeeded", "timings": {
            "started_at": f"2024-05-{self.night:02d}T02:00:00+00:00"}}))
        (job.run_dir / "metrics.json").write_text(json.dumps({"metrics": {"landmark_rmse_m": {
            "value": self.level[self.night] + 0.001 * job.cell.seed, "better": "lower", "unit": "m",
            "tolerance": 1e-6, "rel_tolerance": 1e-3}}}))
        return None


def test_cli_by_date(tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch) -> None:
    """One commit, its suite run every night on that night's recording (same name, new bytes): --by date reads 5
    nights, the error doubled on night 4 judged from night 3; by-date.html and its markdown; index.html still the
    commits; --version of another commit is refused, and so is --version without --by date."""
    monkeypatch.setenv("SLAMREPLAY_CACHE", str(tmp_path / "cache"))
    repo = tmp_path / "repo"
    repo.mkdir()
    git(repo, "init", "-q")
    git(repo, "commit", "-q", "--allow-empty", "-m", "the code")
    git(repo, "commit", "-q", "--allow-empty", "-m", "newer code, never run")
    monkeypatch.chdir(repo)
    monkeypatch.setattr(hist, "prepare_revision", lambda repo, rev, cache, note=None: Revision(rev, rev, repo, (), {}))
    nights = Nights({1: 0.10, 2: 0.10, 3: 0.10, 4: 0.20, 5: 0.20})
    real = hist.run_history
    monkeypatch.setattr(hist, "run_history", lambda *a, **k: real(*a, **{**k, "run": nights}))
    suite = tmp_path / "s.toml"
    suite.write_text('seeds = [0, 1, 2]\n[recordings.r]\npath = "r.mcap"\n[pipelines.dslam]\n')
    out, md = tmp_path / "h", tmp_path / "summary.md"
    for night in range(1, 6):
        nights.night = night
        (tmp_path / "r.mcap").write_bytes(f"the recording of night {night}".encode())
        code, stdout, err = run_cli(["history", str(suite), "--revs", "HEAD~1", "--out", str(out), "--by", "date",
                                     "--markdown", str(md), "-q"], capsys)
        assert code == 0, err
    changes = json.loads((out / "changes-by-date.json").read_text())
    assert [(c["previous"], c["commit"], c["verdict"], c["recording"]) for c in changes] == [
        ("2024-05-03", "2024-05-04", "regression", "r")]
    page = (out / "by-date.html").read_text()
    assert "over the days it ran" in page and page.index("<code>2024-05-01</code>") < page.index(
        "<code>2024-05-05</code>") and "<script" not in page
    assert "| `2024-05-04` code " in md.read_text() and "by-date.html" in md.read_text()
    assert "1 commit(s)" in (out / "index.html").read_text()
    code, stdout, _err = run_cli(["history", str(suite), "--revs", "HEAD~1", "--out", str(out), "--by", "date",
                                  "--version", "HEAD~1"], capsys)
    assert code == 0 and "REGRESSION  r/dslam/default landmark_rmse_m" in stdout and "5 day(s)" in stdout
    code, _out, err = run_cli(["history", str(suite), "--revs", "HEAD~1", "--out", str(out), "--by", "date",
                               "--version", "HEAD", "-q"], capsys)
    assert_bad_input(code, err, r"no run of code version '[0-9a-f]{40}' in this history")
    code, _out, err = run_cli(["history", str(suite), "--revs", "HEAD~1", "--out", str(out), "--version", "HEAD"],
                              capsys)
    assert_bad_input(code, err, r"--version picks the runs of one code version for --by date")


@pytest.fixture
def client(tmp_path: Path) -> Iterator[TestClient]:
    app = create_app(Settings(allowed_hosts=("testserver",), data_dir=tmp_path / "data", workers=1),
                     executor=InlineExecutor())
    with TestClient(app) as c:
        yield c


def rewrite(client: TestClient, doc: dict[str, Any], day: int, ape: float) -> None:
    """A suite's runs as if started on 2024-05-<day>, their APE ``ape + 0.001 * seed``."""
    for cell in doc["cells"]:
        run = Path(client.app.state.jobs.run_dir(cell["job_id"]))  # type: ignore[attr-defined]
        manifest = json.loads((run / "manifest.json").read_text())
        manifest["timings"]["started_at"] = f"2024-05-{day:02d}T01:00:00+00:00"
        (run / "manifest.json").write_text(json.dumps(manifest))
        metrics = json.loads((run / "metrics.json").read_text())
        metrics["metrics"]["ape_rmse_m"]["value"] = ape + 0.001 * cell["seed"]
        (run / "metrics.json").write_text(json.dumps(metrics))


def test_service_by_date(client: TestClient, tmp_path: Path) -> None:
    """Four nights, each the suite on that night's new recording: ?by=date has one series over all recordings, four
    days, the APE's step at night 4 judged from night 3; the page switches between the two views and filters by
    code version; an unknown version is a 422."""
    for night, ape in ((1, 0.1), (2, 0.1), (3, 0.1), (4, 0.3)):
        rec = write_tiny_recording(tmp_path / f"night{night}.mcap", n=40, seed=night)
        rid = client.post("/recordings", content=rec.read_bytes(), params={"filename": rec.name}).json()["id"]
        toml = f'name = "nightly"\nseeds = [0, 1]\n[recordings.night{night}]\nid = "{rid}"\n[pipelines.odometry]\n'
        doc = wait_suite(client, client.post("/suites", content=toml).json()["id"])
        assert doc["progress"]["status"] == "succeeded", doc
        rewrite(client, doc, night, ape)
    r = client.get("/history/suites/nightly", params={"by": "date"})
    assert r.status_code == 200, r.text
    h = r.json()
    assert h["by"] == "date" and [d["date"] for d in h["days"]] == [f"2024-05-0{i}" for i in range(1, 5)]
    assert {(s["recording"], s["metric"]) for s in h["series"]} >= {("all recordings", "ape_rmse_m")}
    assert all(s["recording"] == "all recordings" for s in h["series"])  # each recording met once
    ape = [(c["previous_date"], c["date"], c["verdict"]) for c in h["changes"] if c["metric"] == "ape_rmse_m"]
    assert ape == [("2024-05-03", "2024-05-04", "regression")]
    code = h["days"][0]["versions"][0]
    assert len(client.get("/history/suites/nightly", params={"by": "date", "version": code}).json()["days"]) == 4
    assert client.get("/history/suites/nightly", params={"by": "date", "version": "0123456789"}).status_code == 422
    assert client.get("/history/suites/nightly", params={"by": "week"}).status_code == 422
    page = client.get("/ui/history/nightly", params={"by": "date"})
    assert page.status_code == 200 and 'id="history-days"' in page.text and 'id="history-by-commit"' in page.text
    days = page.text[page.text.index('id="history-days"'):]
    assert days.index("2024-05-01") < days.index("2024-05-04") and f'<option value="{code}">' in page.text
    assert 'href="/ui/history/nightly?by=date"' in client.get("/ui/history/nightly").text
    assert client.get("/ui/history/nightly", params={"by": "date", "version": code}).status_code == 200
