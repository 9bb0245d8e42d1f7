"""examples/my_pipeline, pip-installed as a user would: found through its entry point, run, diffed against odometry."""

from __future__ import annotations

import json
import math
import os
import shutil
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from slamreplay.api.cli.command import main
from slamreplay.recorder.plugins import refresh

REPO = Path(__file__).resolve().parents[2]
EXAMPLE = REPO / "examples" / "my_pipeline"


@pytest.fixture(scope="module")
def site(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The example built and installed by pip into a folder of its own (a copy: the build leaves files behind)."""
    tmp = tmp_path_factory.mktemp("my_pipeline")
    shutil.copytree(EXAMPLE, tmp / "src", ignore=shutil.ignore_patterns("build", "*.egg-info", "__pycache__"))
    subprocess.run([sys.executable, "-m", "pip", "install", "--quiet", "--no-deps", "--no-build-isolation",
                    "--no-index", "--target", str(tmp / "site"), str(tmp / "src")], check=True)
    return tmp / "site"


@pytest.fixture
def installed(site: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[Path]:
    """The installed example on sys.path of this process."""
    monkeypatch.syspath_prepend(str(site))
    refresh()
    yield site
    refresh()
    for mod in [m for m in sys.modules if m == "my_pipeline" or m.startswith("my_pipeline.")]:
        del sys.modules[mod]


def test_filter_known_answers(installed: Path) -> None:
    """Exact odometry of a constant arc is followed exactly; noisy odometry's speed is smoothed, not biased."""
    from my_pipeline.filter import ConstantVelocityFilter, CvNoise, arc_increment, mean_velocity

    for v, w, dt in [(0.3, 0.0, 0.1), (0.5, 0.7, 0.2), (-0.2, -1.3, 0.05), (0.0, 0.4, 0.1)]:
        assert np.allclose(mean_velocity(*arc_increment(v, w, dt), dt), (v, w), atol=1e-12)
    noise = CvNoise(0.05, 0.05, 0.01, 0.01, 0.0, 1e-4, 1e-4)
    f = ConstantVelocityFilter(np.array([1.0, 2.0, 0.5]), noise)
    v, w, dt = 0.4, 0.25, 0.1
    for _ in range(100):
        step = f.step(np.array(arc_increment(v, w, dt)), dt)
    th = 0.5 + w * dt * 100  # the circle's centre is at distance v/w to the left of the start
    centre = np.array([1.0, 2.0]) + v / w * np.array([-math.sin(0.5), math.cos(0.5)])
    truth = centre + v / w * np.array([math.sin(th), -math.cos(th)])
    assert np.hypot(*(step.mean[:2] - truth)) < 1e-4 and abs(step.mean[2] - math.remainder(th, math.tau)) < 1e-5
    assert np.allclose(step.mean[3:], (v, w), atol=1e-6)

    rng = np.random.default_rng(7)  # white speed noise of 0.05 m/s on a constant 0.3 m/s
    f = ConstantVelocityFilter(np.zeros(3), CvNoise(0.02, 0.02, 0.05 * math.sqrt(0.1 / 0.3), 0.01, 0.0, 0.0, 1e-3))
    raw, est = [], []
    for _ in range(600):
        vm = 0.3 + rng.normal(0, 0.05)
        est.append(f.step(np.array(arc_increment(vm, 0.0, 0.1)), 0.1).mean[3])
        raw.append(vm)
    raw_err, est_err = np.asarray(raw[100:]) - 0.3, np.asarray(est[100:]) - 0.3
    assert 0.04 < np.sqrt(np.mean(raw_err**2)) < 0.06
    assert 0.1 * 0.05 < np.sqrt(np.mean(est_err**2)) < 0.5 * 0.05  # smoothed, but not frozen
    assert abs(np.mean(est_err) - np.mean(raw_err)) < 0.002  # no bias of its own: the mean follows the data's
    with pytest.raises(ValueError, match="dt must be finite and > 0"):
        f.step(np.zeros(3), 0.0)
    with pytest.raises(ValueError, match="increment must be a finite"):
        f.step(np.array([np.nan, 0, 0]), 0.1)


def metrics(run: Path) -> dict[str, float]:
    return {k: v["value"] for k, v in json.loads((run / "metrics.json").read_text())["metrics"].items()}


def test_plugin_runs_and_diffs_against_odometry(installed: Path, tmp_path: Path,
                                                capsys: pytest.CaptureFixture[str]) -> None:
    """The installed plugin is listed with its distribution, runs on a simulated recording with the recording's
    odometry noise, estimates speed and turn rate better than raw odometry, and diffs against an odometry run."""
    env = {**os.environ, "PYTHONPATH": str(installed)}
    exe = Path(sys.executable).parent / "slamreplay"
    listed = subprocess.run([str(exe), "pipelines", "--json"], capture_output=True, text=True, env=env)
    rows = {r["name"]: r for r in json.loads(listed.stdout)}
    assert listed.returncode == 0, listed.stderr
    assert rows["cv-filter"]["origin"] == "slamreplay-my-pipeline 0.1.0" and rows["odometry"]["origin"] == "built-in"
    assert {m: s["better"] for m, s in rows["cv-filter"]["metrics"].items()}["speed_rmse_mps"] == "lower"

    rec = tmp_path / "rec.mcap"
    assert main(["record", "sim-landmarks", "--out", str(rec), "--seed", "3", "--duration-s", "60", "-q"]) == 0
    assert main(["run", str(rec), "--pipeline", "odometry", "--out", str(tmp_path / "odo"), "-q"]) == 0
    assert main(["run", str(rec), "--pipeline", "cv-filter", "--out", str(tmp_path / "cv"), "-q"]) == 0
    assert main(["run", str(rec), "--pipeline", "cv-filter", "--preset", "follow-odometry",
                 "--out", str(tmp_path / "loose"), "-q"]) == 0
    odo, cv, loose = metrics(tmp_path / "odo"), metrics(tmp_path / "cv"), metrics(tmp_path / "loose")
    assert cv["speed_rmse_mps"] < 0.8 * cv["odom_speed_rmse_mps"]
    assert cv["yaw_rate_rmse_degps"] < 0.8 * cv["odom_yaw_rate_rmse_degps"]
    assert 0.8 * odo["ape_rmse_m"] < cv["ape_rmse_m"] < 1.25 * odo["ape_rmse_m"]
    # a filter that trusts odometry entirely is dead reckoning: the same trajectory, to a millimetre
    assert abs(loose["ape_rmse_m"] - odo["ape_rmse_m"]) < 1e-3
    manifest = json.loads((tmp_path / "cv" / "manifest.json").read_text())
    assert manifest["config_sources"]["translation_sigma_per_sqrt_m"] == "recording"
    assert manifest["pipeline_origin"]["distribution"] == "slamreplay-my-pipeline"
    assert (tmp_path / "cv" / "velocity.csv").read_text().startswith("t_ns,speed_mps")
    capsys.readouterr()
    main(["diff", str(tmp_path / "odo"), str(tmp_path / "cv"), "--json"])
    diff = json.loads(capsys.readouterr().out)
    changes = {c["field"]: c for c in diff["changes"]}
    assert changes["pipeline_origin.distribution"]["b"] == "slamreplay-my-pipeline"
    ate = next(m for m in diff["metrics"] if m["name"] == "ape_rmse_m")
    assert ate["a"] == pytest.approx(odo["ape_rmse_m"]) and ate["b"] == pytest.approx(cv["ape_rmse_m"])


def test_plugin_bad_config_is_one_line(installed: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """The example's config validation reaches the user as one line, exit 2."""
    from conftest import write_tiny_recording

    rec = write_tiny_recording(tmp_path / "tiny.mcap")
    code = main(["run", str(rec), "--pipeline", "cv-filter", "--set", "accel_sigma_mps2=-1", "--out",
                 str(tmp_path / "r")])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and "accel_sigma_mps2 must be finite and > 0, got -1.0" in err[0]
