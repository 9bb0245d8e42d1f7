"""External pipelines: programs declared in TOML, run under limits, scored, recorded in the manifest."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest
from conftest import write_tiny_recording

from slamreplay.recorder.plugins import refresh
from slamreplay.replay.engine.declared import DECLARATIONS_ENV
from slamreplay.replay.engine.pipeline import get_pipeline, pipeline_plugins
from slamreplay.replay.errors import ReplayError
from slamreplay.replay.runs.run import run_recording
from tests.replay.view_runs import blueprint_views, matches, rrd_entities

# dead reckoning of odometry.csv on stdin, in the frame of the first pose: the built-in odometry pipeline's answer
DEAD_RECKONING = '''
import math, sys
out = open(sys.argv[1], "w")
prev = None
x = y = th = 0.0
for line in sys.stdin.read().splitlines()[1:]:
    t, ox, oy, oth = line.split(",")
    t, ox, oy, oth = int(t), float(ox), float(oy), float(oth)
    if prev is not None:
        px, py, pth = prev
        c, s = math.cos(pth), math.sin(pth)
        dx, dy = c * (ox - px) + s * (oy - py), -s * (ox - px) + c * (oy - py)
        x, y = x + math.cos(th) * dx - math.sin(th) * dy, y + math.sin(th) * dx + math.cos(th) * dy
        th = th + oth - pth
    prev = (ox, oy, oth)
    out.write(f"{t // 10**9}.{t % 10**9:09d} {x!r} {y!r} 0 0 0 {math.sin(th / 2)!r} {math.cos(th / 2)!r}\\n")
print("poses written")
print("dead reckoning done", file=sys.stderr)
'''


def declare(tmp_path: Path, monkeypatch: pytest.MonkeyPatch, script: str, **keys: object) -> None:
    """Write ``prog.py`` and a declaration ``ext`` running it (TOML keys overridable), and use it."""
    (tmp_path / "prog.py").write_text(script)
    table = {"command": ["{python}", "prog.py", "{out}/trajectory.tum"], "exports": ["odometry_csv"],
             "stdin": "{exports}/odometry.csv", "version_command": ["{python}", "--version"], **keys}
    def toml(v: object) -> str:
        return ("{" + ", ".join(f"{k} = {toml(x)}" for k, x in v.items()) + "}" if isinstance(v, dict)
                else json.dumps(v))

    lines = ["[pipelines.ext]"] + [f"{k} = {toml(v)}" for k, v in table.items()]
    (tmp_path / "ext.toml").write_text("\n".join(lines) + "\n")
    monkeypatch.setenv(DECLARATIONS_ENV, str(tmp_path / "ext.toml"))
    refresh()


@pytest.fixture
def rec(tmp_path: Path) -> Path:
    return write_tiny_recording(tmp_path / "tiny.mcap")


def test_external_program_scored_like_a_builtin(tmp_path: Path, rec: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A program dead-reckoning the exported odometry gives the odometry pipeline's metrics (to 1e-9), and the
    manifest, log and artifacts say what ran."""
    declare(tmp_path, monkeypatch, DEAD_RECKONING)
    ext = run_recording(rec, "ext", tmp_path / "ext")
    base = run_recording(rec, "odometry", tmp_path / "odometry")
    assert set(base.metrics) == set(ext.metrics)
    for name, value in base.metrics.items():
        assert ext.metrics[name] == pytest.approx(value, rel=1e-9, abs=1e-12), name
    origin = ext.manifest["pipeline_origin"]
    assert origin["distribution"] == "external" and origin["version"].startswith("Python 3.")
    assert origin["command"] == ["{python}", "prog.py", "{out}/trajectory.tum"]
    assert origin["executable"] == sys.executable and len(origin["executable_sha256"]) == 64
    assert list(origin["files_sha256"]) == ["prog.py"]
    assert ext.manifest["pipeline_run"]["runs"][0]["exit_status"] == 0
    log = (tmp_path / "ext" / "log.txt").read_text()
    assert "stdout (run 1 of 2): poses written" in log and "stderr (run 1 of 2): dead reckoning done" in log
    assert (tmp_path / "ext" / "program_stdout.txt").read_text() == "poses written\n"
    assert (tmp_path / "ext" / "trajectory.tum").is_file() and (tmp_path / "ext" / "run.rrd").is_file()
    assert get_pipeline("ext").blueprint() is not None and "ext" in pipeline_plugins()


