"""kill -9 of `suite run` and of `slamreplay serve`: nothing unfinished reads as finished, a re-run resumes,
a restarted server ends every job. The 20-trial passes are `benchmarks/crash_consistency.py`."""

from __future__ import annotations

import json
import sys
import uuid
from collections.abc import Iterator
from pathlib import Path

import pytest
from conftest import REPO, write_tiny_recording

from slamreplay.api.service.executor import Task, run_task
from slamreplay.replay.errors import ReplayError
from slamreplay.replay.runs.compare import load_side
from slamreplay.replay.runs.suite import load_suite
from slamreplay.replay.runs.suite_run import CellJob, run_suite, unfinished

sys.path.insert(0, str(REPO / "benchmarks"))
import crash_suite_service as cs


class Killed(BaseException):
    """Stands for SIGKILL: nothing after it runs (no except Exception catches it)."""


def serial(stop_after: int | None = None):  # type: ignore[no-untyped-def]
    """A ``run_cells`` running cells one by one in this process; ``Killed`` after ``stop_after`` cells."""

    def run_cells(todo: list[CellJob]) -> Iterator[tuple[CellJob, str | None]]:
        for i, job in enumerate(todo):
            if stop_after is not None and i == stop_after:
                raise Killed
            task = Task(uuid.uuid4().hex, str(job.recording.path), job.cell.pipeline, dict(job.cell.config),
                        job.cell.seed, str(job.run_dir), "", dict(job.recording.topic_map))
            outcome = run_task(task, lambda f: None)
            yield job, None if outcome.status == "succeeded" else outcome.error

    return run_cells


def test_suite_killed_between_cells_is_unfinished_until_resumed(tmp_path: Path) -> None:
    """A suite stopped after 2 of 4 cells: compare refuses it as unfinished; the re-run reuses the 2 and runs 2."""
    write_tiny_recording(tmp_path / "tiny.mcap", n=40)
    (tmp_path / "s.toml").write_text('seeds = [0, 1, 2, 3]\n[recordings.tiny]\npath = "tiny.mcap"\n'
                                     '[pipelines.odometry]\n')
    suite, out = load_suite(tmp_path / "s.toml"), tmp_path / "res"
    with pytest.raises(Killed):
        run_suite(suite, out, "code", serial(stop_after=2), cache=tmp_path / "cache")
    assert json.loads((out / "suite.json").read_text())["finished"] is False
    assert len((out / "results.jsonl").read_text().splitlines()) == 2
    why = unfinished(out)
    assert why is not None and "2 of 4 cells" in why and "slamreplay suite run" in why
    with pytest.raises(ReplayError, match="unfinished suite run"):
        load_side(out)
    rows = run_suite(suite, out, "code", serial(), cache=tmp_path / "cache")
    assert [r["cached"] for r in rows] == [True, True, False, False]
    assert all(r["status"] == "succeeded" for r in rows)
    assert unfinished(out) is None and len(load_side(out).rows) == 4


def test_old_results_without_the_flag_count_rows(tmp_path: Path) -> None:
    """A results directory from before the ``finished`` flag is unfinished when it has fewer rows than cells."""
    out = tmp_path / "res"
    out.mkdir()
    (out / "suite.json").write_text(json.dumps({"format": 1, "cells": 3, "suite": "s.toml"}))
    (out / "results.jsonl").write_text("{}\n{}\n")
    assert unfinished(out) is not None and "2 of 3 cells" in (unfinished(out) or "")
    (out / "results.jsonl").write_text("{}\n{}\n{}\n")
    assert unfinished(out) is None


@pytest.mark.slow
def test_suite_run_killed_at_random(tmp_path: Path) -> None:
    """`suite run` killed by SIGKILL part-way (a real process, 2 workers), the moment its first of 4 rows is written, so
    the kill lands mid-run on a fast machine as on a slow one: the trial's rules all hold."""
    recording, baseline = cs.suite_setup(tmp_path, duration_s=30.0, light=True)
    t = cs.suite_trial(tmp_path, recording, baseline, 0, 0.0, light=True, after_rows=1)
    assert t["problems"] == [], t
    assert not t["finished"] and not t["said_finished"] and 1 <= t["rows_before_rerun"] < 4, t
    assert t["reused"] >= 1 and t["reused"] + t["rerun"] == 4, t


@pytest.mark.slow
def test_server_killed_mid_job_then_restarted(tmp_path: Path) -> None:
    """The server killed by SIGKILL with jobs running and an upload streaming in: after a restart nothing partial
    is listed, unfinished jobs are 409 for /diff, and every job ends with its files (none stays running)."""
    recording = tmp_path / "rec.mcap"
    cs.cli("record", "sim-landmarks", "--duration-s", "30", "--seed", "1", "--out", recording, "-q")
    upload = tmp_path / "up.mcap"
    cs.cli("record", "sim-landmarks", "--duration-s", "60", "--seed", "2", "--out", upload, "-q")
    data, rid, base = cs.serve_setup(tmp_path, recording)
    t = cs.serve_trial(tmp_path, data, rid, base, upload.read_bytes(), 0, 1.5, jobs=3)
    assert t["problems"] == [], t
    assert sum(t["ended"].values()) == 3 and set(t["ended"]) <= {"succeeded", "failed", "interrupted"}


def test_killed_after_its_files_before_its_manifest_reads_unfinished(tmp_path: Path,
                                                                     monkeypatch: pytest.MonkeyPatch) -> None:
    """The manifest is a run's commit point: a suite killed after a cell's run.rrd and metrics.json landed but
    before its manifest did (the window a random kill once hit) leaves a run diff refuses as unfinished, and the
    re-run runs that cell again instead of reusing it."""
    import slamreplay.replay.runs.run as run_mod
    from slamreplay.replay.runs.diff import load_run

    write_tiny_recording(tmp_path / "tiny.mcap", n=40)
    (tmp_path / "s.toml").write_text('seeds = [0]\n[recordings.tiny]\npath = "tiny.mcap"\n[pipelines.odometry]\n')
    suite, out = load_suite(tmp_path / "s.toml"), tmp_path / "res"
    real = run_mod.atomic_write

    def killed_at_manifest(path: Path, data: str | bytes) -> None:
        if path.name == "manifest.json":
            raise Killed
        real(path, data)

    with monkeypatch.context() as m:
        m.setattr(run_mod, "atomic_write", killed_at_manifest)
        with pytest.raises(Killed):
            run_suite(suite, out, "code", serial(), cache=tmp_path / "cache")
    (run_dir,) = (out / "runs").iterdir()
    assert (run_dir / "run.rrd").is_file() and (run_dir / "metrics.json").is_file()
    assert not (run_dir / "manifest.json").exists()
    with pytest.raises(ReplayError, match="not a finished run"):
        load_run(run_dir)
    rows = run_suite(suite, out, "code", serial(), cache=tmp_path / "cache")
    assert [(r["cached"], r["status"]) for r in rows] == [(False, "succeeded")]
    assert unfinished(out) is None
