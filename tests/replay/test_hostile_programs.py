"""A campaign of hostile external programs: whatever the program does, its run returns within its time limit
plus 10 s, no process of it is left behind, its output is capped, and a failed run looks failed."""

from __future__ import annotations

import json
import os
import re
import signal
import threading
import time
from pathlib import Path

import pytest
from conftest import write_tiny_recording
from patience import deadline as give_up_at

from slamreplay.recorder.plugins import refresh
from slamreplay.replay.engine.declared import DECLARATIONS_ENV
from slamreplay.replay.errors import ReplayError
from slamreplay.replay.runs.run import run_recording
from slamreplay.replay.tools.containment import MEMORY_ENV, OUTPUT_CAP_BYTES, memory_limit_mib

pytestmark = pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="containment is checked through /proc")

# every program gets HOSTILE_MARK in its environment and puts it in its sleepers' command lines (sleep 3601.<n>)
PRELUDE = '''
import os, signal, subprocess, sys, time
MARK = os.environ["HOSTILE_MARK"]

def trajectory(path=None):
    with open(path or sys.argv[1], "w") as out:
        for line in sys.stdin.read().splitlines()[1:]:
            t, x, y, _ = line.split(",")
            out.write(f"{int(t) // 10**9}.{int(t) % 10**9:09d} {x} {y} 0 0 0 0 1\\n")

def daemon():
    """A double-forked sleeper in a session of its own, holding our stdout and stderr."""
    if os.fork() == 0:
        os.setsid()
        if os.fork() == 0:
            os.execvp("sleep", ["sleep", MARK])
        os._exit(0)
    os.wait()
'''

CASES = {
    # (a) ignores SIGTERM and starts `setsid sleep` inheriting stdout, then hangs
    "sigterm-ignored-setsid": ('signal.signal(signal.SIGTERM, signal.SIG_IGN)\n'
                               'subprocess.Popen(["setsid", "sleep", MARK])\nprint("started", flush=True)\n'
                               'time.sleep(3600)\n', 2, r"ran past its wall-time limit of 2 s and was killed"),
    # (b) double-forks a daemon, then fails
    "double-fork-then-fail": ('daemon()\nprint("daemon started; giving up", file=sys.stderr)\nsys.exit(2)\n', 3,
                              r"exited with status 2: daemon started; giving up$"),
    # (c) a process group of 200 sleepers, then hangs
    "200-sleepers": ('for _ in range(200):\n    subprocess.Popen(["sleep", MARK])\ntime.sleep(3600)\n', 3,
                     r"ran past its wall-time limit of 3 s"),
    # (e) closes stdout and stderr, then hangs
    "closed-stdout-hangs": ('os.close(1)\nos.close(2)\ntime.sleep(3600)\n', 2, r"ran past its wall-time limit of 2 s"),
    # (f) invalid UTF-8 and terminal escape sequences in its output, and in the error's last line
    "bad-bytes-and-escapes": ('for f in (sys.stdout.buffer, sys.stderr.buffer):\n'
                              '    f.write(b"\\xff\\xfe not utf-8 \\x1b[2J\\x1b]0;pwned\\x07 \\x1b[31mred\\r\\n")\n'
                              '    f.flush()\nsys.exit(1)\n', 3,
                              r"exited with status 1: \ufffd\ufffd not utf-8 \\x1b\[2J\\x1b\]0;pwned\\x07"),
    # (g) the trajectory is a symbolic link to a valid TUM file outside its output folder: refused
    "trajectory-symlink-out": ('outside = os.path.dirname(os.environ["SLAMREPLAY_OUT"]) + "/elsewhere.tum"\n'
                               'trajectory(outside)\nos.symlink(outside, sys.argv[1])\n', 3,
                               r"its output \{out\}/trajectory.tum is a symbolic link \(to .*elsewhere.tum\)"),
    "trajectory-symlink-dev-zero": ('os.symlink("/dev/zero", sys.argv[1])\n', 3,
                                    r"is a symbolic link \(to /dev/zero\)"),
    # (h) fills its output folder: a 1 GiB trajectory (sparse: no disk is used) is not read
    "huge-trajectory": ('with open(sys.argv[1], "wb") as f:\n    f.truncate(1 << 30)\n', 3,
                        r"is 1,073,741,824 bytes, more than the 256 MiB slamreplay reads"),
    # its supervisor stopped (SIGSTOP) or killed by the program: slamreplay kills whatever has its run's token
    "freezes-its-supervisor": ('subprocess.Popen(["setsid", "sleep", MARK])\nos.kill(os.getppid(), signal.SIGSTOP)\n'
                               'time.sleep(3600)\n', 2, r"ran past its wall-time limit of 2 s"),
    "kills-its-supervisor": ('subprocess.Popen(["setsid", "sleep", MARK])\nos.kill(os.getppid(), signal.SIGKILL)\n'
                             'time.sleep(3600)\n', 2, r"cannot run .*python.*: its supervisor ended with status -9"),
    # (i) exits 0 with a valid trajectory after 1 s, leaving a detached helper (as `ros2 daemon` does): success
    "leaves-a-helper": ('trajectory()\ndaemon()\ntime.sleep(1)\nprint("done")\n', 15, None),
}


