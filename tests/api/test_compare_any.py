"""Compare anything: two runs of any kind as `diff` does, several side by side, and unpaired suites/jobs said so."""

from __future__ import annotations

import re
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


@pytest.fixture(scope="module")
def client(tmp_path_factory: pytest.TempPathFactory) -> Iterator[TestClient]:
    """A running app (in-thread jobs) over a fresh data directory."""
    app = create_app(Settings(allowed_hosts=("testserver",), data_dir=tmp_path_factory.mktemp("data"), workers=1),
                     executor=InlineExecutor())
    with TestClient(app) as c:
        yield c


@pytest.fixture(scope="module")
def runs(client: TestClient, tmp_path_factory: pytest.TempPathFactory) -> dict[str, str]:
    """One tiny recording (uploaded as sim.mcap) through odometry seed 0, dslam seed 0 and odometry seed 1."""
    rec = write_tiny_recording(tmp_path_factory.mktemp("rec") / "tiny.mcap", n=60)
    rid = client.post("/recordings", content=rec.read_bytes(), params={"filename": "sim.mcap"}).json()["id"]
    out = {"rec": rid}
    for key, pipeline, seed in (("odo", "odometry", 0), ("dslam", "dslam", 0), ("odo1", "odometry", 1)):
        job = client.post("/jobs", json={"recording_id": rid, "pipeline": pipeline, "seed": seed}).json()
        assert wait_for(client, job["id"])["status"] == "succeeded"
        out[key] = job["id"]
    return out


def test_two_runs_of_other_pipelines_diff_as_diff_does(client: TestClient, runs: dict[str, str]) -> None:
    """Odometry against dslam on one recording: the pipeline is under What changed, the ATE has unit and verdict."""
    url = f"/ui/compare?runs={runs['odo']},{runs['dslam']}"
    page = client.get(url)
    assert page.status_code == 200, page.text
    changes = page.text[page.text.index('id="changes-table"'):page.text.index('id="metric-deltas"')]
    assert "<td>pipeline</td><td><code>odometry</code></td><td><code>dslam</code></td>" in changes
    row = re.search(r'<tr class="v-(\w+)"><td title="[^"]*">ape_rmse_m</td><td>m</td>', page.text)
    assert row is not None and row.group(1) == "better"  # dslam corrects the odometry's drift with landmarks
    assert '<span class="verdict better">better</span>' in page.text
    assert "sim.mcap" in page.text and runs["rec"] not in page.text  # the recording by the name it was uploaded as
    assert page.text.count("<polyline") >= 3  # A, B and the ground truth
    data = client.get("/compare", params={"runs": f"{runs['odo']},{runs['dslam']}"}).json()
    ate = next(m for m in data["metrics"] if m["name"] == "ape_rmse_m")
    assert ate["verdict"] == "better" and ate["unit"] == "m" and ate["direction"] == "lower is better"
    assert {"field": "pipeline", "a": "odometry", "b": "dslam", "only": False} in data["changes"]


def test_compare_link_of_the_runs_table_is_no_longer_422(client: TestClient, runs: dict[str, str]) -> None:
    """/compare?runs= answers JSON, and a browser (Accept: text/html) goes to the page at the same runs; the runs
    table's Compare selected leads there."""
    ids = f"{runs['odo']},{runs['dslam']}"
    r = client.get(f"/compare?runs={ids}", headers={"Accept": "text/html"}, follow_redirects=False)
    assert r.status_code == 303 and r.headers["location"] == f"/ui/compare?runs={ids.replace(',', '%2C')}"
    sel = client.get("/ui/runs/compare", params={"sel": [runs["odo"], runs["dslam"]]}, follow_redirects=False)
    assert sel.status_code == 303 and sel.headers["location"] == f"/ui/compare?runs={ids}"  # no page between


