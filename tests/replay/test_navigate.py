"""Closed-loop navigation on a topo-metric map (paper section IV) and its replay through ``topometric-nav``.

One mapping run serves every test: ``sim-corridor`` drives the ``outer`` then the ``left`` tour with
drift-free odometry, the ``topometric`` pipeline maps it with loop closures off (a chain of
locations at their true poses, so these tests do not depend on the mapping's loop closures), and
the fixture adds the edges the loop closures on the shared corridors would add. Navigation then
runs in the same world with drifting odometry.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest

from api.cli import main as cli
from recorder.messages import assert_msg_equal
from replay.errors import ReplayError
from replay.navigate import NavigateSummary, load_nav_map, navigate
from replay.reader import RecordingReader
from replay.run import run_recording
from replay.topomap_io import save_map

pytestmark = pytest.mark.slow
WHEEL_RATIO_ERROR = 0.008  # 0.024 rad of heading drift per metre: odometry alone leaves a corridor in ~10 m


@pytest.fixture(scope="module")
def world(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """The mapping recording, the map (chain + junction edges) and a navigation world with drifting odometry."""
    from recorder.sim.corridor import CorridorConfig, simulate_corridor

    d = tmp_path_factory.mktemp("nav")
    exact = dict(odom_wheel_ratio_error=0.0, odom_wheelbase_error=0.0, odom_scale_error=0.0, odom_sigma_m=0.0,
                 odom_sigma_rad=0.0, odom_sigma_rad_per_m=0.0)
    cfg = CorridorConfig(route="outer,left", camera_rate_hz=2.5, compression="png", **exact)
    simulate_corridor(d / "mapping.mcap", cfg, seed=1)
    run_recording(d / "mapping.mcap", "topometric", d / "mapping_run", config={"max_translation_px": 0.01})
    chain = load_nav_map(d / "mapping_run").topomap
    p = chain.poses
    first = second_tour(p)
    extra = []
    for j in range(first, len(p)):  # the second tour's nodes, linked to the first tour's node it revisits
        d_xy = np.hypot(*(p[:first, :2] - p[j, :2]).T)
        d_yaw = np.abs((p[:first, 2] - p[j, 2] + np.pi) % (2 * np.pi) - np.pi)
        i = int(np.argmin(d_xy + 10.0 * (d_yaw > np.radians(30))))
        if d_xy[i] < 0.4 and d_yaw[i] < np.radians(30):
            extra.append((i, j))
    assert len(extra) > 20
    i, j = np.array(extra).T
    z = np.zeros((len(extra), 3))
    info = np.broadcast_to(np.eye(3), (len(extra), 3, 3))
    linked = dataclasses.replace(
        chain, edge_i=np.r_[chain.edge_i, i], edge_j=np.r_[chain.edge_j, j],
        edge_measurements=np.r_[chain.edge_measurements, z], edge_information=np.r_[chain.edge_information, info],
        edge_loop=np.r_[chain.edge_loop, np.ones(len(extra), bool)])
    (d / "map.npz").write_bytes(save_map(linked))
    drift = dataclasses.replace(cfg, **{**exact, "odom_wheel_ratio_error": WHEEL_RATIO_ERROR,
                                        "odom_sigma_m": 0.01, "odom_sigma_rad": 0.01})
    (d / "world.json").write_text(json.dumps({"config": dataclasses.asdict(drift), "seed": 1}))
    return {"dir": d, "map": d / "map.npz", "chain": d / "mapping_run", "world": d / "world.json",
            "mapping": d / "mapping.mcap"}


def second_tour(poses: np.ndarray) -> int:
    """Index of the first node of the second tour: back at the origin after the first."""
    return int(np.argmin(np.hypot(poses[:, 0], poses[:, 1]) + 1e3 * (np.arange(len(poses)) < 20)))


def node_near(map_path: Path, x: float, y: float, before: int | None = None) -> int:
    """The map node closest to (x, y), among the first ``before`` nodes if given."""
    p = load_nav_map(map_path).graph.poses[:before]
    return int(np.argmin(np.hypot(p[:, 0] - x, p[:, 1] - y)))


@pytest.fixture(scope="module")
def drives(world: dict[str, Path]) -> dict[str, tuple[Path, NavigateSummary]]:
    """The same 21 m drive (south corridor, corner, east corridor) with and without visual correction."""
    goal = node_near(world["map"], 16.0, 5.0)
    out: dict[str, tuple[Path, NavigateSummary]] = {}
    for name, visual in (("on", True), ("off", False)):
        rec = world["dir"] / f"drive_{name}.mcap"
        out[name] = rec, navigate(world["map"], world["world"], goal, rec, seed=3, visual_correction=visual,
                                  through_walls=True)
    return out


def test_closed_loop_reaches_the_goal_on_the_path(drives: dict[str, tuple[Path, NavigateSummary]]) -> None:
    """Visual correction on: goal reached, mean true cross-track error at most 15 cm, many corrections."""
    s = drives["on"][1]
    assert s.reached and not s.collided
    assert s.goal_distance_m < 0.3
    assert s.cross_track_mean_m <= 0.15
    assert s.visual_corrections >= 0.5 * s.images


def test_odometry_alone_leaves_the_path(drives: dict[str, tuple[Path, NavigateSummary]]) -> None:
    """Fig. 4's point: the same drive on odometry only ends more than 1 m from the path (through a wall)."""
    s = drives["off"][1]
    assert s.visual_corrections == 0 and s.loop_closures > 0
    assert s.cross_track_final_m > 1.0
    assert s.collided