def declare(tmp_path: Path, monkeypatch: pytest.MonkeyPatch, script: str, mark: str, **keys: object) -> None:
    """A declaration ``hostile`` running ``script`` (after PRELUDE) on the exported odometry, with HOSTILE_MARK."""
    (tmp_path / "prog.py").write_text(PRELUDE + script)
    table = {"command": ["{python}", "prog.py", "{out}/trajectory.tum"], "exports": ["odometry_csv"],
             "stdin": "{exports}/odometry.csv", "env": {"HOSTILE_MARK": mark}, **keys}
    lines = ["[pipelines.hostile]"] + [
        f"{k} = " + ("{" + ", ".join(f"{n} = {json.dumps(x)}" for n, x in v.items()) + "}" if isinstance(v, dict)
                     else json.dumps(v)) for k, v in table.items()]
    (tmp_path / "hostile.toml").write_text("\n".join(lines) + "\n")
    monkeypatch.setenv(DECLARATIONS_ENV, str(tmp_path / "hostile.toml"))
    refresh()


def left_behind(mark: str) -> list[str]:
    """Processes with ``mark`` in their command line or environment (a program's, by its HOSTILE_MARK)."""
    found = []
    for entry in os.listdir("/proc"):
        if not entry.isdigit() or int(entry) == os.getpid():
            continue
        try:
            cmdline = Path(f"/proc/{entry}/cmdline").read_bytes()
            environ = Path(f"/proc/{entry}/environ").read_bytes()
        except OSError:
            continue
        if mark.encode() in cmdline or f"HOSTILE_MARK={mark}".encode() in environ:
            found.append(f"{entry}: {cmdline.replace(bytes(1), b' ').decode(errors='replace')}")
    return found


def unique_mark() -> str:
    return f"3601.{os.getpid()}{time.monotonic_ns() % 10**6:06d}"


@pytest.fixture
def rec(tmp_path: Path) -> Path:
    return write_tiny_recording(tmp_path / "tiny.mcap", n=30)


