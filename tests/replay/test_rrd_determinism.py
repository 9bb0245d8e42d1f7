"""The same recording replayed through any built-in pipeline gives the same ``.rrd`` content, on a loaded machine too.

Five replays of a small seeded recording per pipeline, each by its own process, two at a time beside a
CPU-bound busy loop per core: every pair of ``run.rrd`` files is equal to ordered ``rerun rrd compare``
(the same chunks in the same order), and ``diff_runs`` calls the content and the metrics the same.
Separate processes matter: Rerun's batcher emitted an entity's static and temporal chunks in an order
drawn from a hash seeded per process (one draw per process, the same for every entity: five processes
catch it with probability 15/16); a loaded machine matters: a chunk cut by the batcher's thread took its
place among the others by the wall clock (``slamreplay.replay.engine.observer``). The in-process test
below catches either for certain: no row of a run goes through the batcher.
"""

from __future__ import annotations

import dataclasses
import itertools
import json
import os
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import rerun as rr
import rerun._log

from slamreplay.replay.engine.pipeline import pipeline_plugins
from slamreplay.replay.runs import rrd_compare
from slamreplay.replay.runs.diff import diff_runs
from slamreplay.replay.runs.diff_view import write_comparison_rrd
from slamreplay.replay.runs.rrd_compare import rerun_cli, rrd_content_equal
from slamreplay.replay.runs.run import run_recording
from slamreplay.replay.tools.graph_io import optimize_file
from tests.conftest import REPO
from tests.replay.test_graph_cli import small_graph_file
from tests.replay.view_runs import write_multi_recording

REPLAYS = 5
PARALLEL = 2
# A fresh interpreter imports every pipeline once, then forks a process per replay, PARALLEL at a time:
# argv[1] is [{"pipeline": [recording, run dir], ...} per replay], argv[2] is PARALLEL. Each forked process
# draws its own hash seeds (Rerun's first use of a hash comes after the fork), and the imports, most of a
# small replay's cost, are paid once.
REPLAY_ALL = """
import json, os, sys, traceback
from slamreplay.replay.engine.pipeline import get_pipeline
from slamreplay.replay.runs.run import run_recording
jobs, parallel = json.loads(sys.argv[1]), int(sys.argv[2])
for replay in jobs:
    for pipeline in replay:
        get_pipeline(pipeline)
pending, running, failed = list(enumerate(jobs)), {}, []
while pending or running:
    while pending and len(running) < parallel:
        k, replay = pending.pop(0)
        pid = os.fork()
        if pid == 0:
            try:
                for pipeline, (recording, out) in replay.items():
                    run_recording(recording, pipeline, out, seed=1)
            except BaseException:
                traceback.print_exc()
                os._exit(1)
            os._exit(0)
        running[pid] = k
    pid, status = os.wait()
    if status:
        failed.append(running[pid])
    del running[pid]
sys.exit(f"replays {failed} failed" if failed else 0)
"""
BUSY = "while True: pass"


@pytest.fixture(scope="module")
def recordings(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """A small seeded recording per built-in pipeline (topometric-nav's is a drive on a topometric map)."""
    from slamreplay.recorder.sim.corridor import CorridorConfig, simulate_corridor
    from slamreplay.recorder.sim.landmarks import LandmarkSimConfig, simulate_landmarks
    from slamreplay.recorder.sim.seabed import SeabedSimConfig, simulate_seabed
    from slamreplay.replay.tools.navigate import load_nav_map, navigate

    d = tmp_path_factory.mktemp("determinism")
    simulate_landmarks(d / "lm.mcap", LandmarkSimConfig(duration_s=10.0), seed=1)
    simulate_seabed(d / "sea.mcap", SeabedSimConfig(legs=2, leg_length_m=2.0, image_px=128), seed=2)
    cfg = CorridorConfig(route="left", camera_rate_hz=1.0, compression="png", image_width=160, image_height=120)
    simulate_corridor(d / "cor.mcap", cfg, seed=3)
    topo = run_recording(d / "cor.mcap", "topometric", d / "map").run_dir
    (d / "world.json").write_text(json.dumps({"config": dataclasses.asdict(cfg), "seed": 3}))
    poses = load_nav_map(topo).graph.poses
    along = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(poses[:, :2], axis=0).T))])
    navigate(topo, d / "world.json", int(np.searchsorted(along, 3.0)), d / "nav.mcap", seed=1)
    write_multi_recording(d / "multi.mcap", steps=30)
    lm = d / "lm.mcap"
    return {"odometry": lm, "dslam": lm, "ekfslam": lm, "slsjf": lm, "ifmi": d / "sea.mcap",
            "topometric": d / "cor.mcap", "topometric-nav": d / "nav.mcap", "dslam-multi": d / "multi.mcap"}


