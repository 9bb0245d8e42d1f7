"""`slamreplay suite run` and `slamreplay compare` end to end: cache reuse, failures, revisions, exit codes."""

from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import pytest
from conftest import REPO, write_tiny_recording
from test_cli import assert_bad_input, run_cli

from slamreplay.replay.runs import suite_run


@pytest.fixture(autouse=True)
def cache(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """Each test its own recording / revision cache."""
    monkeypatch.setenv("SLAMREPLAY_CACHE", str(tmp_path / "cache"))
    return tmp_path / "cache"


def tiny_suite(tmp_path: Path, extra: str = "") -> Path:
    write_tiny_recording(tmp_path / "tiny.mcap", n=60)
    (tmp_path / "broken.mcap").write_bytes(b"not an mcap file at all")
    suite = tmp_path / "suite.toml"
    suite.write_text('seeds = [0, 1]\n[recordings.tiny]\npath = "tiny.mcap"\n[recordings.sim]\nsim = "sim-landmarks"\n'
                     'args = { duration-s = 8, landmarks = 9 }\nseeds = [1]\n[pipelines.odometry]\n'
                     '[pipelines.dslam.variants]\ndefault = {}\nloose = { range_sigma_m = 0.3 }\n' + extra)
    return suite


def assert_notes_then_error(code: int, err: str, pattern: str) -> list[str]:
    """Notes and progress lines (no error, no traceback), then exit 2 with one error line matching pattern;
    returns the notes."""
    lines = [line for line in err.splitlines() if line.strip()]
    assert lines and not any(line.startswith("slamreplay: error") for line in lines[:-1]), err
    assert_bad_input(code, lines[-1], pattern)
    return lines[:-1]


def manifests(rows: list[dict[str, Any]]) -> dict[str, str]:
    return {r["run_dir"]: json.loads((Path(r["run_dir"]) / "manifest.json").read_text())["run_id"] for r in rows}


def test_suite_run_then_cached(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Every cell runs once; a second run of the suite re-runs none (same run ids) and takes well under 5 s."""
    suite, out = tiny_suite(tmp_path), tmp_path / "results"
    code, stdout, err = run_cli(["suite", "run", str(suite), "--out", str(out), "--jobs", "2"], capsys)
    assert code == 0, err
    rows = suite_run.read_results(out)
    assert len(rows) == 2 * 3 * 2  # (tiny, sim seed 1) x (odometry, dslam default, dslam loose) x seeds 0, 1
    assert all(r["status"] == "succeeded" and not r["cached"] for r in rows), rows
    dslam = next(r for r in rows if r["pipeline"] == "dslam" and r["variant"] == "loose")
    assert dslam["config"] == {"range_sigma_m": 0.3} and "ape_rmse_m" in dslam["metrics"]
    for key in ("recording_sha256", "config_hash", "code_version", "wall_s", "peak_rss_mib"):
        assert dslam[key], key
    assert dslam["code_version"] == suite_run.code_version()
    first = manifests(rows)
    tic = time.perf_counter()
    code, stdout, err = run_cli(["suite", "run", str(suite), "--out", str(out)], capsys)
    assert code == 0 and time.perf_counter() - tic < 5.0
    again = suite_run.read_results(out)
    assert all(r["cached"] for r in again) and manifests(again) == first
    assert "12 from cache, 0 run, 0 failed" in stdout
    report = tmp_path / "r.html"
    code, stdout, err = run_cli(["compare", str(out), str(out), "--report", str(report)], capsys)
    assert code == 0 and "0 regression(s)" in stdout, err
    text = report.read_text()
    assert "Estimated trajectories" in text and text.count("<polyline") == 4 * 12  # paths, errors: A and B
    assert text.count("position error (m) over time") == 12
    assert "<tr class='regression'>" not in text and "<tr class='unchanged'>" in text


def test_failed_cell_recorded_and_suite_goes_on(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A broken recording fails its cells only; the others succeed; the results say which and why."""
    suite = tmp_path / "s.toml"
    write_tiny_recording(tmp_path / "tiny.mcap", n=40)
    (tmp_path / "broken.mcap").write_bytes(b"not an mcap file at all")
    suite.write_text('[recordings.tiny]\npath = "tiny.mcap"\n[recordings.broken]\npath = "broken.mcap"\n'
                     "[pipelines.odometry]\n")
    code, stdout, err = run_cli(["suite", "run", str(suite), "--out", str(tmp_path / "res")], capsys)
    assert code == 0, err
    rows = {r["recording"]: r for r in suite_run.read_results(tmp_path / "res")}
    assert rows["tiny"]["status"] == "succeeded"
    assert rows["broken"]["status"] == "failed" and rows["broken"]["error"]
    assert "FAILED" in stdout


def test_topic_map_and_out_checks(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A recording's topic_map reaches its runs; --out must be a results directory or new."""
    from slamreplay.recorder import OdometryPose, Recorder

    with Recorder(tmp_path / "robot.mcap", source={"test": "renamed"}, seed=0) as rec:
        for k in range(30):
            rec.write("/robot/odom", OdometryPose(1_000_000_000 + k * 100_000_000, 0.1 * k, 0.0, 0.0))
    suite = tmp_path / "s.toml"
    suite.write_text('[recordings.robot]\npath = "robot.mcap"\ntopic_map = { "/robot/odom" = "/odom" }\n'
                     "[pipelines.odometry]\n")
    code, _out, err = run_cli(["suite", "run", str(suite), "--out", str(tmp_path / "res")], capsys)
    assert code == 0, err
    (row,) = suite_run.read_results(tmp_path / "res")
    assert row["status"] == "succeeded", row["error"]
    manifest = json.loads((Path(row["run_dir"]) / "manifest.json").read_text())
    assert manifest["recording"]["topic_map"] == {"/robot/odom": "/odom"}
    (tmp_path / "file").write_text("x")
    (tmp_path / "other").mkdir()
    (tmp_path / "other" / "mine.txt").write_text("x")
    for target, pattern in (("file", r"is a file"), ("other", r"holds other files")):
        code, _out, err = run_cli(["suite", "run", str(suite), "--out", str(tmp_path / target)], capsys)
        assert_bad_input(code, err, pattern)


def test_url_recording_fetched_once(tmp_path: Path, capsys: pytest.CaptureFixture[str], cache: Path) -> None:
    """A url recording is fetched through fsspec once, then served from the cache."""
    fsspec = pytest.importorskip("fsspec")
    fs = fsspec.filesystem("memory")
    fs.pipe("/suite-test/tiny.mcap", write_tiny_recording(tmp_path / "tiny.mcap", n=30).read_bytes())
    suite = tmp_path / "s.toml"
    suite.write_text('[recordings.remote]\nurl = "memory://suite-test/tiny.mcap"\n[pipelines.odometry]\n')
    for _ in range(2):
        code, _out, err = run_cli(["suite", "run", str(suite), "--out", str(tmp_path / "res")], capsys)
        assert code == 0, err
    (row,) = suite_run.read_results(tmp_path / "res")
    assert row["status"] == "succeeded" and row["cached"]
    assert len(list((cache / "downloads").iterdir())) == 1
    suite.write_text('[recordings.remote]\nurl = "memory://suite-test/missing.mcap"\n[pipelines.odometry]\n')
    code, _out, err = run_cli(["suite", "run", str(suite), "--out", str(tmp_path / "res2")], capsys)
    assert_bad_input(code, err, r"recording remote: cannot open memory://suite-test/missing\.mcap")


def test_code_version_of_a_dirty_tree(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Uncommitted changes: `<sha>-dirty+<hash of the diff>`, which changes with the diff."""
    repo = tmp_path / "repo"
    repo.mkdir()
    git = ["git", "-c", "user.name=t", "-c", "user.email=t@t", "-C", str(repo)]
    subprocess.run([*git, "init", "-q"], check=True)
    (repo / "f.py").write_text("x = 1\n")
    subprocess.run([*git, "add", "f.py"], check=True)
    subprocess.run([*git, "commit", "-qm", "c"], check=True)
    monkeypatch.setattr(suite_run, "SOURCE_ROOT", repo)
    monkeypatch.setattr(suite_run, "git_commit", lambda: "abc-dirty")
    (repo / "f.py").write_text("x = 2\n")
    v1 = suite_run.code_version()
    (repo / "f.py").write_text("x = 3\n")
    v2 = suite_run.code_version()
    assert v1.startswith("abc-dirty+") and v2.startswith("abc-dirty+") and v1 != v2
    monkeypatch.setattr(suite_run, "git_commit", lambda: "abc")
    assert suite_run.code_version() == "abc"


def write_results(path: Path, values: list[float], code: str) -> Path:
    path.mkdir(parents=True)
    rows = [{"recording": "landmarks", "recording_seed": i + 1, "pipeline": "dslam", "variant": "default",
             "seed": 0, "config": {}, "status": "succeeded", "error": None, "run_dir": str(path / f"run{i}"),
             "code_version": code, "metrics": {"landmark_rmse_m": v}, "better": {"landmark_rmse_m": "lower"},
             "tolerance": {"landmark_rmse_m": 1e-9}, "units": {"landmark_rmse_m": "m"}} for i, v in enumerate(values)]
    (path / "results.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))
    return path


def test_compare_exit_codes_and_reports(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A A: exit 0; clearly degraded B: exit 1 with the regression in the HTML (red) and markdown."""
    a = write_results(tmp_path / "a", [0.05, 0.08, 0.06], "aaa")
    b = write_results(tmp_path / "b", [0.075, 0.121, 0.089], "bbb")
    code, out, err = run_cli(["compare", str(a), str(a)], capsys)
    assert code == 0 and "0 regression(s)" in out, err
    html, md = tmp_path / "r.html", tmp_path / "s.md"
    code, out, err = run_cli(["compare", str(a), str(b), "--report", str(html), "--markdown", str(md)], capsys)
    assert code == 1 and "REGRESSION" in out and "landmark_rmse_m" in out, out + err
    assert "<tr class='regression'>" in html.read_text() and "landmark_rmse_m" in md.read_text()
    code, out, err = run_cli(["compare", str(a), str(b), "--tolerance", "landmark_rmse_m=100%", "--json"], capsys)
    assert code == 0 and json.loads(out)["regressions"] == []
    code, out, err = run_cli(["compare", str(a), str(b), "-q"], capsys)  # quiet: the verdict line alone
    assert code == 1 and out.splitlines() == ["Result: 1 regression(s): landmarks/dslam/default landmark_rmse_m"]


def test_compare_run_directories(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Two run directories compare as one cell with one seed (tolerance verdict)."""
    rec = write_tiny_recording(tmp_path / "tiny.mcap", n=40)
    for name in ("r1", "r2"):
        assert run_cli(["run", str(rec), "--pipeline", "odometry", "--out", str(tmp_path / name), "-q"], capsys)[0] == 0
    code, out, err = run_cli(["compare", str(tmp_path / "r1"), str(tmp_path / "r2")], capsys)
    assert code == 0 and "tolerance (one seed)" not in out and "unchanged" in out, out + err


@pytest.mark.parametrize(("args", "pattern"), [
    (["compare", "{a}", "{other}"], r"no cell in common"),
    (["compare", "{a}", "{tmp}/missing"], r"does not exist"),
    (["compare", "{a}", "{tmp}"], r"neither a run nor a results directory"),
    (["compare", "{a}", "rev:HEAD"], r"rev:HEAD needs --suite"),
    (["compare", "{a}", "{a}", "--tolerance", "x"], r"--tolerance expects NAME=VALUE"),
    (["compare", "{a}", "{a}", "--tolerance", "nope=1"], r"unknown metrics: nope"),
    (["compare", "{a}", "{a}", "--tolerance", "landmark_rmse=1"], r"rmse \(did you mean 'landmark_rmse_m'\?\)"),
    (["compare", "{a}", "{a}", "--suite", "{tmp}/bad.toml"], r"bad\.toml:2: seeds: must be"),
    (["suite", "run", "{tmp}/bad.toml", "--out", "{tmp}/o"], r"bad\.toml:2: seeds: must be"),
    (["suite", "run", "{tmp}/none.toml", "--out", "{tmp}/o"], r"suite file .* does not exist"),
    (["suite", "run", "{tmp}/ok.toml", "--out", "{tmp}/o", "--jobs", "0"], r"--jobs must be >= 1"),
    (["suite", "run", "{tmp}/ok.toml", "--out", "{tmp}/o", "--rev", "no-such-rev-xyz"], r"unknown revision"),
    (["suite", "run", "{tmp}/ok.toml", "--out", "{tmp}/o", "--rev", "HEAD", "--executor", "ray"],
     r"use --executor local"),
])
def test_bad_input_exits_2_with_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str], args: list[str],
                                         pattern: str) -> None:
    """Every bad input: exit 2, one line, no traceback, no results written."""
    a = write_results(tmp_path / "a", [0.05, 0.08, 0.06], "aaa")
    other = write_results(tmp_path / "other", [0.05], "aaa")
    rows = (other / "results.jsonl").read_text().replace('"dslam"', '"odometry"')
    (other / "results.jsonl").write_text(rows)
    (tmp_path / "bad.toml").write_text('[recordings.x]\nseeds = "one"\n')
    (tmp_path / "bad.toml").write_text('# a suite\nseeds = "one"\n[recordings.x]\nsim = "sim-landmarks"\n'
                                       "[pipelines.odometry]\n")
    (tmp_path / "ok.toml").write_text('[recordings.x]\nsim = "sim-landmarks"\n[pipelines.odometry]\n')
    argv = [x.format(a=a, other=other, tmp=tmp_path) for x in args]
    code, _out, err = run_cli(argv, capsys)
    assert_bad_input(code, err, pattern)
    assert not (tmp_path / "o" / "results.jsonl").exists()


def git(repo: Path, *args: str) -> str:
    return subprocess.run(["git", "-c", "user.name=t", "-c", "user.email=t@t", "-C", str(repo), *args],
                          check=True, capture_output=True, text=True).stdout.strip()


@pytest.mark.slow
def test_suite_at_a_revision(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                             monkeypatch: pytest.MonkeyPatch) -> None:
    """--rev runs cells with that revision's code (its worktree), reused on a second run; a relative --out is
    relative to where the command was typed, not to the worktree."""
    clone = tmp_path / "clone"
    subprocess.run(["git", "clone", "-q", "--no-hardlinks", str(REPO), str(clone)], check=True)
    sha = git(clone, "rev-parse", "HEAD")
    monkeypatch.chdir(clone)
    monkeypatch.setenv("SLAMREPLAY_REV_PYTHON", sys.executable)  # no pip install in the test; still the worktree
    suite = tmp_path / "s.toml"
    write_tiny_recording(tmp_path / "tiny.mcap", n=40)
    suite.write_text('seeds = [0, 1]\n[recordings.tiny]\npath = "tiny.mcap"\n[pipelines.odometry]\n')
    out = clone / "res"  # given relative to here: the cells run in the worktree, which must not change its meaning
    code, stdout, err = run_cli(["suite", "run", str(suite), "--out", "res", "--rev", "HEAD", "-q"], capsys)
    assert code == 0, err
    rows = suite_run.read_results(out)
    assert [r["status"] for r in rows] == ["succeeded", "succeeded"], rows
    assert {r["code_version"] for r in rows} == {sha}
    assert {r["git_commit"] for r in rows} == {sha}  # the manifest's: the run came from the worktree
    assert (tmp_path / "cache" / "revs" / sha / "ready").is_file()
    code, stdout, err = run_cli(["suite", "run", str(suite), "--out", str(out), "--rev", "HEAD"], capsys)
    assert code == 0 and "2 from cache" in stdout
    code, stdout, err = run_cli(["compare", "rev:HEAD", "rev:HEAD", "--suite", str(suite)], capsys)
    assert code == 0, err


@pytest.mark.slow
def test_revision_that_does_not_build(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                      monkeypatch: pytest.MonkeyPatch) -> None:
    """A revision whose package cannot be installed: exit 2, one line naming the build log, no worktree left."""
    repo = tmp_path / "repo"
    repo.mkdir()
    git(repo, "init", "-q")
    (repo / "pyproject.toml").write_text('[project]\nname = "slamreplay"\ndependencies = ["no-such-dist-x"]\n')
    git(repo, "add", "pyproject.toml")
    git(repo, "commit", "-qm", "broken")
    monkeypatch.chdir(repo)
    monkeypatch.delenv("SLAMREPLAY_REV_PYTHON", raising=False)
    monkeypatch.setenv("PIP_NO_INDEX", "1")
    (tmp_path / "ok.toml").write_text('[recordings.x]\nsim = "sim-landmarks"\n[pipelines.odometry]\n')
    code, _out, err = run_cli(["suite", "run", str(tmp_path / "ok.toml"), "--out", str(tmp_path / "o"),
                              "--rev", "HEAD"], capsys)
    notes = assert_notes_then_error(code, err, r"revision HEAD \([0-9a-f]{10}\) does not build: .*pip install.*"
                                                r"failed-build\.log")
    assert notes[0].startswith("suite ok @HEAD: building the environment of HEAD (") and "build.log" in notes[0]
    assert [n.split(": ", 1)[1].split(" (")[0] for n in notes[1:]] == [  # said before each slow step
        "git worktree add", "building the environment of its dependencies", "python -m venv", "pip install"]
    sha = git(repo, "rev-parse", "HEAD")
    assert not (tmp_path / "cache" / "revs" / sha).exists()
    assert len(git(repo, "worktree", "list").splitlines()) == 1  # the failed worktree is gone
    assert not (tmp_path / "o" / "results.jsonl").exists()
    assert (tmp_path / "cache" / "revs" / f"{sha}.failed-build.log").is_file()


@pytest.mark.slow
def test_bisect_finds_the_degrading_commit(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                           monkeypatch: pytest.MonkeyPatch) -> None:
    """good, harmless, degrading, harmless: bisect names the degrading commit; compare of the ends exits 1."""
    clone = tmp_path / "clone"
    subprocess.run(["git", "clone", "-q", "--no-hardlinks", str(REPO), str(clone)], check=True)
    slam = clone / "replay" / "pipelines" / "landmark_slam.py"
    for i, degrade in enumerate((False, True, False)):
        if degrade:
            text = slam.read_text()
            assert "msg.ranges_m[keep], msg.bearings_rad[keep]" in text
            slam.write_text(text.replace("msg.ranges_m[keep], msg.bearings_rad[keep]",
                                         "msg.ranges_m[keep] * 1.05, msg.bearings_rad[keep]"))
            git(clone, "commit", "-qam", "degrade: ranges read 5% long")
        else:
            (clone / f"note{i}.txt").write_text("harmless\n")
            git(clone, "add", f"note{i}.txt")
            git(clone, "commit", "-qm", f"harmless {i}")
    monkeypatch.chdir(clone)
    monkeypatch.setenv("SLAMREPLAY_REV_PYTHON", sys.executable)
    write_tiny_recording(tmp_path / "tiny.mcap", n=60)
    suite = tmp_path / "s.toml"
    suite.write_text('[recordings.tiny]\npath = "tiny.mcap"\n[pipelines.dslam]\n')
    code, out, err = run_cli(["bisect", "HEAD~3", "HEAD", "--suite", str(suite), "--metric", "landmark_rmse_m"],
                             capsys)
    assert code == 0, err
    assert out.strip().splitlines()[-1].endswith("degrade: ranges read 5% long"), out
    report = tmp_path / "r.md"
    code, out, err = run_cli(["compare", "rev:HEAD~3", "rev:HEAD", "--suite", str(suite), "--markdown", str(report)],
                             capsys)
    assert code == 1 and "landmark_rmse_m" in report.read_text() and "degrade: ranges read 5% long" in out
    for side in ("compare rev:HEAD~3: ", "compare rev:HEAD: "):  # stderr is not a terminal: plain lines
        assert f"{side}using the environment of " in err and f"{side}done (1/1 cells, 1 reused in " in err, err
    code, out, err = run_cli(["bisect", "HEAD~3", "HEAD~2", "--suite", str(suite), "--metric", "landmark_rmse_m"],
                             capsys)
    assert_notes_then_error(code, err, r"did not regress at HEAD~2")
    code, out, err = run_cli(["bisect", "HEAD~3", "HEAD", "--suite", str(suite), "--metric", "landmark_rmsee_m"],
                             capsys)
    assert_notes_then_error(code, err, r"--metric 'landmark_rmsee_m' is not a metric of this suite "
                                       r"\(did you mean 'landmark_rmse_m'\?\)")


@pytest.mark.ray
def test_suite_on_ray(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """--executor ray runs the cells as Ray tasks (the service's RayExecutor, no job store)."""
    pytest.importorskip("ray")
    write_tiny_recording(tmp_path / "tiny.mcap", n=40)
    suite = tmp_path / "s.toml"
    suite.write_text('seeds = [0, 1]\n[recordings.tiny]\npath = "tiny.mcap"\n[pipelines.odometry]\n')
    code, _out, err = run_cli(["suite", "run", str(suite), "--out", str(tmp_path / "res"), "--executor", "ray",
                               "--jobs", "2"], capsys)
    assert code == 0, err
    assert [r["status"] for r in suite_run.read_results(tmp_path / "res")] == ["succeeded"] * 2


def test_compare_markdown_links_with_a_base_url(tmp_path: Path) -> None:
    """`compare --markdown S.md --base-url URL`: runs inside the summary's folder are linked under URL; the
    regression leads the table."""
    from slamreplay.api.cli.command import main

    def results(name: str, values: list[float]) -> Path:
        out = tmp_path / name
        out.mkdir()
        rows = [{"recording": "lm", "recording_seed": i + 1, "pipeline": "dslam", "variant": "default", "seed": 0,
                 "config": {}, "status": "succeeded", "error": None, "run_dir": str(out / f"r{i}"),
                 "code_version": name, "metrics": {"landmark_rmse_m": v, "steps": 10.0},
                 "better": {"landmark_rmse_m": "lower", "steps": "none"},
                 "tolerance": {"landmark_rmse_m": 1e-6, "steps": 0.0}, "units": {"landmark_rmse_m": "m", "steps": ""}}
                for i, v in enumerate(values)]
        (out / "results.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))
        return out

    a, b = results("a", [0.05, 0.08, 0.06]), results("b", [0.075, 0.121, 0.089])
    assert main(["compare", str(a), str(b), "--markdown", str(tmp_path / "s.md"),
                 "--base-url", "https://ci.example/7/", "-q"]) == 1
    text = (tmp_path / "s.md").read_text()
    assert "[A1](https://ci.example/7/a/r0)" in text
    table = [line for line in text.splitlines() if line.startswith("| lm/")]
    assert "regression" in table[0] and "landmark_rmse_m" in table[0]