def test_comparison_rrd_names_runs_as_the_user_knows_them(client: TestClient, runs: dict[str, str]) -> None:
    """The comparison .rrd of two runs is made from run directories named by their labels, not server paths."""
    r = client.get("/diff.rrd", params={"a": runs["odo"][:8], "b": runs["dslam"][:8]})
    assert r.status_code == 200 and len(r.content) > 1000
    labels = client.app.state.settings.runs_dir / "diffs" / ".labels"  # type: ignore[attr-defined]
    names = sorted(p.name for p in labels.glob("*/*"))
    assert names == sorted([f"{runs['dslam'][:8]}: dslam on sim.mcap, seed 0",
                            f"{runs['odo'][:8]}: odometry on sim.mcap, seed 0"])


def test_three_runs_overlay_three_trajectories(client: TestClient, runs: dict[str, str]) -> None:
    """Three runs: one SVG with three coloured paths over the grey truth, metrics side by side, a link per pair."""
    ids = [runs["odo"], runs["dslam"], runs["odo1"]]
    page = client.get("/ui/compare", params={"runs": ",".join(ids)})
    assert page.status_code == 200, page.text
    svg = page.text[page.text.index("<svg"):page.text.index("</svg>")]
    colours = re.findall(r'<polyline points="[^"]*" fill="none" stroke="(#[0-9a-f]{6})"', svg)
    assert len(colours) == 4 and colours[0] == "#7f7f7f" and len(set(colours[1:])) == 3  # truth, then 3 runs
    assert svg.count('class="legend"') == 1 and "ground truth of sim.mcap" in svg
    table = page.text[page.text.index('id="metrics-side-table"'):]
    head = table[:table.index("</tr>")]
    assert head.count('<th class="n"') == 3
    assert re.search(r"<td[^>]*>ape_rmse_m</td><td>m</td><td class=\"muted dir\">lower is better</td>", table)
    pairs = re.findall(r'href="/ui/compare\?runs=([0-9a-f]{32}),([0-9a-f]{32})"', page.text)
    assert len(pairs) == 3 and {frozenset(p) for p in pairs} == {frozenset(p) for p in
                                                                 [(ids[0], ids[1]), (ids[0], ids[2]),
                                                                  (ids[1], ids[2])]}


def test_unpaired_jobs_say_why_and_show_the_diff(client: TestClient, runs: dict[str, str]) -> None:
    """Two jobs with other seeds give no paired cell: one sentence says why, then the two-run diff (not an empty
    table headed 0 regressions); odometry against dslam works from the same form."""
    page = client.get("/ui/compare", params={"a": runs["odo"], "b": runs["odo1"]})
    assert page.status_code == 200, page.text
    assert "0 regression" not in page.text
    reason = re.search(r'id="unpaired-reason">([^<]*)<', page.text)
    assert reason is not None
    assert reason.group(1).startswith("A and B share no recording/pipeline/variant/seed cell")
    assert "seed 0" in reason.group(1) and "seed 1" in reason.group(1)
    assert "<td>seed</td><td><code>0</code></td><td><code>1</code></td>" in page.text
    other = client.get("/ui/compare", params={"a": runs["odo"], "b": runs["dslam"]})
    assert other.status_code == 200 and "odometry on sim.mcap" in other.text and 'id="delta-table"' in other.text


def test_unpaired_suites_say_why(client: TestClient, runs: dict[str, str]) -> None:
    """Two suites over other seeds: the page says why nothing pairs and shows their runs side by side."""
    suite = 'seeds = [{seed}]\n[recordings.sim]\nid = "{rid}"\n[pipelines.odometry]\n'
    ids = []
    for seed in (0, 1):
        r = client.post("/suites", content=suite.format(rid=runs["rec"][:8], seed=seed))
        assert r.status_code == 202, r.text
        ids.append(r.json()["id"])
        for cell in r.json()["cells"]:
            wait_for(client, cell["job_id"])
    page = client.get("/ui/compare", params={"a": ids[0][:8], "b": ids[1][:8]})
    assert page.status_code == 200, page.text
    assert 'id="unpaired-reason">A and B share no' in page.text and "0 regression" not in page.text
    assert 'id="metrics-side-table"' in page.text


