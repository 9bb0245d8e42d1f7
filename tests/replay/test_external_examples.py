"""The external-pipeline examples: the Python program reading the MCAP, the C program built by Debian's cc,
the suite with both beside dslam, and compare telling a biased build of the C program from the original."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import pytest
from conftest import write_tiny_recording

from slamreplay.recorder.plugins import refresh
from slamreplay.replay.engine.declared import DECLARATIONS_ENV
from slamreplay.replay.evaluation.evaluate import TRAJECTORY_METRICS
from slamreplay.replay.runs.run import run_recording
from slamreplay.replay.runs.suite import load_suite

EXAMPLES = Path(__file__).resolve().parents[2] / "examples"
CC = shutil.which("cc")
needs_cc = pytest.mark.skipif(CC is None, reason="no C compiler (cc): `make test-examples` installs gcc with apt-get")


def build(out: Path, bias: float = 0.0) -> Path:
    """deadreckon.c built into ``out`` with -DSCALE_BIAS=bias, and a declaration of deadreckon-c running it."""
    out.mkdir(parents=True)
    subprocess.run([str(CC), "-O2", "-std=c99", f"-DSCALE_BIAS={bias}", "-o", str(out / "deadreckon"),
                    str(EXAMPLES / "external_c" / "deadreckon.c"), "-lm"], check=True)
    text = (EXAMPLES / "external_c" / "pipeline.toml").read_text().replace("build/deadreckon", str(out / "deadreckon"))
    text = "\n".join(line for line in text.splitlines() if not line.startswith("build ="))  # built above instead
    (out / "pipeline.toml").write_text(text)
    return out / "pipeline.toml"


def test_python_example_reads_the_mcap(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """mcap_odometry.py (mcap + protobuf, no slamreplay) is dead reckoning: the odometry pipeline's metrics;
    scale=1.05 makes it worse."""
    monkeypatch.setenv(DECLARATIONS_ENV, str(EXAMPLES / "external_python" / "pipeline.toml"))
    refresh()
    write_tiny_recording(tmp_path / "tiny.mcap")
    monkeypatch.chdir(tmp_path)  # a relative recording path: the program runs in its own folder
    rec = Path("tiny.mcap")
    py = run_recording(rec, "mcap-odometry-py", tmp_path / "py")
    base = run_recording(rec, "odometry", tmp_path / "odometry")
    for name in TRAJECTORY_METRICS:
        assert py.metrics[name] == pytest.approx(base.metrics[name], rel=1e-9), name
    assert py.manifest["pipeline_origin"]["version"] == "mcap_odometry 1.0"
    assert "mcap_odometry.py" in py.manifest["pipeline_origin"]["files_sha256"]
    scaled = run_recording(rec, "mcap-odometry-py", tmp_path / "scaled", config={"scale": "1.05"})
    assert scaled.metrics["path_length_m"] == pytest.approx(1.05 * base.metrics["path_length_m"], rel=1e-9)


def test_example_suite_file_is_valid(monkeypatch: pytest.MonkeyPatch) -> None:
    """examples/suites/external.toml names both examples (through its declarations) and dslam, seeds 1-3."""
    monkeypatch.delenv(DECLARATIONS_ENV, raising=False)
    refresh()
    suite = load_suite(EXAMPLES / "suites" / "external.toml")
    assert set(suite.pipelines) == {"deadreckon-c", "mcap-odometry-py", "dslam"}
    assert list(suite.recordings["landmarks"].seeds) == [1, 2, 3]


@needs_cc
def test_c_example_and_a_biased_build_compare(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                              capsys: pytest.CaptureFixture[str]) -> None:
    """The C example equals the odometry pipeline; a build with a 5 % scale bias, run as the same pipeline in a
    second results directory, makes `compare` exit 1 naming the trajectory metrics."""
    from slamreplay.api.cli.command import main

    monkeypatch.delenv(DECLARATIONS_ENV, raising=False)
    rec = write_tiny_recording(tmp_path / "tiny.mcap")
    good, biased = build(tmp_path / "good"), build(tmp_path / "biased", 0.05)
    monkeypatch.setenv(DECLARATIONS_ENV, str(good))
    refresh()
    c = run_recording(rec, "deadreckon-c", tmp_path / "c")
    base = run_recording(rec, "odometry", tmp_path / "odometry")
    for name in TRAJECTORY_METRICS:
        assert c.metrics[name] == pytest.approx(base.metrics[name], rel=1e-9), name
    assert c.manifest["pipeline_origin"]["version"] == "deadreckon 1.0 (scale bias 0)"
    monkeypatch.delenv(DECLARATIONS_ENV)
    for name, decl in (("a", good), ("b", biased)):
        monkeypatch.delenv(DECLARATIONS_ENV, raising=False)  # a suite's declarations stay for the process
        (tmp_path / f"{name}.toml").write_text(
            f'declarations = ["{decl}"]\n[recordings.landmarks]\nsim = "sim-landmarks"\n'
            f'args = {{ duration-s = 15 }}\nseeds = [1, 2, 3]\n[pipelines.deadreckon-c]\n')
        assert main(["suite", "run", str(tmp_path / f"{name}.toml"), "--out", str(tmp_path / f"results-{name}"),
                     "-q"]) == 0
    capsys.readouterr()
    assert main(["compare", str(tmp_path / "results-a"), str(tmp_path / "results-b")]) == 1
    out = capsys.readouterr().out
    regressions = out.rsplit("Result:", 1)[1]
    assert "deadreckon-c/default ape_rmse_m" in regressions and "ape_se2_rmse_m" in regressions
