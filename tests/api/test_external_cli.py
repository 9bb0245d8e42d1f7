"""The command line and the service for SLAM systems outside slamreplay: evaluate, export, run
--check-determinism, diff/compare on programs that are not deterministic, and the service's permission."""

from __future__ import annotations

import json
import warnings
from pathlib import Path

import numpy as np
import pytest
from conftest import write_tiny_recording
from service_helpers import InlineExecutor, wait_for

with warnings.catch_warnings():
    warnings.simplefilter("ignore", DeprecationWarning)
    from fastapi.testclient import TestClient

from patience import deadline as give_up_at

from slamreplay.api.app import create_app
from slamreplay.api.cli.command import main
from slamreplay.api.service.settings import Settings
from slamreplay.recorder.plugins import refresh
from slamreplay.replay.engine.declared import DECLARATIONS_ENV

# dead reckoning of odometry.csv on stdin, plus noise from os.urandom when argv[2] == "noisy"
PROGRAM = '''
import math, os, sys
out = open(sys.argv[1], "w")
noisy = sys.argv[2:] == ["noisy"]
x = 0.0
for line in sys.stdin.read().splitlines()[1:]:
    t, ox, oy, oth = line.split(",")
    t = int(t)
    x = float(ox) + (int.from_bytes(os.urandom(2), "big") * 1e-6 if noisy else 0.0)
    out.write(f"{t // 10**9}.{t % 10**9:09d} {x!r} {float(oy)!r} 0 0 0 0 1\\n")
'''