def _start(code: str, *args: str) -> subprocess.Popen[str]:
    # Numeric libraries on one thread: their pools only spin in this oversubscription and slow the test down;
    # Rerun's threads (batcher, encoder, file writer), the ones that matter here, are untouched.
    one = dict.fromkeys(("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "OPENCV_FOR_THREADS_NUM"), "1")
    return subprocess.Popen([sys.executable, "-c", code, *args], cwd=REPO, text=True, stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE, env={**os.environ, "PYTHONHASHSEED": "random", **one})


def _replays_under_load(recordings: dict[str, Path], out: Path) -> list[dict[str, Path]]:
    """``REPLAYS`` replays of every pipeline, each by its own process, ``PARALLEL`` at a time, beside as many
    busy loops; the run directories of each replay."""
    jobs = [{p: (str(rec), str(out / f"{k}" / p)) for p, rec in recordings.items()} for k in range(REPLAYS)]
    busy = [_start(BUSY) for _ in range(PARALLEL)]
    replays = _start(REPLAY_ALL, json.dumps(jobs), str(PARALLEL))
    try:
        _, err = replays.communicate(timeout=600)
        assert replays.returncode == 0, f"replays failed:\n{err}"
    finally:
        for proc in [*busy, replays]:
            proc.kill()
            proc.wait()
    return [{p: Path(run_dir) for p, (_, run_dir) in job.items()} for job in jobs]


@pytest.mark.slow
@pytest.mark.skipif(not hasattr(os, "fork"), reason="the replays are forked from one interpreter")
def test_every_pipeline_gives_the_same_rrd_content_on_a_loaded_machine(recordings: dict[str, Path],
                                                                       tmp_path: Path) -> None:
    """Five replays per pipeline under load: every pair equal to ordered `rerun rrd compare`, and to diff_runs."""
    assert rerun_cli() is not None, "the rerun CLI ships with rerun-sdk"
    builtin = {name for name, p in pipeline_plugins().items() if getattr(p, "builtin", False)}
    assert set(recordings) == builtin, "a built-in pipeline has no recording here"
    runs = _replays_under_load(recordings, tmp_path)
    # every pair: with the first replay through diff_runs, the others through rrd_content_equal (what diff_runs
    # calls: ordered `rerun rrd compare`, and the first difference in words when there is one)
    pairs = [(p, i, j) for p in recordings for i, j in itertools.combinations(range(REPLAYS), 2)]

    def check(pij: tuple[str, int, int]) -> str | None:
        p, i, j = pij
        a, b = runs[i][p], runs[j][p]
        if i == 0:
            d = diff_runs(a, b)
            bad = [m.name for m in d.metrics if m.verdict != "same"]
            return None if (d.rrd_equal, d.rrd_detail, bad) == (True, "", []) else f"{p} {i}-{j}: {d.rrd_detail} {bad}"
        equal, why = rrd_content_equal(a / "run.rrd", b / "run.rrd")
        return None if equal is True else f"{p} {i}-{j}: {why}"

    with ThreadPoolExecutor(PARALLEL) as pool:
        unequal = [why for why in pool.map(check, pairs) if why is not None]
    assert not unequal, f"{len(unequal)} of {len(pairs)} pairs differ, first: {unequal[0]}"


def test_no_row_of_a_run_goes_through_the_batcher(recordings: dict[str, Path], tmp_path: Path,
                                                  monkeypatch: pytest.MonkeyPatch) -> None:
    """Every pipeline's run, a comparison file and a pose-graph recording send explicit chunks only: nothing is
    logged as rows (``log``, ``send_property``...) to a stream that writes a file, so no chunk is cut by the
    batcher's thread or ordered by its per-process hash."""
    files: list[rr.RecordingStream] = []  # the streams saved to a file (blueprints are sent from memory streams)
    rows: list[str] = []
    save, log_components = rr.RecordingStream.save, rerun._log._log_components

    def saving(self: rr.RecordingStream, path: Any, *args: Any, **kwargs: Any) -> None:
        files.append(self)
        save(self, path, *args, **kwargs)

    def logging(entity_path: Any, components: Any, *, static: bool = False, recording: Any = None) -> None:
        if any(recording is f for f in files):
            rows.append(f"{entity_path}{' (static)' if static else ''}")
        log_components(entity_path, components, static=static, recording=recording)

    monkeypatch.setattr(rr.RecordingStream, "save", saving)
    monkeypatch.setattr(rerun._log, "_log_components", logging)
    for p, rec in recordings.items():
        run_recording(rec, p, tmp_path / p, seed=1)
    write_comparison_rrd(tmp_path / "dslam", tmp_path / "ekfslam", tmp_path / "diff.rrd")
    optimize_file(small_graph_file(tmp_path), tmp_path / "out.g2o", rrd_path=tmp_path / "graph.rrd")
    assert len(files) == len(recordings) + 2
    assert not rows, f"rows logged through the batcher: {sorted(set(rows))[:10]}"


def _rrd(path: Path, values: list[float], *, static_first: bool = False, extra: str | None = None) -> Path:
    """A small ``.rrd``: scalars at steps 0.. on ``/e`` and a static label, in either order; maybe ``extra``."""
    rec = rr.RecordingStream("slamreplay-test", recording_id=path.stem, send_properties=False)
    rec.save(path)
    static = [rr.ComponentColumn(b.component_descriptor(), b, lengths=[1])
              for b in rr.SeriesLines(names="e").as_component_batches()]
    if static_first:
        rec.send_columns("e", indexes=[], columns=static)
    rec.send_columns("e", indexes=[rr.TimeColumn("step", sequence=range(len(values)))],
                     columns=rr.Scalars.columns(scalars=values))
    if not static_first:
        rec.send_columns("e", indexes=[], columns=static)
    if extra:
        rec.send_columns(extra, indexes=[rr.TimeColumn("step", sequence=[0])], columns=rr.Scalars.columns(scalars=[0]))
    rec.disconnect()
    return path


@pytest.mark.parametrize(("b", "detail"), [
    ({"values": [0.0, 1.0, 2.0, 3.5, 4.0]}, "entity /e, component Scalars:scalars: values differ from step 3 on"),
    ({"values": [0.0, 1.0, 2.0, 3.0]}, "entity /e, on timelines step: 5 rows in A, 4 in B"),
    ({"extra": "f"}, "entity only in B: /f"),
    ({"static_first": True}, "the same rows per entity and component, but cut into chunks or ordered differently: "
                             "chunk 1 holds 5 rows of /e on step in A, 1 static row of /e in B"),
])
@pytest.mark.parametrize("cli", [True, False])
def test_rrd_content_equal_names_the_difference_in_the_users_terms(tmp_path: Path, b: dict[str, Any], detail: str,
                                                                    cli: bool, monkeypatch: pytest.MonkeyPatch) -> None:
    """A difference is told by entity, timeline, row counts and component, never by Rerun's internal assertion;
    the same verdict and words without the rerun CLI (the files read with Rerun's Python API alone)."""
    if not cli:
        monkeypatch.setattr(rrd_compare, "rerun_cli", lambda: None)
    a = _rrd(tmp_path / "a.rrd", [0.0, 1.0, 2.0, 3.0, 4.0])
    other = _rrd(tmp_path / "b.rrd", **{"values": [0.0, 1.0, 2.0, 3.0, 4.0], **b})
    assert rrd_content_equal(a, a) == (True, "")
    assert rrd_content_equal(a, other) == (False, detail)