@pytest.mark.parametrize("case", list(CASES))
def test_hostile_program_is_contained(tmp_path: Path, rec: Path, monkeypatch: pytest.MonkeyPatch, case: str) -> None:
    """Each hostile program: the run returns within timeout_s + 10 s, no process of it is left, a failed run has a
    failed manifest and no metrics.json, and the log and the error show its bytes only as printable text."""
    script, timeout_s, error = CASES[case]
    mark = unique_mark()
    declare(tmp_path, monkeypatch, script, mark, timeout_s=timeout_s)
    run = tmp_path / "run"
    tic = time.monotonic()
    try:
        run_recording(rec, "hostile", run)
        failure = None
    except ReplayError as err:
        failure = str(err)
    elapsed = time.monotonic() - tic
    print(f"{case}: returned in {elapsed:.2f} s")  # the campaign's measure, shown with -s
    assert elapsed < timeout_s + 10, f"{case} took {elapsed:.1f} s"
    assert left_behind(mark) == []
    manifest = json.loads((run / "manifest.json").read_text())
    log = (run / "log.txt").read_text()
    assert "\x1b" not in log and "\x07" not in log
    if error is None:
        assert failure is None and manifest["status"] == "succeeded" and (run / "metrics.json").is_file()
        assert elapsed < 10, "a program that exited must not wait for its leftovers"
        return
    assert failure is not None and re.search(error, failure), failure
    assert "\n" not in failure and "\x1b" not in failure
    assert manifest["status"] == "failed" and not (run / "metrics.json").exists() and not (run / "run.rrd").exists()


