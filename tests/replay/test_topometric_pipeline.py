"""Pipeline topometric on a small seeded sim-corridor route; the map file round trip and its errors."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from slamreplay.algorithms.topometric import Localizer, NavigationConfig
from slamreplay.recorder.sim.corridor import CorridorConfig, simulate_corridor
from slamreplay.replay.errors import ReplayError
from slamreplay.replay.runs.run import run_recording
from slamreplay.replay.tools.topomap_io import load_map, save_map

CONFIG = CorridorConfig(route="left", laps=2, camera_rate_hz=2.0)
REPO = Path(__file__).resolve().parents[2]
RUN = ("import sys; from slamreplay.replay.runs.run import run_recording; "
       "run_recording(sys.argv[1], 'topometric', sys.argv[2], seed=0)")


@pytest.fixture(scope="module")
def corridor(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Two laps of the left loop (34 m each): the second lap revisits the first."""
    path = tmp_path_factory.mktemp("corridor") / "left2.mcap"
    simulate_corridor(path, CONFIG, seed=3)
    return path


@pytest.fixture(scope="module")
def runs(corridor: Path, tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    out = tmp_path_factory.mktemp("runs")
    run_recording(corridor, "topometric", out / "a", seed=0)
    run_recording(corridor, "topometric", out / "b", seed=0)
    return out / "a", out / "b"


def test_pipeline_maps_closes_loops_and_is_deterministic(runs: tuple[Path, Path]) -> None:
    """No false loop closure, most revisits closed, relaxation beats odometry, identical reruns."""
    a, b = runs
    m = {k: v["value"] for k, v in json.loads((a / "metrics.json").read_text())["metrics"].items()}
    assert m["loop_closures"] >= 10 and m["locations"] < m["images"]
    assert m["loop_closure_precision"] == 1.0
    assert m["loop_closure_recall"] >= 0.8  # 0.878 measured (65 loop closures)
    assert m["ape_rmse_m"] < m["odometry_ate_rmse_m"]  # 0.218 m against 0.243 m: little drift on 68 m
    assert (a / "metrics.json").read_bytes() == (b / "metrics.json").read_bytes()
    manifest = json.loads((a / "manifest.json").read_text())
    assert manifest["timings"]["pipeline_image_mean_s"] > 0
    assert "map.npz" in manifest["artifacts"]


def test_fresh_processes_give_identical_runs(corridor: Path, runs: tuple[Path, Path], tmp_path: Path) -> None:
    """Two fresh processes with other hash seeds (and this pytest process) give the same metrics and map bytes."""
    outs = []
    for hash_seed in ("1", "4242"):
        out = tmp_path / f"hash{hash_seed}"
        env = {**os.environ, "PYTHONHASHSEED": hash_seed, "PYTHONPATH": str(REPO)}
        subprocess.run([sys.executable, "-c", RUN, str(corridor), str(out)], cwd=REPO, env=env, check=True,
                       capture_output=True, timeout=600)
        outs.append(out)

    def fingerprint(run: Path) -> tuple[bytes, str]:
        manifest = json.loads((run / "manifest.json").read_text())
        return (run / "metrics.json").read_bytes(), manifest["artifacts"]["map.npz"]["sha256"]

    assert fingerprint(outs[0]) == fingerprint(outs[1]) == fingerprint(runs[0])


def test_map_file_round_trip(runs: tuple[Path, Path]) -> None:
    """map.npz loads, saves to the same arrays, and gives a navigation localizer."""
    topo = load_map(runs[0] / "map.npz")
    again = load_map(save_map(topo))
    for name in ("poses", "edge_i", "edge_j", "descriptors", "histogram_words", "words"):
        np.testing.assert_array_equal(getattr(topo, name), getattr(again, name))
    assert again.config == topo.config
    assert Localizer(topo, NavigationConfig(), 0).vocabulary.n_words == len(topo.words)
    assert topo.truth_poses is not None and again.truth_poses is not None
    np.testing.assert_array_equal(topo.truth_poses, again.truth_poses)


def test_map_holds_the_true_pose_of_each_location(corridor: Path, runs: tuple[Path, Path]) -> None:
    """truth_poses: the ground truth at each location's reference image, near the relaxed pose (ATE scale)."""
    from slamreplay.replay.engine.reader import RecordingReader

    topo = load_map(runs[0] / "map.npz")
    assert topo.truth_poses is not None and topo.truth_poses.shape == (topo.n_locations, 3)
    assert np.all(np.isfinite(topo.truth_poses))
    np.testing.assert_allclose(topo.truth_poses[0], topo.poses[0], atol=1e-6)  # the map starts at the true start
    gt = np.array([e.msg.xy_yaw for e in RecordingReader(corridor).messages(topics=["/ground_truth/pose"])])
    d = np.hypot(gt[None, :, 0] - topo.truth_poses[:, None, 0], gt[None, :, 1] - topo.truth_poses[:, None, 1])
    assert d.min(axis=1).max() < 0.05  # on the true trajectory
    assert np.hypot(*(topo.truth_poses[:, :2] - topo.poses[:, :2]).T).mean() < 1.0


def test_version_1_maps_load_without_truth(runs: tuple[Path, Path], tmp_path: Path) -> None:
    """A version 1 file (before truth_poses) still loads, with truth_poses None; a map without truth saves so."""
    good = dict(np.load(runs[0] / "map.npz"))
    header = json.loads(good["header"].tobytes())
    assert header["version"] == 2
    header["version"] = 1
    old = {k: v for k, v in good.items() if k != "truth_poses"}
    old["header"] = np.frombuffer(json.dumps(header).encode(), np.uint8)
    path = tmp_path / "v1.npz"
    np.savez(path, **old)  # type: ignore[arg-type]
    topo = load_map(path)
    assert topo.truth_poses is None and topo.n_locations == len(good["poses"])
    assert load_map(save_map(topo)).truth_poses is None


def test_bad_map_files(runs: tuple[Path, Path], tmp_path: Path) -> None:
    """Not a map, wrong version, inconsistent arrays, missing file: ReplayError saying so."""
    with pytest.raises(ReplayError, match="not a topo-metric map"):
        load_map(b"hello")
    with pytest.raises(ReplayError, match="cannot read"):
        load_map(tmp_path / "missing.npz")
    good = dict(np.load(runs[0] / "map.npz"))
    header = json.loads(good["header"].tobytes())

    def write(arrays: dict[str, np.ndarray], name: str) -> Path:
        path = tmp_path / name
        with path.open("wb") as fh:
            np.savez(fh, **arrays)  # type: ignore[arg-type]
        return path

    header["version"] = 99
    bad_version = {**good, "header": np.frombuffer(json.dumps(header).encode(), np.uint8)}
    with pytest.raises(ReplayError, match="version 99 is not supported"):
        load_map(write(bad_version, "v99.npz"))
    with pytest.raises(ReplayError, match="inconsistent topo-metric map.*keypoint_offsets"):
        load_map(write({**good, "keypoint_offsets": good["keypoint_offsets"][:-1]}, "cut.npz"))
    with pytest.raises(ReplayError, match="lacks the arrays words"):
        load_map(write({k: v for k, v in good.items() if k != "words"}, "nowords.npz"))


def test_paper_preset_resolves_and_the_manifest_records_it(corridor: Path, runs: tuple[Path, Path],
                                                           tmp_path: Path) -> None:
    """--preset paper: no odometry gate, plain relaxation, an image every 50 cm / 10 deg, recorded as the preset's
    in the manifest; a key the user sets on top (the robust kernel) wins and is counted apart."""
    from slamreplay.replay.engine.pipeline import get_pipeline, resolve_layers

    cls = get_pipeline("topometric")
    resolved = resolve_layers(cls, preset="paper")
    cfg = resolved.config
    assert (cfg.odometry_gate, cfg.relax_robust, cfg.sample_distance_m, cfg.sample_angle_deg) == (False, "none",
                                                                                                  0.5, 10.0)
    assert set(cls.presets["paper"]) <= set(cls.preset_notes)  # every extra says what it adds
    assert resolve_layers(cls).config.odometry_gate is True  # the default keeps the gate
    run_recording(corridor, "topometric", tmp_path / "p", seed=0, preset="paper", config={"relax_robust": "dcs"})
    manifest = json.loads((tmp_path / "p" / "manifest.json").read_text())
    assert manifest["preset"] == "paper"
    src = manifest["config_sources"]
    assert (src["odometry_gate"], src["sample_distance_m"], src["relax_robust"]) == ("preset paper", "preset paper",
                                                                                    "user")
    assert manifest["config"]["odometry_gate"] is False and manifest["config"]["relax_robust"] == "dcs"
    m = {k: v["value"] for k, v in json.loads((tmp_path / "p" / "metrics.json").read_text())["metrics"].items()}
    assert "loop_closures_rejected" in m and m["loop_closure_precision"] == 1.0
    default = json.loads((runs[0] / "metrics.json").read_text())["metrics"]
    assert "loop_closures_rejected" not in default  # only with the kernel


@pytest.mark.parametrize(("values", "match"), [
    ({"relax_robust": "huber"}, r"relax_robust"),
    ({"odometry_gate": "maybe"}, r"odometry_gate"),
])
def test_bad_robust_settings_are_refused_naming_the_key(values: dict, match: str) -> None:
    """A bad relax_robust or odometry_gate is a ReplayError naming the key, before anything runs."""
    from slamreplay.replay.engine.pipeline import get_pipeline, resolve_layers

    with pytest.raises(ReplayError, match=match):
        resolve_layers(get_pipeline("topometric"), values)
