"""Small runs of every built-in pipeline, for the tests of what their ``.rrd`` files show."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Any

import numpy as np
import rerun.blueprint as rrb
from rerun.chunk import RrdReader

from slamreplay.algorithms.common import se2
from slamreplay.recorder import GroundTruthPose, LandmarkMap, OdometryPose, RangeBearingScan, Recorder
from slamreplay.replay.runs.run import run_recording


def make_runs(out: Path) -> dict[str, Path]:
    """One run directory per pipeline, on short seeded simulations (about a minute in all)."""
    from slamreplay.recorder.sim.corridor import CorridorConfig, simulate_corridor
    from slamreplay.recorder.sim.landmarks import LandmarkSimConfig, simulate_landmarks
    from slamreplay.recorder.sim.seabed import SeabedSimConfig, simulate_seabed
    from slamreplay.replay.tools.navigate import load_nav_map, navigate

    out.mkdir(parents=True, exist_ok=True)
    runs: dict[str, Path] = {}
    simulate_landmarks(out / "lm.mcap", LandmarkSimConfig(duration_s=60.0), seed=1)
    for name in ("odometry", "dslam", "ekfslam", "slsjf"):
        runs[name] = run_recording(out / "lm.mcap", name, out / name, seed=1).run_dir
    simulate_seabed(out / "sea.mcap", SeabedSimConfig(legs=3, leg_length_m=3.0), seed=2)
    runs["ifmi"] = run_recording(out / "sea.mcap", "ifmi", out / "ifmi").run_dir
    cfg = CorridorConfig(route="left", laps=2, camera_rate_hz=2.0, compression="png")
    simulate_corridor(out / "cor.mcap", cfg, seed=3)
    runs["topometric"] = run_recording(out / "cor.mcap", "topometric", out / "topometric").run_dir
    (out / "world.json").write_text(json.dumps({"config": dataclasses.asdict(cfg), "seed": 3}))
    poses = load_nav_map(runs["topometric"]).graph.poses
    along = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(poses[:, :2], axis=0).T))])
    navigate(runs["topometric"], out / "world.json", int(np.searchsorted(along, 6.0)), out / "nav.mcap", seed=1)
    runs["topometric-nav"] = run_recording(out / "nav.mcap", "topometric-nav", out / "topometric-nav").run_dir
    write_multi_recording(out / "multi.mcap", steps=100)
    runs["dslam-multi"] = run_recording(out / "multi.mcap", "dslam-multi", out / "dslam-multi").run_dir
    return runs


STARTS = {1: np.array([4.0, 5.0, 0.3]), 2: np.array([12.0, 6.0, -1.0]), 3: np.array([20.0, 5.0, 2.0])}
SIGMA_R, SIGMA_B = 0.05, np.radians(1.0)


def write_multi_recording(path: Path, steps: int = 200, seed: int = 4, robots: tuple[int, ...] = (1, 2, 3),
                          truth: tuple[int, ...] = (1, 2, 3)) -> Path:
    """Robots wandering around their own part of a 8 x 4 landmark grid, topics under /robotN/, ground truth
    for the robots in ``truth``; one step is 0.2 s, the robots' messages 1 ms apart within a step."""
    rng = np.random.default_rng(seed)
    gx, gy = np.arange(8) * 3.0 + 1.0, np.arange(4) * 3.0 + 1.0
    lm = np.stack(np.meshgrid(gx, gy), -1).reshape(-1, 2)
    pose = {k: STARTS[k].copy() for k in robots}
    odo = {k: np.zeros(3) for k in robots}
    with Recorder(path, source={"test": "multi"}, seed=seed) as rec:
        rec.write("/ground_truth/landmarks", LandmarkMap(1_000_000_000, np.arange(len(lm)), lm))
        for step in range(steps):
            for k in robots:
                t = 1_000_000_000 + step * 200_000_000 + k * 1_000_000
                ns = f"/robot{k}"
                if k in truth:
                    rec.write(f"{ns}/ground_truth/pose", GroundTruthPose(t, *pose[k]))
                rec.write(f"{ns}/odom", OdometryPose(t, *odo[k]))
                rel = se2.transform_points(se2.inverse(pose[k]), lm)
                r, b = np.hypot(rel[:, 0], rel[:, 1]), np.arctan2(rel[:, 1], rel[:, 0])
                ids = np.flatnonzero((r < 5) & (np.abs(b) < np.pi / 2))
                rec.write(f"{ns}/landmarks/range_bearing",
                          RangeBearingScan(t, r[ids] + rng.normal(0, SIGMA_R, len(ids)),
                                           b[ids] + rng.normal(0, SIGMA_B, len(ids)), ids, SIGMA_R, SIGMA_B))
                home = STARTS[k][:2] + np.array([0.0, 0.5]) - pose[k][:2]
                w = float(np.clip(rng.normal(0, 0.1), -0.3, 0.3))
                if np.hypot(*home) > 3:
                    w = float(np.clip(se2.wrap_angle(np.arctan2(home[1], home[0]) - pose[k][2]), -0.3, 0.3))
                u = np.array([0.04, 0.0, 0.2 * w])
                pose[k] = se2.compose(pose[k], u)
                odo[k] = se2.compose(odo[k], u + rng.normal(0, [0.004, 0.001, 0.004]))
    return path


def rrd_entities(rrd: Path) -> dict[str, dict[str, Any]]:
    """Per entity of an ``.rrd``: whether it has static data, its last step, and its component columns."""
    out: dict[str, dict[str, Any]] = {}
    for ch in RrdReader(rrd).stream():
        e = out.setdefault(str(ch.entity_path), {"static": False, "last_step": None, "columns": set()})
        rb = ch.to_record_batch()
        e["columns"].update(n for n in rb.schema.names if ":" in n)
        if ch.is_static:
            e["static"] = True
        elif "step" in rb.schema.names:
            last = max(int(s) for s in rb.column("step").to_pylist())
            e["last_step"] = last if e["last_step"] is None else max(e["last_step"], last)
    return out


def blueprint_views(bp: rrb.Blueprint) -> list[tuple[str, str, list[str]]]:
    """(tab name, view name, content patterns) of every view of a blueprint made by `slamreplay.replay.engine.views`."""
    out: list[tuple[str, str, list[str]]] = []
    tabs = bp.root_container
    assert isinstance(tabs, rrb.Tabs), "a run's layout is a row of tabs"

    def walk(tab: str, node: Any) -> None:
        if isinstance(node, rrb.Container):
            for child in node.contents:
                walk(tab, child)
            return
        origin = str(node.origin).rstrip("/")
        contents = node.contents
        patterns = list(contents) if isinstance(contents, list) else [str(contents)]
        patterns = [p.replace("$origin", origin) for p in patterns]
        out.append((tab, str(node.name), patterns))

    for t in tabs.contents:
        walk(str(t.name), t)
    return out


def matches(pattern: str, entity: str) -> bool:
    """Whether a ``+ /path`` or ``+ /path/**`` content pattern includes ``entity``."""
    p = pattern.removeprefix("+").strip()
    if p.endswith("/**"):
        base = p[:-3].rstrip("/")
        return entity == base or entity.startswith(base + "/") or base == ""
    return entity == p