def test_a_helper_left_running_is_killed_and_named(tmp_path: Path, rec: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A program that exits 0 after 1 s with a valid trajectory and a detached helper holding its stdout succeeds
    in about 1 s; the log names the helper, killed; its output is kept whole."""
    mark = unique_mark()
    declare(tmp_path, monkeypatch, CASES["leaves-a-helper"][0], mark, timeout_s=15)
    tic = time.monotonic()
    result = run_recording(rec, "hostile", tmp_path / "run")
    assert time.monotonic() - tic < 8 and result.metrics["poses_scored"] > 0
    log = (tmp_path / "run" / "log.txt").read_text()
    assert re.search(r"left `sleep` \(pid \d+\) running \(run 1 of 2\): killed", log), log
    assert (tmp_path / "run" / "program_stdout.txt").read_bytes() == b"done\n"
    assert result.manifest["pipeline_run"]["runs"][0]["killed"] == ["sleep"]
    assert left_behind(mark) == []


def test_escapes_are_shown_as_text_and_kept_as_bytes(tmp_path: Path, rec: Path,
                                                     monkeypatch: pytest.MonkeyPatch) -> None:
    """Invalid UTF-8 and terminal escapes: the log writes them as text (\\x1b), the artifact keeps the bytes."""
    script = ('sys.stdout.buffer.write(b"\\xff\\xfe \\x1b[2J\\x1b]0;pwned\\x07 ok\\n")\ntrajectory()\n')
    declare(tmp_path, monkeypatch, script, unique_mark())
    run_recording(rec, "hostile", tmp_path / "run")
    log = (tmp_path / "run" / "log.txt").read_text()
    assert "stdout (run 1 of 2): \ufffd\ufffd \\x1b[2J\\x1b]0;pwned\\x07 ok" in log
    assert (tmp_path / "run" / "program_stdout.txt").read_bytes() == b"\xff\xfe \x1b[2J\x1b]0;pwned\x07 ok\n"


def _rss_kib(field: str) -> int:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(field + ":"):
            return int(line.split()[1])
    raise AssertionError(f"no {field} in /proc/self/status")


def test_a_flood_on_stderr_is_capped(tmp_path: Path, rec: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """500 MB on stderr: slamreplay's memory grows by less than 50 MB, the file keeps the first 10 MiB and says
    how much was dropped, the log says so too, and the last line past the cap still names the error."""
    script = ('block = b"x" * (1 << 20)\nfor _ in range(500):\n    sys.stderr.buffer.write(block)\n'
              'sys.stderr.buffer.write(b"\\nfatal: the very last line\\n")\nsys.exit(4)\n')
    declare(tmp_path, monkeypatch, script, unique_mark(), timeout_s=30)
    peak = Path("/proc/self/clear_refs")
    try:
        peak.write_text("5")  # resets VmHWM: the peak below is this run's
        before = _rss_kib("VmRSS")
    except OSError:
        pytest.skip("cannot reset the peak RSS (/proc/self/clear_refs)")
    sampled = [0]
    done = threading.Event()

    def watch() -> None:  # also sampled, in case VmHWM was not reset
        while not done.wait(0.05):
            sampled[0] = max(sampled[0], _rss_kib("VmRSS"))

    watcher = threading.Thread(target=watch)
    watcher.start()
    tic = time.monotonic()
    try:
        with pytest.raises(ReplayError, match=r"exited with status 4: fatal: the very last line$"):
            run_recording(rec, "hostile", tmp_path / "run")
    finally:
        done.set()
        watcher.join()
    elapsed = time.monotonic() - tic
    growth_mib = (max(_rss_kib("VmHWM"), sampled[0]) - before) / 1024
    print(f"500 MB on stderr: returned in {elapsed:.2f} s, RSS +{growth_mib:.1f} MiB")
    assert growth_mib < 50
    log = (tmp_path / "run" / "log.txt").read_text()
    assert "stderr (run 1 of 2): 513,802,267 bytes past the first 10 MiB were not kept" in log


def test_the_default_memory_limit(tmp_path: Path, rec: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Without memory_mib, a program runs under 4096 MiB of address space (numpy imports fine, 8 GiB does not);
    $SLAMREPLAY_EXTERNAL_MEMORY_MIB changes the default, a declaration's memory_mib wins over it."""
    assert memory_limit_mib(None) == 4096 and memory_limit_mib(64) == 64
    monkeypatch.setenv(MEMORY_ENV, "512")
    assert memory_limit_mib(None) == 512 and memory_limit_mib(64) == 64
    monkeypatch.setenv(MEMORY_ENV, "lots")
    with pytest.raises(ReplayError, match=r"SLAMREPLAY_EXTERNAL_MEMORY_MIB must be a whole number of MiB >= 16"):
        memory_limit_mib(None)
    monkeypatch.delenv(MEMORY_ENV)
    declare(tmp_path, monkeypatch, "import numpy, scipy.linalg\ntrajectory()\nx = bytearray(8 << 30)\n", unique_mark())
    with pytest.raises(ReplayError, match=r"exited with status 1 \(memory limit 4096 MiB: out of memory\?\): "
                                          r"MemoryError"):
        run_recording(rec, "hostile", tmp_path / "run")
    assert OUTPUT_CAP_BYTES == 10 * 1024 * 1024


@pytest.mark.parametrize(("script", "keys", "error"), [
    ('print("mapping"); print("bad input", file=sys.stderr)\nopen(os.environ["SLAMREPLAY_OUT"] + "/landmarks.csv", '
     '"w").write("id,x_m,y_m\\n0,1,2\\n")\nsys.exit(3)\n', {}, r"exited with status 3: bad input$"),
    ('print("mapping", flush=True); print("bad input", file=sys.stderr, flush=True)\n'
     'open(os.environ["SLAMREPLAY_OUT"] + "/landmarks.csv", "w").write("id,x_m,y_m\\n0,1,2\\n")\ntime.sleep(60)\n',
     {"timeout_s": 2}, r"ran past its wall-time limit of 2 s and was killed .*: bad input$"),
])
def test_a_failed_run_keeps_what_the_program_wrote(tmp_path: Path, rec: Path, monkeypatch: pytest.MonkeyPatch,
                                                   script: str, keys: dict[str, object], error: str) -> None:
    """A program that fails, or is killed at its limit: its stdout, stderr and landmark map stay in the failed run
    directory (listed in its manifest), nothing there looks finished, and a retry into it is not refused."""
    declare(tmp_path, monkeypatch, script, unique_mark(), landmarks="{out}/landmarks.csv", **keys)
    run = tmp_path / "run"
    for _ in range(2):  # the second time: the retry of a failed run into its directory
        with pytest.raises(ReplayError, match=error):
            run_recording(rec, "hostile", run)
        manifest = json.loads((run / "manifest.json").read_text())
        assert manifest["status"] == "failed" and not (run / "metrics.json").exists()
        assert (run / "program_stdout.txt").read_text() == "mapping\n"
        assert (run / "program_stderr.txt").read_text() == "bad input\n"
        assert (run / "program_landmarks.csv").read_text() == "id,x_m,y_m\n0,1,2\n"
        assert set(manifest["artifacts"]) == {"program_stdout.txt", "program_stderr.txt", "program_landmarks.csv"}


def test_a_cancelled_job_leaves_nothing(tmp_path: Path, rec: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Through the service's executor: a job running a program that ignores SIGTERM and started a setsid sleeper
    is cancelled; its worker is killed, and the program, the sleeper and the run's temporary folder are gone
    within a few seconds."""
    from slamreplay.api.service.executor import LocalExecutor, Outcome
    from tests.api.service_helpers import claimed, make_store

    mark = unique_mark()
    declare(tmp_path, monkeypatch, CASES["sigterm-ignored-setsid"][0], mark, timeout_s=120)
    scratch = tmp_path / "worker-tmp"
    scratch.mkdir()
    monkeypatch.setenv("TMPDIR", str(scratch))  # where the worker's runs put their exports and the program's output
    executor = LocalExecutor(1)  # spawned after declare(): its worker sees the declaration
    executor.start()
    try:
        task = claimed(make_store(tmp_path / "jobs.sqlite"), rec, "c" * 32, "hostile", tmp_path)
        out: list[Outcome] = []
        thread = threading.Thread(target=lambda: out.append(executor.run(task)))
        thread.start()
        deadline = give_up_at(60)
        while not any("sleep " + mark in p for p in left_behind(mark)):
            assert time.monotonic() < deadline, "the program never started its sleeper"
            time.sleep(0.05)
        tic = time.monotonic()
        executor.cancel(task.job_id)
        thread.join(30)
        assert out == [Outcome("cancelled", "cancelled by request")]
        while (left_behind(mark) or list(scratch.glob("slamreplay-external-*"))) and time.monotonic() - tic < 10:
            time.sleep(0.05)
        print(f"cancel: nothing left after {time.monotonic() - tic:.2f} s")
        assert left_behind(mark) == []
        assert list(scratch.glob("slamreplay-external-*")) == []  # removed by the program's supervisor
    finally:
        executor.close()


def test_an_interrupted_run_leaves_nothing(tmp_path: Path, rec: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Ctrl-C while the program runs (SIGINT to slamreplay's process): the program and its setsid sleeper are
    killed before the KeyboardInterrupt leaves run_recording."""
    mark = unique_mark()
    # the interrupt comes long before the program's own limit, however loaded the machine (once, at a load that
    # stretched the wait below to 120 s, the limit of 120 s came first)
    declare(tmp_path, monkeypatch, CASES["sigterm-ignored-setsid"][0], mark, timeout_s=900)
    signal.signal(signal.SIGINT, signal.default_int_handler)  # Ctrl-C as a terminal gives it, whatever ran before

    def interrupt() -> None:
        deadline = min(give_up_at(60), time.monotonic() + 300)
        while not any("sleep " + mark in p for p in left_behind(mark)) and time.monotonic() < deadline:
            time.sleep(0.05)
        os.kill(os.getpid(), signal.SIGINT)

    threading.Thread(target=interrupt, daemon=True).start()
    with pytest.raises(KeyboardInterrupt):
        run_recording(rec, "hostile", tmp_path / "run")
    assert left_behind(mark) == []
    assert json.loads((tmp_path / "run" / "manifest.json").read_text())["status"] != "succeeded"
    assert not (tmp_path / "run" / "metrics.json").exists()