@pytest.mark.parametrize(("script", "keys", "match"), [
    ("import sys; print('reading', file=sys.stderr); print('boom: bad header', file=sys.stderr); sys.exit(3)", {},
     r"external pipeline ext: python\S* exited with status 3: boom: bad header$"),
    ("print('nothing written')", {}, r"exited 0 but wrote no \{out\}/trajectory.tum: nothing on stderr"),
    ("import sys; open(sys.argv[1], 'w').write('1.0 0 0 0 0 0 0 1\\n2.0 oops\\n')", {},
     r"external pipeline ext: python\S*'s output trajectory.tum, line 2: expected 8 fields"),
    ("import time; time.sleep(30)", {"timeout_s": 0.5},
     r"ran past its wall-time limit of 0.5 s and was killed \(timeout_s in .*ext.toml\)"),
    ("x = bytearray(1 << 31)", {"memory_mib": 200},
     r"exited with status 1 \(memory limit 200 MiB: out of memory\?\): MemoryError"),
    ("", {"command": ["./no-such-program"]}, r"program ./no-such-program not found"),
])
def test_program_failures_are_one_line(tmp_path: Path, rec: Path, monkeypatch: pytest.MonkeyPatch, script: str,
                                       keys: dict[str, object], match: str) -> None:
    """A non-zero exit, no output, bad output, the wall-time and memory limits, a missing program: one line
    naming the program and its last stderr line; the run's manifest says failed."""
    declare(tmp_path, monkeypatch, script, **keys)
    with pytest.raises(ReplayError, match=match):
        run_recording(rec, "ext", tmp_path / "run")
    manifest = json.loads((tmp_path / "run" / "manifest.json").read_text())
    assert manifest["status"] == "failed" and "\n" not in manifest["error"]


@pytest.mark.parametrize(("toml", "match"), [
    ("[pipelines.ext]\nsummary = 'x'\n", r"ext.toml \[pipelines.ext\]: no command"),
    ("[pipelines.ext]\ncommand = 'x {outdir}'\n", r"command names placeholder \{outdir\}"),
    ("[pipelines.ext]\ncommand = 'x'\ncomand = 1\n", r"unknown keys comand"),
    ("[pipelines.ext]\ncommand = 'x'\nexports = ['lidar']\n", r"exports must be a list of odometry_tum"),
    ("[pipelines.ext]\ncommand = 'x'\nframe = 'map'\n", r"frame must be 'start'"),
    ("[pipelines.ext]\ncommand = 'x'\ntimeout_s = 0\n", r"timeout_s must be a number of seconds > 0"),
    ("[pipelines.odometry]\ncommand = 'x'\n", r"has the name of an installed pipeline"),
    ("[pipelines.ext\n", r"is not valid TOML"),
])
def test_bad_declarations_name_the_file(tmp_path: Path, monkeypatch: pytest.MonkeyPatch, toml: str,
                                        match: str) -> None:
    """A declaration that is wrong is a broken pipeline whose error names the file and the key; others work."""
    (tmp_path / "ext.toml").write_text(toml)
    monkeypatch.setenv(DECLARATIONS_ENV, str(tmp_path))  # a folder: every *.toml in it
    refresh()
    plugins = pipeline_plugins()
    broken = [p for p in plugins.values() if p.error is not None]
    assert len(broken) == 1 and "declared in" in broken[0].origin
    with pytest.raises(ReplayError, match=match):
        broken[0].load()
    assert get_pipeline("dslam").name == "dslam"