def test_compare_form_never_starts_with_a_equal_b(client: TestClient, runs: dict[str, str]) -> None:
    """The main page's compare form selects different A and B; choosing the same one is a message."""
    home = client.get("/").text
    form = home[home.index('id="compare-form"'):home.index("</form>", home.index('id="compare-form"'))]
    selects = re.findall(r'<select name="([ab])">(.*?)</select>', form, re.S)
    chosen = {side: re.search(r'<option value="([0-9a-f]+)" selected>', body).group(1)  # type: ignore[union-attr]
              for side, body in selects}
    assert chosen["a"] != chosen["b"]
    same = client.get("/ui/compare", params={"a": runs["odo"], "b": runs["odo"]})
    assert same.status_code == 422 and "A and B are the same" in same.text


def test_too_few_runs_and_unfinished_runs_are_one_line(client: TestClient, runs: dict[str, str],
                                                       tmp_path: Path) -> None:
    """One run is a 422 saying how to ask; a malformed id in runs= is a 404 naming it."""
    r = client.get("/compare", params={"runs": runs["odo"]})
    assert r.status_code == 422 and "at least two runs" in r.json()["detail"]
    r = client.get("/compare", params={"runs": f"{runs['odo']},zz-top"})
    assert r.status_code == 404 and "'zz-top'" in r.json()["detail"]


def test_position_error_over_time_overlaid_in_the_paths_colours(client: TestClient, runs: dict[str, str]) -> None:
    """Issue 41: the compare page draws each run's position error over time on one axis, one colour per run, the
    colours and legend of the trajectory overlay; each curve's peak is the run's robot_max_error_m."""
    from slamreplay.api.service.compare_runs import runs_of
    from slamreplay.api.web.compare_plots import overlay
    from slamreplay.api.web.svg_plots import RUN_COLOURS

    jobs = client.app.state.jobs  # type: ignore[attr-defined]
    ids = [runs["odo"], runs["dslam"], runs["odo1"]]
    paths, errors = overlay(jobs, runs_of(jobs, ids))
    for svg in (paths, errors):
        assert all(f'stroke="{c}"' in svg for c in RUN_COLOURS[:3]) and f'stroke="{RUN_COLOURS[3]}"' not in svg
        assert all(f"{i}: {job[:8]}" in svg for i, job in enumerate(ids, 1))
    page = client.get("/ui/compare", params={"runs": ",".join(ids)})
    assert 'id="error-over-time"' in page.text and "position error over time of 3 runs" in page.text

    import numpy as np

    from slamreplay.replay.engine.trajectory import TRUTH_TUM_ARTIFACT, TUM_ARTIFACT, paired_with_truth, read_tum

    checked = 0
    for job in ids:  # the curve drawn is the error the metrics report (the pipelines that report its peak)
        if "robot_max_error_m" not in jobs.metric_values(job):
            continue
        checked += 1
        t, est = read_tum((jobs.run_dir(job) / TUM_ARTIFACT).read_text())
        tt, truth = read_tum((jobs.run_dir(job) / TRUTH_TUM_ARTIFACT).read_text())
        paired = paired_with_truth(t, est, tt)
        assert paired is not None
        peak = float(np.hypot(*(paired[:, :2] - truth[:, :2]).T).max())
        assert peak == pytest.approx(jobs.metric_values(job)["robot_max_error_m"], rel=1e-6)  # TUM: 9 decimals
    assert checked == 2


