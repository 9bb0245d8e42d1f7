"""The ``dslam`` and ``ekfslam`` pipelines end to end: metrics on a simulation, drawing, determinism, bad input."""

from __future__ import annotations

import json
import subprocess
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from slamreplay.algorithms.observe import Image, Points, Text
from slamreplay.recorder import GroundTruthPose, LandmarkMap, OdometryPose, RangeBearingScan, Recorder
from slamreplay.recorder.importers.mrclam import import_mrclam
from slamreplay.recorder.sim import LandmarkSimConfig, simulate_landmarks
from slamreplay.recorder.writer import GROUND_TRUTH_IS_ESTIMATE, METADATA_NAME
from slamreplay.replay.engine.loop import replay
from slamreplay.replay.engine.observer import MemoryObserver
from slamreplay.replay.engine.pipeline import get_pipeline, ground_truth_is_estimate, resolve_config
from slamreplay.replay.engine.reader import RecordingReader
from slamreplay.replay.errors import ReplayError
from slamreplay.replay.runs.rrd_compare import rerun_cli
from slamreplay.replay.runs.run import run_recording


@pytest.fixture(scope="module")
def sim(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """90 s of the paper scenario (seed 3): about 30 landmarks seen."""
    path = tmp_path_factory.mktemp("sim") / "sim.mcap"
    simulate_landmarks(path, LandmarkSimConfig(duration_s=90.0), seed=3)
    return path


def metrics_of(run_dir: Path) -> dict[str, float]:
    doc = json.loads((run_dir / "metrics.json").read_text())
    return {k: v["value"] for k, v in doc["metrics"].items()}


@pytest.mark.parametrize("pipeline", ["dslam", "ekfslam"])
def test_seeded_simulation_bounds(sim: Path, tmp_path: Path, pipeline: str) -> None:
    """Known ids: no false landmark, landmark RMSE < 8 cm, NEES means within consistent/conservative bounds."""
    res = run_recording(sim, pipeline, tmp_path / "run", seed=1)
    m = res.metrics
    assert m["landmarks_true"] == 196 and m["landmarks_mapped"] >= 20 and m["false_landmarks"] == 0
    assert m["landmark_rmse_m"] < 0.08 and m["landmark_nees_mean"] <= 2.5
    assert m["ape_rmse_m"] < 0.1 and m["robot_nees_mean"] <= 3.5 and m["steps"] == 451
    assert "data_association_errors" not in m  # known ids: not applicable
    if pipeline == "dslam":
        assert 1 < m["info_nnz_blocks_per_landmark"] < 20
    timings = json.loads((res.run_dir / "manifest.json").read_text())["timings"]
    assert {"pipeline_scan_step_mean_s", "pipeline_scan_step_p95_s", "pipeline_algorithm_total_s"} <= set(timings)
    if pipeline == "dslam":
        assert "pipeline_recover_mean_s" in timings


def test_unknown_ids_and_ekf_comparison(sim: Path, tmp_path: Path) -> None:
    """Unknown ids: no association error, no false landmark; D-SLAM's and SLSJF's maps (SLSJF matching each local
    map's features to the global map's) within 1.5x of EKF-SLAM's."""
    d = run_recording(sim, "dslam", tmp_path / "d", config={"association": "unknown"}).metrics
    e = run_recording(sim, "ekfslam", tmp_path / "e", config={"association": "unknown"}).metrics
    s = run_recording(sim, "slsjf", tmp_path / "s", config={"association": "unknown"})
    for m in (d, e, s.metrics):
        assert m["data_association_errors"] == 0 and m["false_landmarks"] == 0 and m["landmarks_mapped"] >= 20
    assert d["landmark_rmse_m"] <= 1.5 * e["landmark_rmse_m"]
    assert s.metrics["landmark_rmse_m"] <= 1.5 * e["landmark_rmse_m"]
    assert s.metrics["landmarks_mapped"] == e["landmarks_mapped"]
    assert "unknown ids: " in (s.run_dir / "log.txt").read_text()


def test_everything_is_drawn(sim: Path) -> None:
    """Prediction, measurement and CI poses, anchors, associations, links, sparsity, NEES and solver series."""
    cls = get_pipeline("dslam")
    obs = MemoryObserver()
    replay(RecordingReader(sim), cls, resolve_config(cls, {"info_every_scans": 200}), obs, seed=0,
           log=lambda s: None)
    paths = obs.paths()
    expected = {"world/robot", "world/robot/covariance", "world/robot/prediction", "world/robot/prediction/covariance",
                "world/robot/measurement", "world/robot/measurement/covariance", "world/landmarks/anchors",
                "world/associations", "world/landmarks/observed", "world/landmarks/estimate",
                "world/landmarks/estimate/covariance", "world/landmarks/truth", "world/information/links",
                "dslam/information/sparsity", "world/trajectory/truth", "world/trajectory/odometry",
                "world/trajectory/estimate", "metrics/robot_nees", "metrics/landmark_nees", "metrics/cg_iterations",
                "metrics/ci_omega"}
    assert expected <= paths, sorted(expected - paths)
    anchors = obs.of("world/landmarks/anchors")[0]
    assert isinstance(anchors, Points) and anchors.labels is not None and anchors.labels[0].startswith("f1")
    images = obs.of("dslam/information/sparsity")
    assert len(images) == 3 and isinstance(images[-1], Image) and images[-1].pixels.dtype == np.uint8


def test_two_runs_are_identical(sim: Path, tmp_path: Path) -> None:
    """Same recording, config and seed: byte-identical metrics.json and equal .rrd content."""
    a = run_recording(sim, "dslam", tmp_path / "a", seed=2, config={"map_every_scans": 100})
    b = run_recording(sim, "dslam", tmp_path / "b", seed=2, config={"map_every_scans": 100})
    assert (a.run_dir / "metrics.json").read_bytes() == (b.run_dir / "metrics.json").read_bytes()
    proc = subprocess.run([rerun_cli(), "rrd", "compare", str(a.run_dir / "run.rrd"), str(b.run_dir / "run.rrd")],
                          capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr[-2000:]


def write_recording(path: Path, scans: list[tuple[list[float], list[float], list[int]]], odom: bool = True,
                    source: dict[str, object] | None = None, landmarks: LandmarkMap | None = None) -> Path:
    """Odometry along +x at 0.1 m per step (when ``odom``) with ground truth, and the given scans."""
    with Recorder(path, source=source or {"test": "landmark pipelines"}) as rec:
        if landmarks is not None:
            rec.write("/ground_truth/landmarks", landmarks)
        for k, (r, b, ids) in enumerate(scans):
            t = 1_000_000_000 + k * 100_000_000
            rec.write("/ground_truth/pose", GroundTruthPose(t, 0.1 * k, 0.0, 0.0))
            if odom:
                rec.write("/odom", OdometryPose(t, 0.1 * k, 0.0, 0.0))
            rec.write("/landmarks/range_bearing", RangeBearingScan(t, r, b, ids, 0.05, 0.01))
    return path


def test_bad_input(tmp_path: Path) -> None:
    """No odometry: a failed run; one landmark per scan: localization only, said in the log; NaN never gets in."""
    scan = ([2.0, 3.0], [0.3, -0.4], [0, 1])
    with pytest.raises(ReplayError, match="has no /odom topic"):
        run_recording(write_recording(tmp_path / "no_odom.mcap", [scan] * 3, odom=False), "dslam", tmp_path / "r1")
    single = [scan, scan] + [([2.0 - 0.1 * k], [0.3], [0]) for k in range(2, 6)]
    cls = get_pipeline("dslam")
    obs = MemoryObserver()
    stats = replay(RecordingReader(write_recording(tmp_path / "one.mcap", single)), cls, resolve_config(cls), obs,
                   seed=0, log=lambda s: None)
    notes = [e.text for e in obs.of("dslam/log") if isinstance(e, Text)]
    assert len(notes) == 4 and all("localization only" in n for n in notes)
    assert stats.metrics["steps"] == 6 and stats.metrics["landmarks_mapped"] == 2
    assert "landmarks_true" not in stats.metrics  # no ground-truth map: not applicable
    with pytest.raises(ValueError, match="ranges_m contains NaN"):
        RangeBearingScan(1, [np.nan], [0.0], [0])
    with pytest.raises(ReplayError, match="config key 'recovery' must be one of"):
        run_recording(tmp_path / "one.mcap", "dslam", tmp_path / "r2", config={"recovery": "invert"})


@pytest.mark.slow
def test_mrclam_robot1(shared_data: Path, tmp_path: Path) -> None:
    """MRCLAM robot 1 with no setting (the noise measured at import): robot error far below dead reckoning's 2.62 m."""
    rec = tmp_path / "r1.mcap"
    import_mrclam(shared_data / "mrclam-dataset6", 1, rec)
    run = run_recording(rec, "dslam", tmp_path / "d", config={"map_every_scans": 1000})
    d = run.metrics
    assert run.manifest["config_sources"]["range_sigma_m"] == "recording"
    assert 0.08 < run.manifest["config"]["range_sigma_m"] < 0.13  # README of the data: robust std 0.084, bias 0.038
    assert d["false_landmarks"] == 0 and d["landmarks_mapped"] >= 5  # a camera seeing 1-2 landmarks starves D-SLAM
    assert d["ape_rmse_m"] < 1.0


def test_paper_preset_turns_every_extra_off() -> None:
    """dslam's "paper" preset: every key is a documented config key, and each changes what its note says."""
    from slamreplay.algorithms.dslam import DSlam, ScanStatus
    from slamreplay.algorithms.dslam.localization import PoseStatus
    from slamreplay.replay.pipelines.dslam import DSlamPipeline

    cls = get_pipeline("dslam")
    assert cls is DSlamPipeline
    paper = DSlamPipeline.presets["paper"]
    assert set(paper) == set(DSlamPipeline.preset_notes)
    default, faithful = resolve_config(cls), resolve_config(cls, paper)
    for key, value in paper.items():
        assert getattr(faithful, key) == value and key in DSlamPipeline.preset_notes
    assert default.final_relinearization_iterations > 0 and default.map_gate_probability < 1
    truth = np.array([[2.0, 1.0], [2.5, -1.5], [4.0, 0.5]])
    statuses = {}
    for name, cfg in (("default", default), ("paper", faithful)):
        slam = DSlam(cfg.algorithm("known"))
        for _ in range(3):  # phase I
            d = truth
            slam.observe(np.hypot(*d.T), np.arctan2(d[:, 1], d[:, 0]), [0, 1, 2], 0.05, 0.02)
        slam.predict([0.5, 0.0, 0.0])
        d = truth - [0.5, 0.0]
        r = np.hypot(*d.T) + [0.0, 0.0, 1.0]  # feature 2 read 1 m long: a wrong association
        res = slam.observe(r, np.arctan2(d[:, 1], d[:, 0]), [0, 1, 2], 0.05, 0.02)
        statuses[name] = (res.status, res.measurement.status if res.measurement else None,
                          slam.finalize().method)
    assert statuses["default"] == (ScanStatus.MAP_REJECTED, PoseStatus.INCONSISTENT, "relinearized")
    assert statuses["paper"] == (ScanStatus.MAPPED, PoseStatus.OK, "direct")


@pytest.mark.parametrize("association", ["known", "unknown"])
def test_slsjf_smoothed_local_maps(sim: Path, tmp_path: Path, association: str) -> None:
    """SLSJF with each local map re-solved at its join (``local_map_estimate=smoothed``), with ids and without: no
    false landmark or association error, the map within the bounds EKF-SLAM's meets, its NEES consistent (measured:
    landmark RMSE 0.048 / 0.041 m, NEES 1.99 / 1.98, as with the EKF's local maps to 2 mm); the setting is recorded as
    the user's."""
    res = run_recording(sim, "slsjf", tmp_path / "s", seed=1,
                        config={"local_map_estimate": "smoothed", "association": association})
    m = res.metrics
    assert m["landmarks_mapped"] >= 20 and m["false_landmarks"] == 0 and m["local_maps"] >= 10
    assert m["landmark_rmse_m"] < 0.08 and 0.3 < m["landmark_nees_mean"] <= 2.5
    assert m["ape_rmse_m"] < 0.1 and m["robot_nees_mean"] <= 3.5
    assert m.get("data_association_errors", 0) == 0
    manifest = json.loads((res.run_dir / "manifest.json").read_text())
    assert manifest["config"]["local_map_estimate"] == "smoothed"
    assert manifest["config_sources"]["local_map_estimate"] == "user"


def test_slsjf_pcg_state_recovery(sim: Path, tmp_path: Path) -> None:
    """``state_recovery=pcg`` (D-SLAM's recovery): the run's metrics are the direct factor's to the solves' tolerance,
    the setting is recorded as the user's, and a value not offered is refused before anything runs."""
    direct = run_recording(sim, "slsjf", tmp_path / "d", seed=1).metrics
    res = run_recording(sim, "slsjf", tmp_path / "p", seed=1, config={"state_recovery": "pcg"})
    for key in ("landmark_rmse_m", "landmark_nees_mean", "ape_rmse_m", "robot_nees_mean"):
        assert res.metrics[key] == pytest.approx(direct[key], rel=1e-4), key
    assert res.metrics["landmarks_mapped"] == direct["landmarks_mapped"]
    manifest = json.loads((res.run_dir / "manifest.json").read_text())
    assert manifest["config"]["state_recovery"] == "pcg" and manifest["config_sources"]["state_recovery"] == "user"
    with pytest.raises(ReplayError, match="config key 'state_recovery' must be one of"):
        run_recording(sim, "slsjf", tmp_path / "bad", config={"state_recovery": "cholesky"})
    assert not (tmp_path / "bad").exists()
    cls, obs, logs = get_pipeline("slsjf"), MemoryObserver(), []  # what the view and the log show
    replay(RecordingReader(sim), cls, resolve_config(cls, {"state_recovery": "pcg"}), obs, seed=1, log=logs.append)
    per_join = [e.value for e in obs.of("metrics/slsjf/pcg_iterations")]
    assert len(per_join) == res.metrics["local_maps"] and all(0 <= v <= 400 * 10 for v in per_join)
    assert per_join[0] == 0 and min(per_join[1:]) > 0  # the first local map alone is its own solution
    said = [line for line in logs if line.startswith("state_recovery=pcg: ")]
    assert len(said) == 1 and "; 0 redone by a direct factorization" in said[0], said


def test_a_reference_that_is_an_estimate_has_its_nees_bands_start_at_zero(tmp_path: Path) -> None:
    """A recording whose ground truth is an estimate of its own measurements (Victoria Park's batch optimum): both
    NEES bands are drawn from 0 and the log says why; without the flag, or with a source record that cannot be read,
    the bands are the truth's, with their lower ends above 0."""
    scans = [([2.0, 3.0], [0.3, -0.4], [0, 1])] * 6
    truth = LandmarkMap(0, [0, 1], [[1.9, 0.6], [2.8, -1.2]])
    lows = {}
    for flag in (True, False):
        path = write_recording(tmp_path / f"{flag}.mcap", scans, source={"test": "x", GROUND_TRUTH_IS_ESTIMATE: flag},
                               landmarks=truth)
        reader = RecordingReader(path)
        assert ground_truth_is_estimate(reader.info) is flag
        cls, obs, logs = get_pipeline("ekfslam"), MemoryObserver(), []
        replay(reader, cls, resolve_config(cls), obs, seed=0, log=logs.append)
        lows[flag] = [e.value for p in ("landmark", "robot") for e in obs.of(f"metrics/nees_band/{p}_95_low")]
        assert any("the ground truth is an estimate" in line for line in logs) is flag
    assert len(lows[True]) >= 6 and all(v == 0.0 for v in lows[True])
    assert len(lows[False]) >= 6 and all(v > 0.0 for v in lows[False])
    info = RecordingReader(tmp_path / "True.mcap").info
    for text in ("{not json", "[1, 2]", "[" * 100 + "]" * 100, '{"ground_truth_is_estimate": "yes"}'):
        assert not ground_truth_is_estimate(replace(info, metadata={METADATA_NAME: {"source": text}}))