def test_frame_world_and_config(tmp_path: Path, rec: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """frame = "world" takes the poses as they are; config keys reach the program in {config}."""
    script = ('import json, sys; c = json.load(open(sys.argv[2]))\n'
              'open(sys.argv[1], "w").write("".join(f"{1 + k / 10:.9f} {c[\'x\'] + 0.1 * k} 0 0 0 0 0 1\\n" '
              'for k in range(100)))\n')
    declare(tmp_path, monkeypatch, script, command=["{python}", "prog.py", "{out}/trajectory.tum", "{config}"],
            frame="world", config={"x": 0.0})
    run = run_recording(rec, "ext", tmp_path / "run", config={"x": "5.0"})
    assert run.metrics["poses_scored"] == 100
    from slamreplay.replay.engine.trajectory import read_tum

    _, est = read_tum((tmp_path / "run" / "trajectory.tum").read_text())
    assert est[0, 0] == pytest.approx(5.0) and est[-1, 0] == pytest.approx(14.9)
    assert run.manifest["config"] == {"x": 5.0, "check_determinism": False, "min_coverage": 0.5}


def test_determinism_check(tmp_path: Path, rec: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """check_determinism runs the program twice: identical outputs say deterministic, noisy ones do not, with
    the largest position difference; the manifest records it."""
    declare(tmp_path, monkeypatch, DEAD_RECKONING)
    same = run_recording(rec, "ext", tmp_path / "same", config={"check_determinism": "true"})
    assert same.manifest["pipeline_run"]["determinism"] == {"checked": True, "deterministic": True,
                                                           "max_difference_m": 0.0}
    assert len(same.manifest["pipeline_run"]["runs"]) == 2
    noisy = DEAD_RECKONING.replace("x = y = th = 0.0", "import os\nx = y = th = 0.0").replace(
        "th = th + oth - pth", "th = th + oth - pth\n        x += int.from_bytes(os.urandom(2), 'big') * 1e-9")
    declare(tmp_path, monkeypatch, noisy)
    other = run_recording(rec, "ext", tmp_path / "noisy", config={"check_determinism": "true"})
    det = other.manifest["pipeline_run"]["determinism"]
    assert det["deterministic"] is False and 0 < det["max_difference_m"] < 100 * 65536e-9
    assert "NOT deterministic" in (tmp_path / "noisy" / "log.txt").read_text()


def test_determinism_checked_once_per_program(tmp_path: Path, rec: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Without asking: the first run of a program runs it twice and keeps the verdict; later runs of the same
    program (same hashes) run once and record the verdict as cached; an edited program is checked again; a
    program that is not deterministic is recorded so on every later run, which compare reads."""
    declare(tmp_path, monkeypatch, DEAD_RECKONING)
    first = run_recording(rec, "ext", tmp_path / "first")
    assert len(first.manifest["pipeline_run"]["runs"]) == 2
    assert first.manifest["pipeline_run"]["determinism"]["checked"] is True
    assert "the first run of this program" in (tmp_path / "first" / "log.txt").read_text()
    later = run_recording(rec, "ext", tmp_path / "later", seed=3)
    assert len(later.manifest["pipeline_run"]["runs"]) == 1
    assert later.manifest["pipeline_run"]["determinism"] == {"checked": "cached", "deterministic": True,
                                                            "max_difference_m": 0.0}
    forced = run_recording(rec, "ext", tmp_path / "forced", config={"check_determinism": "true"})
    assert len(forced.manifest["pipeline_run"]["runs"]) == 2
    noisy = DEAD_RECKONING.replace("x = y = th = 0.0", "import os\nx = y = th = 0.0").replace(
        "th = th + oth - pth", "th = th + oth - pth\n        x += int.from_bytes(os.urandom(2), 'big') * 1e-9")
    declare(tmp_path, monkeypatch, noisy)
    runs = [run_recording(rec, "ext", tmp_path / f"noisy{k}") for k in range(2)]
    assert [len(r.manifest["pipeline_run"]["runs"]) for r in runs] == [2, 1]
    assert [r.manifest["pipeline_run"]["determinism"]["deterministic"] for r in runs] == [False, False]


def test_views_summary_first(tmp_path: Path, rec: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The program's replay draws the estimate against the truth, the position error over time and the
    program's output in the log; its blueprint opens on the summary tab."""
    from slamreplay.algorithms.observe import Text
    from slamreplay.replay.engine.loop import replay
    from slamreplay.replay.engine.observer import MemoryObserver
    from slamreplay.replay.engine.pipeline import resolve_config
    from slamreplay.replay.engine.reader import RecordingReader

    declare(tmp_path, monkeypatch, DEAD_RECKONING)
    cls = get_pipeline("ext")
    observer = MemoryObserver()
    lines: list[str] = []
    stats = replay(RecordingReader(rec), cls, resolve_config(cls), observer, seed=0,
                   log=lambda text: (lines.append(text), observer.log("log", Text(text))))
    assert {"world/trajectory/estimate", "world/trajectory/truth", "metrics/robot_position_error_m",
            "world/robot", "world/robot_truth", "log"} <= observer.paths()
    assert "stderr (run 1 of 2): dead reckoning done" in lines  # the first run of a program checks determinism
    assert stats.trajectory is not None and len(stats.trajectory[0]) == 100
    run_recording(rec, "ext", tmp_path / "run")
    entities = rrd_entities(tmp_path / "run" / "run.rrd")
    tabs = blueprint_views(cls.blueprint(None))
    assert tabs[0][0] == "Summary" and any(view == "Log" for _, view, _ in tabs)
    for tab, view, patterns in tabs:  # every view of the layout shows something of the run
        shown = [p for p, e in entities.items() if any(matches(pat, p) for pat in patterns if not pat.startswith("-"))
                 and (e["static"] or e["last_step"] is not None) and e["columns"] - {"Transform3D:scale"}]
        assert shown, f"view {view!r} of tab {tab!r} shows nothing ({patterns})"


def test_a_program_s_landmark_map_is_scored(tmp_path: Path, rec: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """``landmarks = "{out}/landmarks.csv"``: the map is matched to the recording's true landmarks by id. The
    program writes the four true landmarks (world frame) each 0.3 m east and 0.4 m north of the truth, plus an
    id the truth lacks: RMSE 0.5 m, 5 mapped, 4 true, 1 false; it is drawn beside the truth. A map it does not
    write, or a malformed line, is one line naming the file."""
    marks = "id,x_m,y_m\n0,2.3,1.4\n1,3.3,-0.6\n2,5.3,2.4\n3,1.3,3.4\n99,0,0\n"
    (tmp_path / "prog.py").write_text(
        "import sys, pathlib\nout = pathlib.Path(sys.argv[1])\n"
        "rows = [l.split(',') for l in pathlib.Path(sys.argv[2]).read_text().splitlines()[1:]]\n"
        "out.joinpath('trajectory.tum').write_text(''.join(\n"
        "    f'{int(t) // 10**9}.{int(t) % 10**9:09d} {x} {y} 0 0 0 0 1\\n' for t, x, y, _ in rows))\n"
        f"if len(sys.argv) < 4: out.joinpath('landmarks.csv').write_text({marks!r})\n"
        "elif sys.argv[3] == 'bad': out.joinpath('landmarks.csv').write_text('0,1\\n')\n")
    table = ("[pipelines.{name}]\ncommand = ['{{python}}', 'prog.py', '{{out}}', '{{exports}}/odometry.csv'{extra}]\n"
             "exports = ['odometry_csv']\nframe = 'world'\nlandmarks = '{{out}}/landmarks.csv'\n")
    (tmp_path / "ext.toml").write_text(table.format(name="mapper", extra="") + table.format(name="nomap", extra=", 'x'")
                                       + table.format(name="badmap", extra=", 'bad'"))
    monkeypatch.setenv(DECLARATIONS_ENV, str(tmp_path / "ext.toml"))
    refresh()
    result = run_recording(rec, "mapper", tmp_path / "run")
    m = result.metrics
    assert m["landmark_rmse_m"] == pytest.approx(0.5, abs=1e-12)
    assert (m["landmarks_mapped"], m["landmarks_true"], m["false_landmarks"]) == (5, 4, 1)
    doc = json.loads((tmp_path / "run" / "metrics.json").read_text())["metrics"]
    assert doc["landmark_rmse_m"]["better"] == "lower" and "ape_rmse_m" in doc
    with pytest.raises(ReplayError, match=r"nomap: python[0-9.]* exited 0 but wrote no \{out\}/landmarks.csv"):
        run_recording(rec, "nomap", tmp_path / "run2")
    with pytest.raises(ReplayError, match=r"badmap: landmarks.csv, line 1: expected id,x_m,y_m"):
        run_recording(rec, "badmap", tmp_path / "run3")
