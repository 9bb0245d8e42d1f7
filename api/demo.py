"""`make demo`: record every built-in simulation (sim-landmarks, sim-seabed), replay each through every pipeline that
fits.

Needs nothing outside the repository. When the MRCLAM dataset folder is there, robot 1 is
imported and replayed as well.
"""

from __future__ import annotations

import shutil
import sys
from pathlib import Path

from replay.pipeline import all_pipelines
from replay.reader import RecordingReader
from replay.run import RunResult, run_recording

MARKER = ".slamreplay-demo"
DEMO_DURATION_S = 600.0


def _say(text: str, quiet: bool) -> None:
    if not quiet:
        print(text, file=sys.stderr, flush=True)


def _recordings(out: Path, data: Path | None, quiet: bool) -> list[Path]:
    from api.cli import progress_bar
    from recorder.sim.landmarks import LandmarkSimConfig, simulate_landmarks

    rec_dir = out / "recordings"
    rec_dir.mkdir(parents=True)
    made = []
    path = rec_dir / "sim-landmarks.mcap"
    _say(f"recording the D-SLAM paper scenario (sim-landmarks, seed 1, 600 s) -> {path}", quiet)
    with progress_bar("simulating", quiet) as update:
        # The paper's scenario, 10 minutes of driving (the simulator's default is 30): the demo
        # replays it through D-SLAM and EKF-SLAM too and should finish in a few minutes.
        simulate_landmarks(path, LandmarkSimConfig(duration_s=DEMO_DURATION_S), seed=1, progress=update)
    made.append(path)
    from recorder.sim.seabed import SeabedSimConfig, simulate_seabed

    path = rec_dir / "sim-seabed.mcap"
    _say(f"recording the iFMI photo-mapping survey (sim-seabed, seed 1) -> {path}", quiet)
    with progress_bar("simulating", quiet) as update:
        simulate_seabed(path, SeabedSimConfig(), seed=1, progress=update)
    made.append(path)
    mrclam = data / "mrclam-dataset6" if data is not None else None
    if mrclam is not None and mrclam.is_dir():
        from recorder.importers.mrclam import import_mrclam

        path = rec_dir / "mrclam6-robot1.mcap"
        _say(f"importing MRCLAM dataset 6, robot 1 -> {path}", quiet)
        with progress_bar("importing", quiet) as update:
            import_mrclam(mrclam, 1, path, progress=update)
        made.append(path)
    else:
        _say(f"(MRCLAM not found under {data}; pass DATA=... to replay it too)", quiet)
    return made


def run_demo(out: Path, data: Path | None, quiet: bool = False) -> int:
    """Record, replay, print a metrics table; returns the exit code."""
    from api.cli import progress_bar

    if out.exists():
        if not (out / MARKER).exists():
            print(f"slamreplay: error: {out} exists and is not a demo folder; choose another --out", file=sys.stderr)
            return 2
        shutil.rmtree(out)
    out.mkdir(parents=True)
    (out / MARKER).write_text("made by `slamreplay demo`; removed and remade by the next demo\n")
    results: list[tuple[str, str, RunResult]] = []
    for recording in _recordings(out, data, quiet):
        topics = set(RecordingReader(recording).info.logical_topics())
        for name, cls in all_pipelines().items():
            if not set(cls.required_topics) <= topics:
                continue
            run_dir = out / f"{recording.stem}--{name}"
            with progress_bar(f"{name} on {recording.name}", quiet) as update:
                result = run_recording(recording, name, run_dir, seed=1, progress=update)
            results.append((recording.stem, name, result))
    print()
    print(f"{'recording':<22} {'pipeline':<12} {'metric':<28} {'value':>12}")
    for rec_name, pipe, result in results:
        for metric, value in sorted(result.metrics.items()):
            shown = f"{value:,.0f}" if float(value).is_integer() else f"{value:.4f}"
            print(f"{rec_name:<22} {pipe:<12} {metric:<28} {shown:>12}")
    print()
    print("Open a run in the Rerun viewer:")
    for _, _, result in results:
        print(f"  rerun {result.run_dir / 'run.rrd'}")
    if len(results) >= 1:
        first = results[0][2].run_dir
        print(f"Compare two runs: slamreplay diff {first} <another run dir>")
    return 0
