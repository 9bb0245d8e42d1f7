"""`make demo`: record every built-in simulation (sim-landmarks, sim-seabed, sim-corridor), replay each through the
pipelines made for it, and navigate on the topo-metric map with the simulator in the loop.

Needs nothing outside the repository. When the MRCLAM dataset folder is there, robot 1 is
imported and replayed as well.
"""

from __future__ import annotations

import shutil
import sys
from pathlib import Path

from slamreplay.api.cli.hints import has_display, tool, view_hint
from slamreplay.api.cli.progress import progress_bar, say
from slamreplay.replay.runs.run import RunResult, run_recording

MARKER = ".slamreplay-demo"
DEMO_DURATION_S = 600.0


def _say(text: str, quiet: bool) -> None:
    say(text, quiet)


# Which pipelines each demo recording goes through (a forward camera is no photo-mapping input).
PIPELINES = {
    "sim-landmarks": ("odometry", "dslam", "ekfslam"),
    "sim-seabed": ("odometry", "ifmi"),
    "mrclam6-robot1": ("odometry", "dslam", "ekfslam"),
    "sim-corridor": ("odometry", "topometric"),
    "sim-corridor-navigation": ("topometric-nav",),
}
NAV_GOAL_ALONG_M = 20.0  # the demo navigates to the first map node this far along the mapped route


def _recordings(out: Path, data: Path | None, quiet: bool) -> list[Path]:
    from slamreplay.recorder.sim.corridor import CorridorConfig, simulate_corridor
    from slamreplay.recorder.sim.landmarks import LandmarkSimConfig, simulate_landmarks
    from slamreplay.recorder.sim.seabed import SeabedSimConfig, simulate_seabed

    rec_dir = out / "recordings"
    rec_dir.mkdir(parents=True)
    made = []
    path = rec_dir / "sim-landmarks.mcap"
    _say(f"recording the D-SLAM paper scenario (sim-landmarks, seed 1, 600 s) -> {path}", quiet)
    with progress_bar("record sim-landmarks", quiet) as update:
        # The paper's scenario, 10 minutes of driving (the simulator's default is 30): the demo
        # replays it through D-SLAM and EKF-SLAM too and should finish in a few minutes.
        simulate_landmarks(path, LandmarkSimConfig(duration_s=DEMO_DURATION_S), seed=1, progress=update)
    made.append(path)
    path = rec_dir / "sim-seabed.mcap"
    _say(f"recording the iFMI photo-mapping survey (sim-seabed, seed 1) -> {path}", quiet)
    with progress_bar("record sim-seabed", quiet) as update:
        simulate_seabed(path, SeabedSimConfig(), seed=1, progress=update)
    made.append(path)
    path = rec_dir / "sim-corridor.mcap"
    _say(f"recording the teleoperated mapping route (sim-corridor, seed 1, 2.5 images/s) -> {path}", quiet)
    with progress_bar("record sim-corridor", quiet) as update:
        simulate_corridor(path, CorridorConfig(camera_rate_hz=2.5), seed=1, progress=update)
    made.append(path)
    mrclam = data / "mrclam-dataset6" if data is not None else None
    if mrclam is not None and mrclam.is_dir():
        from slamreplay.recorder.importers.mrclam import import_mrclam

        path = rec_dir / "mrclam6-robot1.mcap"
        _say(f"importing MRCLAM dataset 6, robot 1 -> {path}", quiet)
        with progress_bar("record mrclam", quiet) as update:
            import_mrclam(mrclam, 1, path, progress=update)
        made.append(path)
    else:
        _say(f"(MRCLAM not found under {data}; pass DATA=... to replay it too)", quiet)
    return made


def _navigation(out: Path, map_run: Path, world: Path, quiet: bool) -> Path:
    """Drive the sim-corridor world on the demo's map, NAV_GOAL_ALONG_M along the mapped route (paper section IV)."""
    import numpy as np

    from slamreplay.replay.tools.navigate import load_nav_map, navigate

    poses = load_nav_map(map_run).graph.poses
    along = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(poses[:, :2], axis=0).T))])
    goal = int(np.searchsorted(along, NAV_GOAL_ALONG_M)) if along[-1] > NAV_GOAL_ALONG_M else len(poses) - 1
    path = out / "recordings" / "sim-corridor-navigation.mcap"
    _say(f"navigating on the map from node 0 to node {goal} with the simulator in the loop -> {path}", quiet)
    with progress_bar(f"navigate to node {goal}", quiet) as update:
        navigate(map_run, world, goal, path, seed=1, progress=update)
    return path


def run_demo(out: Path, data: Path | None, quiet: bool = False) -> int:
    """Record, replay, print a metrics table; returns the exit code."""

    if out.exists():
        if not (out / MARKER).exists():
            print(f"slamreplay: error: {out} exists and is not a demo folder; choose another --out", file=sys.stderr)
            return 2
        shutil.rmtree(out)
    out.mkdir(parents=True)
    (out / MARKER).write_text("made by `slamreplay demo`; removed and remade by the next demo\n")
    results: list[tuple[str, str, RunResult]] = []
    queue = _recordings(out, data, quiet)
    while queue:
        recording = queue.pop(0)
        for name in PIPELINES[recording.stem]:
            run_dir = out / f"{recording.stem}--{name}"
            with progress_bar(f"run {name} on {recording.name}", quiet, unit="messages") as update:
                result = run_recording(recording, name, run_dir, seed=1, progress=update,
                                       )
            results.append((recording.stem, name, result))
            if name == "topometric":  # its map: navigate on it, then replay that drive too
                queue.append(_navigation(out, run_dir, recording, quiet))
    print()
    print(f"{'recording':<24} {'pipeline':<15} {'metric':<28} {'value':>12}")
    for rec_name, pipe, result in results:
        for metric, value in sorted(result.metrics.items()):
            shown = f"{value:,.0f}" if float(value).is_integer() else f"{value:.4f}"
            print(f"{rec_name:<24} {pipe:<15} {metric:<28} {shown:>12}")
    print()
    print("\n".join(next_steps([r for _, _, r in results], {(rec, pipe): r.run_dir for rec, pipe, r in results})))
    return 0


def next_steps(results: list[RunResult], runs: dict[tuple[str, str], Path]) -> list[str]:
    """What to type next, spelled to work as printed here: open the runs, compare D-SLAM with EKF-SLAM."""
    rerun, slamreplay = tool("rerun"), tool("slamreplay")
    lines = [f"Open a run in the Rerun viewer{'' if has_display() else ' (no display here: see below)'}:"]
    lines += [f"  {rerun} {r.run_dir / 'run.rrd'}" for r in results]
    if not has_display() and results:
        lines += view_hint(results[0].run_dir / "run.rrd")
    pair = runs.get(("sim-landmarks", "ekfslam")), runs.get(("sim-landmarks", "dslam"))
    if pair[0] is not None and pair[1] is not None:
        lines.append(f"Compare D-SLAM with EKF-SLAM on one recording (exit 1 when a metric is worse): "
                     f"{slamreplay} diff {pair[0]} {pair[1]}")
    if slamreplay != "slamreplay":
        lines.append(f"To type slamreplay and rerun without the path: source {Path(slamreplay).parent / 'activate'}")
    return lines
