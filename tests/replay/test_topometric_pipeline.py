"""Pipeline topometric on a small seeded sim-corridor route; the map file round trip and its errors."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from recorder.sim.corridor import CorridorConfig, simulate_corridor
from replay.errors import ReplayError
from replay.run import run_recording
from replay.topomap_io import load_map, save_map

CONFIG = CorridorConfig(route="left", laps=2, camera_rate_hz=2.0)


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
    assert m["loop_closure_recall"] >= 0.75  # 0.78 measured (58 of 74)
    assert m["trajectory_ate_rmse_m"] < m["odometry_ate_rmse_m"]  # 0.266 m against 0.270 m: little drift on 68 m
    assert (a / "metrics.json").read_bytes() == (b / "metrics.json").read_bytes()
    manifest = json.loads((a / "manifest.json").read_text())
    assert manifest["timings"]["pipeline_image_mean_s"] > 0
    assert "map.npz" in manifest["artifacts"]


def test_map_file_round_trip(runs: tuple[Path, Path]) -> None:
    """map.npz loads, saves to the same arrays, and gives a navigation localizer."""
    topo = load_map(runs[0] / "map.npz")
    again = load_map(save_map(topo))
    for name in ("poses", "edge_i", "edge_j", "descriptors", "histogram_words", "words"):
        np.testing.assert_array_equal(getattr(topo, name), getattr(again, name))
    assert again.config == topo.config
    assert topo.localizer(start_location=0).vocabulary.n_words == len(topo.words)


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
