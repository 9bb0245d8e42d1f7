"""Small runs of every built-in pipeline, for the tests of what their ``.rrd`` files show."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Any

import numpy as np
import rerun.blueprint as rrb
from rerun.chunk import RrdReader

from slamreplay.replay.run import run_recording


def make_runs(out: Path) -> dict[str, Path]:
    """One run directory per pipeline, on short seeded simulations (about a minute in all)."""
    from slamreplay.recorder.sim.corridor import CorridorConfig, simulate_corridor
    from slamreplay.recorder.sim.landmarks import LandmarkSimConfig, simulate_landmarks
    from slamreplay.recorder.sim.seabed import SeabedSimConfig, simulate_seabed
    from slamreplay.replay.navigate import load_nav_map, navigate

    out.mkdir(parents=True, exist_ok=True)
    runs: dict[str, Path] = {}
    simulate_landmarks(out / "lm.mcap", LandmarkSimConfig(duration_s=60.0), seed=1)
    for name in ("odometry", "dslam", "ekfslam"):
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
    return runs


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
    """(tab name, view name, content patterns) of every view of a blueprint made by `slamreplay.replay.views`."""
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