def test_replay_reproduces_the_run_and_scores_it(world: dict[str, Path],
                                                 drives: dict[str, tuple[Path, NavigateSummary]]) -> None:
    """topometric-nav on the recording gives back every localization and command, and the runner's figures."""
    rec, s = drives["on"]
    result = run_recording(rec, "topometric-nav", world["dir"] / "replay_on")
    m = result.metrics
    assert m["replay_mismatches"] == 0
    assert m["goal_reached"] == 1.0
    assert m["cross_track_error_m_mean"] == pytest.approx(s.cross_track_mean_m, abs=1e-9)
    assert m["cross_track_error_m_max"] == pytest.approx(s.cross_track_max_m, abs=1e-9)
    assert m["visual_corrections"] == s.visual_corrections
    assert m["loop_closure_rate"] == pytest.approx(s.loop_closures / s.images)
    off = run_recording(drives["off"][0], "topometric-nav", world["dir"] / "replay_off").metrics
    assert off["replay_mismatches"] == 0 and off["visual_corrections"] == 0
    assert off["cross_track_error_m_max"] > 1.0


def test_shortcut_differs_from_the_mapped_route(world: dict[str, Path]) -> None:
    """Fig. 6: from the south to the north corridor Dijkstra takes the middle corridor mapped in the second tour."""
    n_outer = second_tour(load_nav_map(world["map"]).graph.poses)
    start = node_near(world["map"], 3.0, 0.0, n_outer)
    goal = node_near(world["map"], 3.0, 10.0, n_outer)
    assert start < goal  # the mapped route from start to goal goes round the east loop
    rec = world["dir"] / "shortcut.mcap"
    s = navigate(world["map"], world["world"], goal, rec, start=start, seed=5)
    mapped = load_nav_map(world["map"]).graph.poses[start:goal + 1, :2]
    mapped_length = float(np.hypot(*np.diff(mapped, axis=0).T).sum())
    assert any(k >= n_outer for k in s.route)  # through the second tour's middle corridor
    assert s.route_length_m < 0.6 * mapped_length
    assert s.reached and s.goal_distance_m < 0.5
    assert s.cross_track_mean_m <= 0.15


def test_navigation_is_deterministic(world: dict[str, Path]) -> None:
    """The same seed gives the same messages; another seed other odometry."""
    goal = node_near(world["map"], 4.0, 0.0, 60)
    runs = []
    for k, seed in enumerate((7, 7, 8)):
        rec = world["dir"] / f"det_{k}.mcap"
        navigate(world["map"], world["world"], goal, rec, seed=seed)
        runs.append([e.msg for e in RecordingReader(rec).messages()])
    assert len(runs[0]) == len(runs[1])
    for a, b in zip(runs[0], runs[1], strict=True):
        assert_msg_equal(a, b)
    assert any(type(a) is not type(b) or repr(a) != repr(b) for a, b in zip(runs[0], runs[2], strict=False))


def test_a_map_that_does_not_match_is_refused(world: dict[str, Path],
                                              drives: dict[str, tuple[Path, NavigateSummary]]) -> None:
    """Replaying with another map file fails with a clear error; so do bad nodes, maps and worlds."""
    rec = drives["on"][0]
    with pytest.raises(ReplayError, match="is not the map this navigation was recorded with"):
        run_recording(rec, "topometric-nav", world["dir"] / "bad_map", config={"map_path": str(world["chain"])})
    with pytest.raises(ReplayError, match="no /cmd_vel topic"):
        run_recording(world["mapping"], "topometric-nav", world["dir"] / "not_nav",
                      config={"map_path": str(world["map"])})
    with pytest.raises(ReplayError, match="--goal 9999 is not a node"):
        navigate(world["map"], world["world"], 9999, world["dir"] / "x.mcap")
    (world["dir"] / "empty").mkdir(exist_ok=True)
    with pytest.raises(ReplayError, match="no map.npz"):
        navigate(world["dir"] / "empty", world["world"], 1, world["dir"] / "x.mcap")
    bad = world["dir"] / "bad.json"
    bad.write_text("[1, 2]")
    with pytest.raises(ReplayError, match="world"):
        navigate(world["map"], bad, 1, world["dir"] / "x.mcap")
    assert not (world["dir"] / "x.mcap").exists()
    assert cli(["navigate", "--map", str(world["map"]), "--world", str(world["world"]), "--goal", "-1",
                "--out", str(world["dir"] / "y.mcap")]) == 2
