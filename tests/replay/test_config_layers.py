"""The sensor model travels in the recording; config values come in layers and the user's always win."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from slamreplay.recorder import Recorder
from slamreplay.recorder.errors import RecorderError
from slamreplay.recorder.importers.mrclam import measure_sensor_model
from slamreplay.recorder.sensor_model import SensorModel
from slamreplay.recorder.sim.landmarks import LandmarkSimConfig, sensor_model, simulate_landmarks
from slamreplay.replay.engine.pipeline import get_pipeline, recording_sensor_model, resolve_layers
from slamreplay.replay.engine.reader import RecordingReader
from slamreplay.replay.errors import ReplayError
from slamreplay.replay.runs.run import run_recording
from tests.conftest import write_tiny_recording


@pytest.fixture(scope="module")
def sim(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("sim") / "sim.mcap"
    simulate_landmarks(path, LandmarkSimConfig(duration_s=60.0), seed=5)
    return path


def test_sensor_model_round_trip_and_validation(tmp_path: Path) -> None:
    model = SensorModel(range_sigma_m=0.1, bearing_sigma_rad=0.02, fx_px=500.0, width_px=640, source="mine")
    path = tmp_path / "r.mcap"
    with Recorder(path, source={"test": "model"}, sensor_model=model) as rec:
        rec.write("/odom", __import__("slamreplay.recorder", fromlist=["OdometryPose"]).OdometryPose(1, 0.0, 0.0, 0.0))
    back = recording_sensor_model(RecordingReader(path).info)
    assert back == model and back.values() == {"range_sigma_m": 0.1, "bearing_sigma_rad": 0.02, "fx_px": 500.0,
                                               "width_px": 640}
    for bad, match in [({"range_sigma_m": -1.0}, "must be >= 0"), ({"range_sigma_m": math.nan}, "finite"),
                       ({"outlier_rate": 1.0}, "must be < 1"), ({"fov_rad": 7.0}, "at most 2 pi"),
                       ({"range_sigma_m": True}, "finite number")]:
        with pytest.raises(RecorderError, match=match):
            SensorModel(**bad)  # type: ignore[arg-type]
    with pytest.raises(RecorderError, match="unknown key 'range_sigma'"):
        SensorModel.from_mapping({"range_sigma": 0.1})
    with pytest.raises(RecorderError, match="not valid JSON"):
        SensorModel.from_record({"sensor_model": "{oops"})
    assert SensorModel.from_record({}) is None
    with pytest.raises(RecorderError, match="must be a SensorModel"):
        Recorder(tmp_path / "x.mcap", source={}, sensor_model={"range_sigma_m": 0.1})  # type: ignore[arg-type]


def test_simulator_states_the_noise_it_drew(sim: Path) -> None:
    """sim-landmarks' model is its noise in the filter's units; measured back from the data it is the same."""
    model = recording_sensor_model(RecordingReader(sim).info)
    assert model is not None and model.source.startswith("sim-landmarks")
    assert model.translation_sigma_per_sqrt_m == pytest.approx(0.02 * math.sqrt(0.1 / 0.2))
    assert model.range_sigma_m == 0.05 and model.bearing_sigma_rad == pytest.approx(math.radians(1.0))
    assert model.heading_sigma_per_sqrt_rad == 0.0 and model.outlier_rate == 0.0
    # Known answer: the MRCLAM importer's estimator, run on a long simulation, finds the stated figures.
    cfg = LandmarkSimConfig(duration_s=1200.0, landmarks=64)
    from slamreplay.recorder.sim.landmarks import landmark_positions, odometry_readings, simulate_motion
    from slamreplay.recorder.sim.unicycle import integrate

    rng = np.random.default_rng(0).spawn(3)
    n = int(cfg.duration_s * cfg.odom_rate_hz)
    speed, turn, truth = simulate_motion(cfg, n, rng[0])
    v, w = odometry_readings(cfg, speed, turn, rng[1])
    odom = integrate((0.0, 0.0, 0.0), v, w, 1.0 / cfg.odom_rate_hz)
    t = np.arange(n + 1, dtype=np.int64) * 100_000_000
    lms = landmark_positions(cfg)
    k = np.arange(0, n + 1, 7)
    lm_idx = k % len(lms)
    d = lms[lm_idx] - truth[k, :2]
    ranges = np.hypot(d[:, 0], d[:, 1]) + rng[2].normal(0, 0.05, len(k))
    bearings = np.arctan2(d[:, 1], d[:, 0]) - truth[k, 2] + rng[2].normal(0, 0.02, len(k))
    measured = measure_sensor_model(t, odom, t, truth, t[k], lm_idx.astype(np.int64), ranges, bearings,
                                    np.arange(len(lms)), lms)
    stated = sensor_model(cfg)
    assert measured.translation_sigma_per_sqrt_m == pytest.approx(stated.translation_sigma_per_sqrt_m, rel=0.15)
    assert measured.heading_sigma_per_sqrt_m == pytest.approx(stated.heading_sigma_per_sqrt_m, rel=0.15)
    assert measured.range_sigma_m == pytest.approx(0.05, rel=0.1)
    assert measured.bearing_sigma_rad == pytest.approx(0.02, rel=0.1)
    assert measured.outlier_rate < 0.01


def test_layers_and_their_order(sim: Path) -> None:
    dslam = get_pipeline("dslam")
    model = recording_sensor_model(RecordingReader(sim).info)
    plain = resolve_layers(dslam)
    assert plain.config.range_sigma_m == 0.15 and set(plain.sources.values()) == {"default"}
    r = resolve_layers(dslam, {"range_sigma_m": "3.0"}, sensor_model=model, preset="paper")
    assert r.config.range_sigma_m == 3.0 and r.sources["range_sigma_m"] == "user"
    assert r.config.translation_sigma_per_sqrt_m == pytest.approx(0.0141421356)
    assert r.sources["translation_sigma_per_sqrt_m"] == "recording" and r.sources["confirm_hits"] == "default"
    assert r.config.outlier_probability == 1.0  # the simulation states no outliers: no gate
    with_outliers = SensorModel(outlier_rate=0.03)
    assert resolve_layers(dslam, sensor_model=with_outliers).config.outlier_probability == 0.9999
    with pytest.raises(ReplayError, match="pipeline dslam has no preset 'fast'; its presets: paper"):
        resolve_layers(dslam, preset="fast")
    with pytest.raises(ReplayError, match="unknown config key 'range_sigma' for pipeline dslam"):
        resolve_layers(dslam, {"range_sigma": 1}, sensor_model=model)
    # odometry has no noise keys: a recording's model does not apply to it, and that is no error
    assert set(resolve_layers(get_pipeline("odometry"), sensor_model=model).sources.values()) <= {"default"}


def test_user_setting_wins_over_what_scans_state(sim: Path, tmp_path: Path) -> None:
    """`--set range_sigma_m=3.0` changes the result although every scan states 0.05 m (it was ignored)."""
    base = run_recording(sim, "dslam", tmp_path / "base", seed=1)
    wide = run_recording(sim, "dslam", tmp_path / "wide", seed=1, config={"range_sigma_m": 3.0})
    assert wide.metrics["landmark_rmse_m"] > 3 * base.metrics["landmark_rmse_m"]  # 60x the range sigma
    manifest = json.loads((tmp_path / "wide" / "manifest.json").read_text())
    assert manifest["config"]["range_sigma_m"] == 3.0 and manifest["config_sources"]["range_sigma_m"] == "user"
    assert manifest["config_sources"]["heading_sigma_per_sqrt_m"] == "recording" and manifest["preset"] is None
    assert base.manifest["config_hash"] != wide.manifest["config_hash"]


def test_old_recordings_without_a_model_use_defaults(tmp_path: Path) -> None:
    rec = write_tiny_recording(tmp_path / "tiny.mcap")
    res = run_recording(rec, "ekfslam", tmp_path / "run")
    assert res.manifest["config_sources"]["translation_sigma_per_sqrt_m"] == "default"
    assert res.manifest["config"]["translation_sigma_per_sqrt_m"] == 0.02


def test_cli_shows_the_model_and_presets(sim: Path, tmp_path: Path) -> None:
    def cli(*args: str) -> subprocess.CompletedProcess[str]:
        return subprocess.run([sys.executable, "-m", "slamreplay.api.cli", *args], capture_output=True, text=True,
                              check=False)

    out = cli("inspect", str(sim))
    assert out.returncode == 0, out.stderr
    assert "sensor model (sim-landmarks: the noise it simulated)" in out.stdout
    assert "  range_sigma_m = 0.05  (range noise (1 sigma), m)" in out.stdout
    report = json.loads(cli("inspect", str(sim), "--json").stdout)
    assert report["sensor_model"]["values"]["max_range_m"] == 5.0
    assert "--preset paper" in cli("pipelines").stdout
    bad = cli("run", str(sim), "--pipeline", "dslam", "--preset", "fast", "--out", str(tmp_path / "r"))
    assert bad.returncode == 2 and bad.stderr.count("\n") == 1 and "no preset 'fast'" in bad.stderr
    assert not (tmp_path / "r").exists()


def test_a_setting_that_cannot_apply_is_an_error(tmp_path: Path) -> None:
    """association=known on scans without ids would map nothing: an error naming the fix, not an empty map."""
    from slamreplay.recorder import OdometryPose, RangeBearingScan

    path = tmp_path / "noids.mcap"
    with Recorder(path, source={"test": "no ids"}) as rec:
        for k in range(5):
            rec.write("/odom", OdometryPose(k * 100_000_000, 0.1 * k, 0.0, 0.0))
            rec.write("/landmarks/range_bearing", RangeBearingScan(k * 100_000_000, [2.0, 3.0], [0.1, -0.2], [-1, -1]))
    with pytest.raises(ReplayError, match="association=known was set, but the scan at 0 ns carries no landmark ids"):
        run_recording(path, "dslam", tmp_path / "known", config={"association": "known"})
    assert run_recording(path, "dslam", tmp_path / "auto").metrics["steps"] == 5  # auto: unknown ids, no error


def test_every_builtin_config_key_has_help() -> None:
    """`slamreplay pipelines` explains every key: each built-in pipeline's config field carries a help text."""
    from slamreplay.replay.engine.pipeline import config_schema, pipeline_plugins

    builtins = {name: p for name, p in pipeline_plugins().items() if p.builtin}
    assert {"dslam", "ekfslam", "topometric", "topometric-nav"} <= set(builtins)
    missing = [f"{name}.{row['key']}" for name, plugin in builtins.items()
               for row in config_schema(plugin.load().Config) if not str(row["help"]).strip()]
    assert not missing, f"config keys without a help text: {', '.join(missing)}"
