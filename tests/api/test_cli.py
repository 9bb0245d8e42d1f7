"""The CLI contract: exit codes, one-line errors without tracebacks, and the happy paths."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
from conftest import write_tiny_recording
from mcap.writer import Writer

from slamreplay.api.cli.command import main
from slamreplay.api.cli.hints import view_hint
from slamreplay.recorder import OdometryPose, Recorder, codec


def run_cli(args: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, str, str]:
    code = main(args)
    out, err = capsys.readouterr()
    return code, out, err


def assert_bad_input(code: int, err: str, pattern: str) -> None:
    """Exit 2, exactly one line on stderr matching pattern, no traceback."""
    assert code == 2, err
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("slamreplay: error: "), err
    assert "Traceback" not in err
    import re

    assert re.search(pattern, lines[0]), lines[0]


def no_success(run_dir: Path) -> None:
    """Nothing in the run directory looks like a success."""
    assert not (run_dir / "metrics.json").exists() and not (run_dir / "run.rrd").exists()
    if (run_dir / "manifest.json").exists():
        assert json.loads((run_dir / "manifest.json").read_text())["status"] == "failed"




@pytest.fixture
def rec(tmp_path: Path) -> Path:
    return write_tiny_recording(tmp_path / "tiny.mcap")


def test_run_success_and_diff_exit_codes(rec: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """run exits 0 and prints how to open the result; diff exits 0 on equal runs and 1 on a regression."""
    code, out, _ = run_cli(["run", str(rec), "--pipeline", "odometry", "--out", str(tmp_path / "a"), "-q"], capsys)
    assert code == 0
    code, out, _ = run_cli(["run", str(rec), "--pipeline", "odometry", "--out", str(tmp_path / "b")], capsys)
    assert code == 0 and "\n".join(view_hint(tmp_path / "b" / "run.rrd")) in out
    code, out, _ = run_cli(["diff", str(tmp_path / "a"), str(tmp_path / "b"), "--json"], capsys)
    assert code == 0 and json.loads(out)["rrd_equal"] is True
    worse = write_tiny_recording(tmp_path / "worse.mcap", drift=0.2)
    run_cli(["run", str(worse), "--pipeline", "odometry", "--out", str(tmp_path / "c"), "-q"], capsys)
    code, out, _ = run_cli(["diff", str(tmp_path / "a"), str(tmp_path / "c"), "--rrd", str(tmp_path / "ab.rrd")],
                           capsys)
    assert code == 1 and "WORSE" in out and (tmp_path / "ab.rrd").exists()
    code, _, _ = run_cli(["diff", str(tmp_path / "a"), str(tmp_path / "c"), "--tolerance", "*=10000%"], capsys)
    assert code == 0
    code, _, err = run_cli(["diff", str(tmp_path / "a"), str(tmp_path / "nope")], capsys)
    assert_bad_input(code, err, "does not exist")


def test_run_error_paths(rec: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Every bad input of `run`: exit 2, one line, nothing that looks like success."""
    def run(file: Path, out: str, *extra: str) -> tuple[int, str]:
        code, _, err = run_cli(["run", str(file), "--pipeline", "odometry", "--out", str(tmp_path / out), "-q",
                                *extra], capsys)
        return code, err

    junk = tmp_path / "junk.mcap"
    junk.write_text("not an mcap at all")
    assert_bad_input(*run(junk, "r1"), "not an MCAP file")
    no_success(tmp_path / "r1")
    empty = tmp_path / "empty.mcap"
    empty.touch()
    assert_bad_input(*run(empty, "r2"), "is empty")
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(rec.read_bytes()[:3000])
    assert_bad_input(*run(cut, "r3"), r"truncated.*slamreplay recover")
    no_success(tmp_path / "r3")
    big = tmp_path / "big.mcap"
    with Recorder(big, source={}) as r:
        for k in range(3000):
            r.write("/odom", OdometryPose(k + 1, k, 0, 0))
    data = bytearray(big.read_bytes())
    data[len(data) // 3] ^= 0x5A
    crc = tmp_path / "crc.mcap"
    crc.write_bytes(bytes(data))
    assert_bad_input(*run(crc, "r4"), r"(corrupt|damaged)")
    no_success(tmp_path / "r4")
    assert_bad_input(*run(rec, "r5", "--topic-map", "/landmarks/range_bearing=/odom"),
                     r"topic /odom has schema slamreplay.RangeBearingScan.*OdometryPose is read from")
    no_success(tmp_path / "r5")
    gt_only = tmp_path / "gt.mcap"
    with Recorder(gt_only, source={}) as r:
        from slamreplay.recorder import GroundTruthPose

        r.write("/ground_truth/pose", GroundTruthPose(1, 0, 0, 0))
    assert_bad_input(*run(gt_only, "r6"), "has no /odom topic")
    no_success(tmp_path / "r6")
    code, _, err = run_cli(["run", str(rec), "--pipeline", "nope", "--out", str(tmp_path / "r7")], capsys)
    assert_bad_input(code, err, "unknown pipeline 'nope'")
    assert not (tmp_path / "r7").exists()
    assert_bad_input(*run(rec, "r8", "--set", "bogus=1"), "unknown config key 'bogus'")
    assert_bad_input(*run(rec, "r9", "--set", "novalue"), "key=value")
    run(rec, "ok")
    assert_bad_input(*run(rec, "ok"), "already exists")
    assert_bad_input(*run(rec, "r10", "--config", str(tmp_path / "none.json")), "no such file")


def test_nan_in_message(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A NaN in a needed message stops the run with its topic and log time."""
    path = tmp_path / "nan.mcap"
    with open(path, "wb") as f:
        w = Writer(f)
        w.start()
        odom = OdometryPose(1, 0, 0, 0)
        cid = w.register_channel("/odom", "protobuf",
                                 w.register_schema(codec.schema_name(odom), "protobuf", codec.schema_data(odom)))
        from foxglove_schemas_protobuf.PoseInFrame_pb2 import PoseInFrame

        bad = PoseInFrame(frame_id="odom")
        bad.pose.position.x = float("nan")
        bad.pose.orientation.w = 1.0
        w.add_message(cid, 1, codec.encode(odom), 1)
        w.add_message(cid, 2, bad.SerializeToString(), 2)
        w.finish()
    code, _, err = run_cli(["run", str(path), "--pipeline", "odometry", "--out", str(tmp_path / "r"), "-q"], capsys)
    assert_bad_input(code, err, r"/odom message at log_time 2 ns is invalid.*nan")
    no_success(tmp_path / "r")


def test_inspect_recover_pipelines(rec: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """inspect reports health (exit 1 when damaged), recover salvages, pipelines lists keys."""
    code, out, _ = run_cli(["inspect", str(rec), "--json"], capsys)
    report = json.loads(out)
    assert code == 0 and report["health"] == "ok" and report["message_count"] == 221
    code, out, _ = run_cli(["inspect", str(rec)], capsys)
    assert code == 0 and "foxglove.PoseInFrame" in out
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(rec.read_bytes()[:-100])
    code, out, _ = run_cli(["inspect", str(cut), "--json"], capsys)
    assert code == 1 and json.loads(out)["health"] == "truncated"
    code, out, _ = run_cli(["recover", str(cut), "--out", str(tmp_path / "fixed.mcap")], capsys)
    assert code == 0 and "recovered 221 messages" in out
    code, _, err = run_cli(["recover", str(cut), "--out", str(tmp_path / "fixed.mcap")], capsys)
    assert_bad_input(code, err, "already exists")
    code, out, _ = run_cli(["pipelines", "--json"], capsys)
    rows = {r["name"]: r for r in json.loads(out)}
    assert rows["odometry"]["required_topics"] == ["/odom"]
    code, _, err = run_cli(["inspect", str(tmp_path / "nothing.mcap")], capsys)
    assert_bad_input(code, err, "no such file")


def test_console_script_help_and_errors(tmp_path: Path) -> None:
    """The installed entry point: --help works; a bad file gives one line and exit 2 in a real process."""
    exe = Path(sys.executable).parent / "slamreplay"
    cmd = [str(exe)] if exe.exists() else [sys.executable, "-m", "slamreplay.api.cli"]
    help_ = subprocess.run([*cmd, "run", "--help"], capture_output=True, text=True)
    assert help_.returncode == 0 and "--pipeline" in help_.stdout
    junk = tmp_path / "x.mcap"
    junk.write_text("nope")
    proc = subprocess.run([*cmd, "run", str(junk), "--pipeline", "odometry", "--out", str(tmp_path / "r")],
                          capture_output=True, text=True)
    assert proc.returncode == 2 and proc.stderr.count("\n") == 1 and "Traceback" not in proc.stderr


def test_record_sim_and_run_with_timings(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """record sim-landmarks writes a recording whose odometry run succeeds; --log-timings adds timings/step_ms."""
    out = tmp_path / "sim.mcap"
    code, _, err = run_cli(["record", "sim-landmarks", "--out", str(out), "--seed", "4", "--duration-s", "30",
                            "--landmarks", "400"], capsys)
    assert code == 0 and "/400 landmarks seen" in err and out.exists()
    code, _, err = run_cli(["record", "sim-landmarks", "--out", str(out)], capsys)
    assert_bad_input(code, err, "already exists")
    code, _, err = run_cli(["record", "sim-landmarks", "--out", str(tmp_path / "x.mcap"), "--speed-mps", "-1"],
                           capsys)
    assert_bad_input(code, err, "speed_mps must be > 0")
    code, _, _ = run_cli(["run", str(out), "--pipeline", "odometry", "--out", str(tmp_path / "r"), "-q",
                          "--log-timings"], capsys)
    assert code == 0
    from rerun.chunk import RrdReader

    paths = {c.entity_path for c in RrdReader(tmp_path / "r" / "run.rrd").stream().to_chunks()}
    assert "/timings/step_ms" in paths
    code, _, _ = run_cli(["run", str(out), "--pipeline", "odometry", "--out", str(tmp_path / "r2"), "-q"], capsys)
    paths = {c.entity_path for c in RrdReader(tmp_path / "r2" / "run.rrd").stream().to_chunks()}
    assert "/timings/step_ms" not in paths  # no wall-clock value unless asked for


def test_record_mrclam_errors(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A missing dataset folder is a one-line error."""
    code, _, err = run_cli(["record", "mrclam", str(tmp_path / "nope"), "--robot", "1", "--out",
                            str(tmp_path / "m.mcap")], capsys)
    assert_bad_input(code, err, "nope")


def test_graph_optimize(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """graph optimize: a consistent square loop reaches chi2 0; a malformed line is a one-line error naming it."""
    g = tmp_path / "square.g2o"
    lines = [f"VERTEX_SE2 {k} {0.1 * k} {0.05 * k} 0.0" for k in range(4)]
    info = "100 0 0 100 0 1000"
    lines += [f"EDGE_SE2 {k} {k + 1} 1.0 0.0 1.5707963267948966 {info}" for k in range(3)]
    lines += [f"EDGE_SE2 3 0 1.0 0.0 1.5707963267948966 {info}"]
    g.write_text("\n".join(lines) + "\n")
    code, out, _ = run_cli(["graph", "optimize", str(g), "--out", str(tmp_path / "o.g2o"), "--json"], capsys)
    summary = json.loads(out)
    assert code == 0 and summary["chi2_final"] < 1e-12 and summary["status"] == "converged"
    bad = tmp_path / "bad.g2o"
    bad.write_text("VERTEX_SE2 0 0 0 0\nEDGE_SE2 0 1 oops\n")
    code, _, err = run_cli(["graph", "optimize", str(bad), "--out", str(tmp_path / "b.g2o")], capsys)
    assert_bad_input(code, err, r"bad.g2o:2")


def test_failed_run_retry_and_nested_out(rec: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """The README's story: a run fails (missing topic), the retry into the same --out works; --out a/b/c is created."""
    from slamreplay.recorder import GroundTruthPose

    gt_only = tmp_path / "gt.mcap"
    with Recorder(gt_only, source={}) as r:
        r.write("/ground_truth/pose", GroundTruthPose(1, 0, 0, 0))
    out = str(tmp_path / "runs" / "nested" / "odo")
    code, _, err = run_cli(["run", str(gt_only), "--pipeline", "odometry", "--out", out, "-q"], capsys)
    assert_bad_input(code, err, "has no /odom topic")
    code, _, err = run_cli(["run", str(rec), "--pipeline", "odometry", "--out", out, "-q"], capsys)
    assert code == 0, err
    code, _, err = run_cli(["run", str(rec), "--pipeline", "odometry", "--out", out, "-q"], capsys)
    assert_bad_input(code, err, "already exists and holds a run with status 'succeeded'.*choose a new --out")
