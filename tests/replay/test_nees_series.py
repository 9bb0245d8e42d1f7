"""nees.json: a run's robot NEES over time with its band, known answers against the metrics, scipy and the .rrd."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np
import pytest
from scipy.stats import chi2

from slamreplay.algorithms.observe import Scalar
from slamreplay.recorder.sim import LandmarkSimConfig, simulate_landmarks
from slamreplay.replay.engine.loop import replay
from slamreplay.replay.engine.observer import MemoryObserver
from slamreplay.replay.engine.pipeline import get_pipeline, resolve_config
from slamreplay.replay.engine.reader import RecordingReader
from slamreplay.replay.evaluation.nees_series import (
    MAX_POINTS,
    NEES_ARTIFACT,
    NeesSeries,
    chi2_band,
    nees_artifact,
    read_nees,
)
from slamreplay.replay.runs.run import run_recording


@pytest.fixture(scope="module")
def sim(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """30 s of the paper scenario (seed 3)."""
    path = tmp_path_factory.mktemp("sim") / "sim.mcap"
    simulate_landmarks(path, LandmarkSimConfig(duration_s=30.0), seed=3)
    return path


def test_chi2_band_is_scipys_central_interval() -> None:
    """The band of a 3-dof NEES is chi2.ppf(0.025, 3) .. chi2.ppf(0.975, 3); bad dof or level raise."""
    assert chi2_band(3) == pytest.approx((chi2.ppf(0.025, 3), chi2.ppf(0.975, 3)), rel=1e-12)
    np.testing.assert_allclose(chi2_band(3), (0.2158, 9.3484), atol=1e-4)
    assert chi2_band(2, 0.99) == pytest.approx((chi2.ppf(0.005, 2), chi2.ppf(0.995, 2)), rel=1e-12)
    with pytest.raises(ValueError, match="dof must be >= 1"):
        chi2_band(0)
    with pytest.raises(ValueError, match="level must be in"):
        chi2_band(3, 1.0)


@pytest.mark.parametrize("pipeline", ["dslam", "ekfslam", "slsjf"])
def test_run_writes_the_nees_its_metric_averages(sim: Path, tmp_path: Path, pipeline: str) -> None:
    """nees.json is listed in the manifest with its sha256; its mean is robot_nees_mean, its band chi2(3)'s."""
    res = run_recording(sim, pipeline, tmp_path / "run", seed=1)
    data = (res.run_dir / NEES_ARTIFACT).read_bytes()
    listed = res.manifest["artifacts"][NEES_ARTIFACT]
    assert listed == {"bytes": len(data), "sha256": hashlib.sha256(data).hexdigest()}
    robot = read_nees(data)["robot"]
    assert robot.metric == "robot_nees_mean" and robot.dof == 3 and robot.level == 0.95
    assert robot.mean == pytest.approx(res.metrics["robot_nees_mean"], rel=1e-15)
    assert np.mean(robot.nees) == pytest.approx(res.metrics["robot_nees_mean"], rel=1e-5)  # 6 digits a value
    assert robot.band == pytest.approx((chi2.ppf(0.025, 3), chi2.ppf(0.975, 3)), rel=1e-12)
    assert robot.stride == 1 and robot.steps == len(robot.nees) <= res.metrics["steps"]
    assert robot.t_s[0] == 0.0 and np.all(np.diff(robot.t_s) > 0)
    assert len(data) < 20_000


def test_nees_json_holds_the_rrd_series_and_band(sim: Path) -> None:
    """The values and band logged to the .rrd (metrics/robot_nees, metrics/nees_band/robot_95_*) are the file's."""
    cls, obs = get_pipeline("dslam"), MemoryObserver()
    stats = replay(RecordingReader(sim), cls, resolve_config(cls), obs, seed=1, log=[].append)
    robot = read_nees(stats.artifacts[NEES_ARTIFACT])["robot"]
    logged = [(t, e[3].value) for e in obs.events if e[2] == "metrics/robot_nees" and isinstance(e[3], Scalar)
              for t in [e[1]]]
    assert logged, "the .rrd has a robot NEES series"
    in_file = {robot.t0_ns + round(t * 1e9): v for t, v in zip(robot.t_s.tolist(), robot.nees.tolist(), strict=True)}
    for t, v in logged:  # each logged step is in the file (which may have last steps the replay had no truth for yet)
        assert in_file[t] == pytest.approx(v, rel=1e-5)
    lows = {e[3].value for e in obs.events if e[2] == "metrics/nees_band/robot_95_low"}
    highs = {e[3].value for e in obs.events if e[2] == "metrics/nees_band/robot_95_high"}
    assert (lows, highs) == ({robot.band[0]}, {robot.band[1]})