def test_nees_over_time_with_its_band_in_the_paths_colours(client: TestClient, runs: dict[str, str]) -> None:
    """Issue 41: the compare page draws the robot NEES over time of each run that has one (dslam's nees.json: a
    point per scan), in its trajectory's colour, over one shaded chi2(3) 95 % band; the odometry runs say why they
    have none; runs without a NEES at all get no NEES plot."""
    from scipy.stats import chi2

    from slamreplay.api.service.compare_runs import runs_of
    from slamreplay.api.web.compare_plots import nees_plot
    from slamreplay.api.web.svg_plots import RUN_COLOURS
    from slamreplay.replay.evaluation.nees_series import NEES_ARTIFACT, read_nees

    jobs = client.app.state.jobs  # type: ignore[attr-defined]
    ids = [runs["odo"], runs["dslam"], runs["odo1"]]
    svg, without, note = nees_plot(jobs, runs_of(jobs, ids))
    robot = read_nees((jobs.run_dir(runs["dslam"]) / NEES_ARTIFACT).read_bytes())["robot"]
    assert robot.mean == pytest.approx(jobs.metric_values(runs["dslam"])["robot_nees_mean"], rel=1e-12)
    lines = re.findall(r'<polyline points="([^"]*)" fill="none" stroke="([^"]+)"', svg)
    assert [colour for _, colour in lines] == [RUN_COLOURS[1]]  # dslam is the second run: the paths' 2nd colour
    assert len(lines[0][0].split()) == len(robot.nees) == robot.steps
    assert svg.count('class="band"') == 1
    low, high = chi2.ppf(0.025, 3), chi2.ppf(0.975, 3)
    assert f"consistent, 95 % of chi2(3): {low:.3g} to {high:.3g}" in svg and f"2: {runs['dslam'][:8]} (dslam" in svg
    assert without == [f"1: {runs['odo'][:8]} (odometry, seed 0): odometry reports no robot pose NEES "
                       "(robot_nees_mean)", f"3: {runs['odo1'][:8]} (odometry, seed 1): odometry reports no robot "
                       "pose NEES (robot_nees_mean)"]
    assert note == ""  # 8 scans: drawn as they are
    page = client.get("/ui/compare", params={"runs": ",".join(ids)}).text
    assert page.count('id="nees-over-time"') == 1 and page.count("<li>1: ") == 1 and 'id="no-nees"' in page
    two = client.get("/ui/compare", params={"runs": f"{runs['odo']},{runs['dslam']}"}).text
    assert 'id="nees-over-time"' in two and "A: " in two[two.index('id="no-nees"'):]
    none = client.get("/ui/compare", params={"runs": f"{runs['odo']},{runs['odo1']}"}).text
    assert 'id="error-over-time"' in none and "nees-over-time" not in none and "no-nees" not in none
    assert nees_plot(jobs, runs_of(jobs, [runs["odo"], runs["odo1"]])) == ("", [], "")


def test_a_long_run_is_drawn_at_every_kth_scan_from_its_nees_json(tmp_path: Path) -> None:
    """A nees.json of 2,500 scans (every 3rd kept): drawn as its 834 points, from 0 s without a truth.tum, its band
    the file's; the compare note says which scans; ordinals read as English."""
    import numpy as np

    from slamreplay.api.web.compare_plots import nees_svg, ordinal, robot_nees
    from slamreplay.replay.evaluation.nees_series import NEES_ARTIFACT, NeesSeries, chi2_band, nees_artifact

    t_ns = 5_000_000_000 + np.arange(2500, dtype=np.int64) * 200_000_000
    series = NeesSeries("robot", 3, (0.0, chi2_band(3)[1]), t_ns, np.full(2500, 3.0))
    (tmp_path / NEES_ARTIFACT).write_bytes(nees_artifact({"robot": series}))
    nees = robot_nees(tmp_path)
    assert nees is not None and (nees.stride, nees.steps, len(nees.values)) == (3, 2500, 834)
    assert nees.t[0] == 0.0 and nees.t[1] == pytest.approx(0.6) and nees.band == (0.0, chi2_band(3)[1])
    assert nees.band_text == "consistent, 95 %: 0 to 9.35 (the truth is an estimate)"
    svg = nees_svg([("1: run", nees.t, nees.values)], [nees], "t")
    points = re.findall(r'<polyline points="([^"]*)"', svg)
    assert len(points) == 1 and len(points[0].split()) == 834 and svg.count('class="band"') == 1
    assert [ordinal(n) for n in (1, 2, 3, 4, 11, 12, 13, 21, 22, 101)] == [
        "1st", "2nd", "3rd", "4th", "11th", "12th", "13th", "21st", "22nd", "101st"]
    assert robot_nees(tmp_path / "absent") is None