@pytest.fixture
def declared(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """Two external pipelines, ``steady`` and ``noisy``, declared through $SLAMREPLAY_PIPELINES; a recording."""
    (tmp_path / "prog.py").write_text(PROGRAM)
    (tmp_path / "ext.toml").write_text(
        "[pipelines.steady]\ncommand = ['{python}', 'prog.py', '{out}/trajectory.tum']\nexports = ['odometry_csv']\n"
        "stdin = '{exports}/odometry.csv'\n"
        "[pipelines.noisy]\ncommand = ['{python}', 'prog.py', '{out}/trajectory.tum', 'noisy']\n"
        "exports = ['odometry_csv']\nstdin = '{exports}/odometry.csv'\n")
    monkeypatch.setenv(DECLARATIONS_ENV, str(tmp_path / "ext.toml"))
    refresh()
    return write_tiny_recording(tmp_path / "tiny.mcap")


def test_evaluate_and_export_commands(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """`evaluate` of a run's trajectory.tum prints the run's ATE; `export` writes odometry.csv; a bad estimate is
    one line and exit 2."""
    rec = write_tiny_recording(tmp_path / "tiny.mcap")
    assert main(["run", str(rec), "--pipeline", "odometry", "--out", str(tmp_path / "odo"), "-q"]) == 0
    capsys.readouterr()
    assert main(["evaluate", str(tmp_path / "odo" / "trajectory.tum"), "--recording", str(rec),
                 "--out", str(tmp_path / "ev")]) == 0
    ate = json.loads((tmp_path / "odo" / "metrics.json").read_text())["metrics"]["ape_rmse_m"]["value"]
    assert f"ape_rmse_m                   {ate:.6g}" in capsys.readouterr().out
    assert main(["trajectory", str(tmp_path / "ev"), "--json"]) == 0
    capsys.readouterr()
    assert main(["export", str(rec), "--out", str(tmp_path / "exp"), "--what", "odometry_csv,range_bearing_csv",
                 "-q"]) == 0
    lines = (tmp_path / "exp" / "odometry.csv").read_text().splitlines()
    assert lines[0] == "t_ns,x_m,y_m,yaw_rad" and len(lines) == 101 and lines[1] == "1000000000,0.0,0.0,0.0"
    assert (tmp_path / "exp" / "range_bearing.csv").read_text().count("\n") == 1 + 20 * 4
    (tmp_path / "bad.tum").write_text("1.0 2 3\n")
    assert main(["evaluate", str(tmp_path / "bad.tum"), "--recording", str(rec), "--out", str(tmp_path / "b")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "bad.tum, line 1: expected 8 fields" in err
    assert main(["export", str(rec), "--out", str(tmp_path / "x"), "--what", "lidar"]) == 2
    assert "unknown export 'lidar'" in capsys.readouterr().err
    # a --topic-map that is not A=B: one line and exit 2, as for run and record (once an internal error, exit 3)
    assert main(["export", str(rec), "--out", str(tmp_path / "y"), "--what", "odometry_csv",
                 "--topic-map", "/wheel/odom"]) == 2
    assert capsys.readouterr().err == "slamreplay: error: --topic-map expects A=B, got '/wheel/odom'\n"
    assert not (tmp_path / "y").exists()


def test_check_determinism_diff_and_compare(declared: Path, tmp_path: Path,
                                           capsys: pytest.CaptureFixture[str]) -> None:
    """run --check-determinism records it; diff and compare name the run that is not deterministic; the flag
    on a built-in pipeline is one line, exit 2; `pipelines NAME` shows a declared pipeline."""
    rec = declared
    for name in ("steady", "noisy"):
        assert main(["run", str(rec), "--pipeline", name, "--out", str(tmp_path / name), "--check-determinism",
                     "-q"]) == 0
    det = {n: json.loads((tmp_path / n / "manifest.json").read_text())["pipeline_run"]["determinism"]["deterministic"]
           for n in ("steady", "noisy")}
    assert det == {"steady": True, "noisy": False}
    capsys.readouterr()
    main(["diff", str(tmp_path / "steady"), str(tmp_path / "noisy")])
    assert "note: run B is not deterministic" in capsys.readouterr().out
    assert main(["run", str(rec), "--pipeline", "noisy", "--out", str(tmp_path / "noisy2"), "-q"]) == 0
    capsys.readouterr()
    main(["compare", str(tmp_path / "noisy"), str(tmp_path / "noisy2")])
    assert "note: not deterministic (two runs of its program on the same input differed)" in capsys.readouterr().out
    assert main(["run", str(rec), "--pipeline", "odometry", "--out", str(tmp_path / "o"), "--check-determinism"]) == 2
    assert "pipeline odometry is slamreplay code" in capsys.readouterr().err
    assert main(["pipelines", "steady"]) == 0
    assert "declared in" in capsys.readouterr().out


def test_service_runs_external_pipelines_only_when_allowed(declared: Path, tmp_path: Path) -> None:
    """By default a job of an external pipeline is 403 naming the setting; with it, the job runs."""
    for allowed in (False, True):
        app = create_app(Settings(allowed_hosts=("testserver",), data_dir=tmp_path / f"data-{allowed}", workers=1,
                                  allow_external_pipelines=allowed), executor=InlineExecutor())
        with TestClient(app) as client:
            rid = client.post("/recordings", content=declared.read_bytes(), params={"filename": "t.mcap"}).json()["id"]
            r = client.post("/jobs", json={"recording_id": rid, "pipeline": "steady"})
            if not allowed:
                assert r.status_code == 403 and "SLAMREPLAY_ALLOW_EXTERNAL_PIPELINES" in r.json()["detail"]
                suite = ('declarations = ["x.toml"]\n[recordings.r]\nid = "' + rid + '"\n[pipelines.odometry]\n')
                s = client.post("/suites", content=suite, headers={"content-type": "application/toml"})
                assert s.status_code == 422 and "cannot declare pipelines" in s.json()["detail"]
                continue
            assert r.status_code == 202, r.json()
            assert wait_for(client, r.json()["id"])["status"] == "succeeded"
    assert Settings.from_env({"SLAMREPLAY_ALLOW_EXTERNAL_PIPELINES": "true"}).allow_external_pipelines


def test_a_suite_of_external_and_builtin_pipelines_in_the_service(declared: Path, tmp_path: Path) -> None:
    """The operator allows external pipelines and declares them ($SLAMREPLAY_PIPELINES): a suite of two external
    programs and odometry runs in the service, every cell lands in the runs table (filterable by pipeline), the
    external one equals odometry (both dead reckoning), and two of its runs compare on the compare page."""
    import time

    app = create_app(Settings(allowed_hosts=("testserver",), data_dir=tmp_path / "data", workers=1,
                              allow_external_pipelines=True), executor=InlineExecutor())
    with TestClient(app) as client:
        rid = client.post("/recordings", content=declared.read_bytes(), params={"filename": "t.mcap"}).json()["id"]
        suite = ('name = "external"\nseeds = [0, 1]\n[recordings.r]\nid = "' + rid + '"\n'
                 "[pipelines.steady]\n[pipelines.noisy]\n[pipelines.odometry]\n")
        r = client.post("/suites", content=suite, headers={"content-type": "application/toml"})
        assert r.status_code == 202, r.text
        deadline = give_up_at(60)
        while (doc := client.get(f"/suites/{r.json()['id']}").json())["progress"]["ended"] < 6:
            assert time.monotonic() < deadline, doc
            time.sleep(0.05)
        assert {c["status"] for c in doc["cells"]} == {"succeeded"}
        table = client.get("/runs", params={"cols": "ape_rmse_m"}).text
        for name in ("steady", "noisy", "odometry"):
            assert f">{name}<" in table
        rows = client.get("/runs.csv", params={"pipeline": "steady", "cols": "ape_rmse_m"}).text.strip().splitlines()
        assert len(rows) == 3 and all(",steady," in row for row in rows[1:])  # a header and the two seeds
        jobs = {(c["pipeline"], c["seed"]): c["job_id"] for c in doc["cells"]}
        ape = {(c["pipeline"], c["seed"]): c["metrics"]["ape_rmse_m"] for c in doc["cells"]}
        assert ape[("steady", 0)] == pytest.approx(ape[("odometry", 0)], rel=1e-9)
        page = client.get("/ui/compare", params={"runs": f"{jobs[('steady', 0)]},{jobs[('odometry', 0)]}"})
        assert page.status_code == 200 and "ape_rmse_m" in page.text


def test_export_ros2_bag_reads_back(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """The ros2_bag export: rosbags reads every odometry pose and range-bearing scan back exactly (CDR float64),
    and slamreplay's own ROS 2 importer records its /odom as the original /odom."""
    from rosbags.highlevel import AnyReader

    from slamreplay.recorder.messages import TOPIC_ODOM, TOPIC_RANGE_BEARING
    from slamreplay.replay.engine.reader import RecordingReader

    rec = write_tiny_recording(tmp_path / "tiny.mcap")
    assert main(["export", str(rec), "--out", str(tmp_path / "exp"), "--what", "ros2_bag", "-q"]) == 0
    bag = tmp_path / "exp" / "ros2_bag"
    assert sorted(p.name for p in bag.iterdir()) == ["metadata.yaml", "ros2_bag.db3"]
    orig = RecordingReader(rec)
    odom = [e.msg.xy_yaw for e in orig.messages([TOPIC_ODOM])]
    scans = [e.msg for e in orig.messages([TOPIC_RANGE_BEARING])]
    with AnyReader([bag]) as reader:
        got: dict[str, list[object]] = {}
        for conn, _t, raw in reader.messages():
            got.setdefault(conn.topic, []).append(reader.deserialize(raw, conn.msgtype))
    assert len(got["/odom"]) == len(odom) == 100 and len(got["/landmarks/range_bearing"]) == len(scans) == 20
    last = got["/odom"][-1]
    assert (last.pose.pose.position.x, last.pose.pose.position.y) == (odom[-1][0], odom[-1][1])
    assert 2 * np.arctan2(last.pose.pose.orientation.z, last.pose.pose.orientation.w) == pytest.approx(odom[-1][2])
    for a, b in zip(got["/landmarks/range_bearing"], scans, strict=True):
        assert a.landmark_ids.tolist() == b.landmark_ids.tolist() and a.ranges_m.tolist() == b.ranges_m.tolist()
    assert main(["record", "ros2", str(bag), "--out", str(tmp_path / "back.mcap"), "-q"]) == 0
    back = [e.msg.xy_yaw for e in RecordingReader(tmp_path / "back.mcap").messages([TOPIC_ODOM])]
    np.testing.assert_allclose(np.array(back), np.array(odom), atol=1e-12)


@pytest.mark.slow
def test_compare_two_revisions_of_an_external_program(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                                      monkeypatch: pytest.MonkeyPatch) -> None:
    """A program declared in the repository with a ``build`` key: ``compare rev:A rev:B`` builds and runs each
    revision's own program in its worktree, so a bias introduced in B's source fails the comparison (exit 1)
    naming the trajectory metrics; the program's source at A is unchanged in the checkout."""
    import subprocess
    import sys

    from conftest import REPO

    def git(*args: str) -> None:
        subprocess.run(["git", "-c", "user.name=t", "-c", "user.email=t@t", "-C", str(clone), *args], check=True,
                       capture_output=True)

    clone = tmp_path / "clone"
    subprocess.run(["git", "clone", "-q", "--no-hardlinks", str(REPO), str(clone)], check=True)
    ext = clone / "ext"
    ext.mkdir()
    (ext / "prog_src.py").write_text(PROGRAM)
    # the "compiler": build/ is ignored by git, so each worktree holds only the source until its build runs
    (ext / "build.py").write_text("import pathlib, shutil\npathlib.Path('build').mkdir(exist_ok=True)\n"
                                  "shutil.copy('prog_src.py', 'build/prog.py')\n")
    (ext / "pipeline.toml").write_text(
        "[pipelines.dr]\ncommand = ['{python}', 'build/prog.py', '{out}/trajectory.tum']\n"
        "exports = ['odometry_csv']\nstdin = '{exports}/odometry.csv'\nbuild = ['{python}', 'build.py']\n")
    git("add", "ext")
    git("commit", "-qm", "dead reckoning")
    (ext / "prog_src.py").write_text(PROGRAM.replace("x = float(ox)", "x = 1.05 * float(ox)"))
    git("commit", "-qam", "a 5 % scale bias")
    write_tiny_recording(tmp_path / "tiny.mcap")
    suite = tmp_path / "s.toml"
    suite.write_text(f'declarations = ["{ext / "pipeline.toml"}"]\nseeds = [0]\n[recordings.tiny]\n'
                     'path = "tiny.mcap"\n[pipelines.dr]\n')
    monkeypatch.chdir(clone)
    monkeypatch.setenv("SLAMREPLAY_REV_PYTHON", sys.executable)  # no virtualenv built: still each worktree's code
    monkeypatch.setenv("SLAMREPLAY_CACHE", str(tmp_path / "cache"))
    refresh()
    code = main(["compare", "rev:HEAD~1", "rev:HEAD", "--suite", str(suite)])
    out = capsys.readouterr().out
    assert code == 1, out
    assert "ape_rmse_m" in out and "regression" in out
    code = main(["compare", "rev:HEAD~1", "rev:HEAD~1", "--suite", str(suite)])
    assert code == 0, capsys.readouterr().out