def test_same_inputs_give_the_same_bytes(sim: Path, tmp_path: Path) -> None:
    """Two runs of the same recording, pipeline and seed write byte-identical nees.json files."""
    a = run_recording(sim, "ekfslam", tmp_path / "a", seed=2)
    b = run_recording(sim, "ekfslam", tmp_path / "b", seed=2)
    assert a.manifest["artifacts"][NEES_ARTIFACT]["sha256"] == b.manifest["artifacts"][NEES_ARTIFACT]["sha256"]


def test_several_robots_write_a_series_each(tmp_path: Path) -> None:
    """dslam-multi: a series per robot, each the mean its robotK_nees_mean metric is; pooled, robot_nees_mean."""
    from tests.replay.view_runs import STARTS, write_multi_recording

    multi = write_multi_recording(tmp_path / "multi.mcap")
    res = run_recording(multi, "dslam-multi", tmp_path / "run", config={"final_relinearization_iterations": 0})
    curves = read_nees((res.run_dir / NEES_ARTIFACT).read_bytes())
    assert sorted(curves) == [f"robot{k}" for k in sorted(STARTS)]
    for name, curve in curves.items():
        assert curve.metric == f"{name}_nees_mean" and curve.mean == pytest.approx(res.metrics[curve.metric], rel=1e-15)
        assert curve.band == chi2_band(3)
    pooled = sum(c.mean * c.steps for c in curves.values()) / sum(c.steps for c in curves.values())
    assert pooled == pytest.approx(res.metrics["robot_nees_mean"], rel=1e-12)


def test_a_pipeline_without_nees_writes_no_file(sim: Path, tmp_path: Path) -> None:
    """The odometry pipeline has no covariance, so no NEES: no nees.json, none listed."""
    res = run_recording(sim, "odometry", tmp_path / "run")
    assert NEES_ARTIFACT not in res.manifest["artifacts"] and not (res.run_dir / NEES_ARTIFACT).exists()


def test_a_long_series_keeps_every_third_step_and_its_exact_mean() -> None:
    """2,500 steps: every 3rd is kept (834 points, real NEES values the band applies to, not means); the mean is
    still over all 2,500; < 25 kB; the same input gives the same bytes."""
    rng = np.random.default_rng(0)
    values = rng.chisquare(3, 2500)
    t_ns = 1_700_000_000_000_000_000 + np.arange(2500, dtype=np.int64) * 100_000_000
    data = nees_artifact({"robot": NeesSeries("robot", 3, chi2_band(3), t_ns, values, metric="robot_nees_mean")})
    robot = read_nees(data)["robot"]
    assert (robot.steps, robot.stride, len(robot.nees)) == (2500, 3, 834) and MAX_POINTS == 1000
    np.testing.assert_allclose(robot.nees, values[::3], rtol=5e-6)  # 6 significant digits
    np.testing.assert_allclose(robot.t_s, np.arange(834) * 0.3, atol=1e-9)
    assert robot.mean == float(values.mean())
    assert len(data) < 25_000
    again = nees_artifact({"robot": NeesSeries("robot", 3, chi2_band(3), t_ns, values.copy(),
                                               metric="robot_nees_mean")})
    assert again == data


def test_bad_series_and_files_raise() -> None:
    """Unequal lengths, decreasing times and files of another format are errors that say so."""
    band = chi2_band(3)
    with pytest.raises(ValueError, match="must be equal"):
        nees_artifact({"robot": NeesSeries("r", 3, band, np.arange(3), np.ones(2))})
    with pytest.raises(ValueError, match="must not decrease"):
        nees_artifact({"robot": NeesSeries("r", 3, band, np.array([2, 1]), np.ones(2))})
    with pytest.raises(ValueError, match="format 2, expected 1"):
        read_nees(json.dumps({"format": 2, "series": {}}))
    with pytest.raises(ValueError, match=r"not a nees\.json file"):
        read_nees("{}")
    assert json.loads(nees_artifact({"robot": NeesSeries("r", 3, band, np.zeros(0, np.int64), np.zeros(0))})) == {
        "format": 1, "series": {}}
