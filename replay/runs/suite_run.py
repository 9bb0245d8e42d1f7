"""Running a suite: recordings made or fetched on demand, a cache key per cell, results.jsonl.

``RESULTS_DIR/`` holds ``results.jsonl`` (one row per cell: the cell, every metric with its
direction, recording sha256, config hash, code version, status, wall time, peak memory, the
run directory), ``suite.json`` (what ran: suite, code version, revision, and ``finished``, true
only once every row is written) and ``runs/<cell>/``. A suite run killed part-way is resumed by
running it again into the same directory: its finished cells are reused.

A cell's cache key is the sha256 of its inputs: recording sha256, pipeline, the variant's
config values, run seed, topic map and code version. The resolved configuration is a function
of those (defaults and the recording's sensor model come from the code and the recording), so
equal keys mean equal runs. A run directory holding a succeeded run with the key it was made
for is reused; anything else in its place (a failed or interrupted run) is removed and run again.

Simulated recordings are made once by the code running the suite (both sides of a comparison
replay the same recordings) and cached by their content in ``<cache>/recordings/``: the key
is the simulator, its options, the seed and a fingerprint of the simulator's loaded code.
``url`` recordings are fetched with fsspec once per (url, the store's checksum of it).
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import subprocess
import tempfile
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from slamreplay.recorder.files import atomic_write, replacing
from slamreplay.recorder.version import SOURCE_ROOT, git_commit, version
from slamreplay.replay.errors import ReplayError
from slamreplay.replay.metric_registry import normalize
from slamreplay.replay.runs.diff import determinism_of
from slamreplay.replay.runs.run import sha256_file
from slamreplay.replay.runs.suite import Cell, RecordingSpec, Suite, canonical, sim_config_class, sim_kwargs
from slamreplay.replay.tools.cache import cache_dir
from slamreplay.replay.tools.determinism import PROGRAM_FIELDS

RESULTS_FORMAT = 1
SIM_MODULES = {sim: tuple(f"slamreplay.recorder.sim.{m}" for m in modules) for sim, modules in {
    "sim-landmarks": ("landmarks", "landmarks_config", "unicycle", "wheel_odometry"),
    "sim-seabed": ("seabed", "seabed_config", "unicycle"),
    "sim-corridor": ("corridor", "corridor_config", "corridor_plan", "corridor_render", "unicycle", "wheel_odometry"),
}.items()}
WRITER_MODULES = tuple(f"slamreplay.recorder.{m}" for m in ("writer", "messages", "codec.protobuf", "codec.schemas"))


def code_version() -> str:
    """The commit of the running code; with local changes ``<sha>-dirty+<hash of the diff>``.

    The diff hash tells two different sets of uncommitted changes apart, so the cache never
    serves a run of other code. Outside a git checkout: ``<version>+code.<fingerprint>``.
    """
    commit = git_commit()
    if commit == "unknown":
        import sys

        from slamreplay.replay.tools.codeprint import code_fingerprint
        mods = [m for m in sys.modules if m.split(".")[0] in ("replay", "algorithms", "recorder")]
        return f"{version()}+code.{code_fingerprint(mods)}"
    if not commit.endswith("-dirty"):
        return commit
    try:
        diff = subprocess.run(["git", "diff", "HEAD", "--binary"], cwd=SOURCE_ROOT, capture_output=True,
                              timeout=30, check=True).stdout
    except (OSError, subprocess.SubprocessError):
        diff = b""
    return f"{commit}+{hashlib.sha256(diff).hexdigest()[:12]}"


# ---------------------------------------------------------------------------------------
# Recordings


def _simulate(spec: RecordingSpec, seed: int, out: Path) -> None:
    cls = sim_config_class(spec.sim or "")
    config = cls(**sim_kwargs(spec.sim or "", spec.args))
    if spec.sim == "sim-landmarks":
        from slamreplay.recorder.sim.landmarks import simulate_landmarks
        simulate_landmarks(out, config, seed=seed)
    elif spec.sim == "sim-seabed":
        from slamreplay.recorder.sim.seabed import simulate_seabed
        simulate_seabed(out, config, seed=seed)
    else:
        from slamreplay.recorder.sim.corridor import simulate_corridor
        simulate_corridor(out, config, seed=seed)


def sim_recording(spec: RecordingSpec, seed: int, cache: Path) -> Path:
    """The recording of ``spec`` at ``seed``, simulated once and cached by its inputs and code."""
    from slamreplay.replay.tools.codeprint import code_fingerprint

    sim = spec.sim or ""
    key = hashlib.sha256(canonical({"sim": sim, "args": sim_kwargs(sim, spec.args), "seed": seed,
                                    "code": code_fingerprint([*SIM_MODULES[sim], *WRITER_MODULES])}).encode())
    out = cache / "recordings" / f"{sim}-s{seed}-{key.hexdigest()[:16]}.mcap"
    if out.is_file():
        return out
    out.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(dir=out.parent, prefix=".sim-") as tmp:
        part = Path(tmp) / out.name
        try:
            _simulate(spec, seed, part)
        except (ValueError, TypeError) as err:
            raise ReplayError(f"recording {spec.name}: {sim} failed: {err}") from err
        os.replace(part, out)
    return out


def url_recording(spec: RecordingSpec, cache: Path) -> Path:
    """A local copy of ``spec.url``, fetched once per (url, the store's checksum of the object)."""
    try:
        import fsspec  # type: ignore[import-untyped]
    except ImportError:
        raise ReplayError(f"recording {spec.name}: url recordings need fsspec (pip install fsspec)") from None
    url = spec.url or ""
    try:
        fs, path = fsspec.core.url_to_fs(url)
        stamp = str(fs.checksum(path))
    except (ValueError, OSError, ImportError) as err:
        raise ReplayError(f"recording {spec.name}: cannot open {url}: {err}") from None
    suffix = Path(path).suffix or ".mcap"
    out = cache / "downloads" / (hashlib.sha256(f"{url}\n{stamp}".encode()).hexdigest()[:24] + suffix)
    if out.is_file():
        return out
    out.parent.mkdir(parents=True, exist_ok=True)
    try:
        with replacing(out) as part, fs.open(path, "rb") as src, open(part, "wb") as dst:
            shutil.copyfileobj(src, dst, 1 << 20)
    except OSError as err:
        raise ReplayError(f"recording {spec.name}: cannot fetch {url}: {err}") from None
    return out


@dataclass(frozen=True, slots=True)
class Recording:
    path: Path
    sha256: str
    topic_map: dict[str, str]


def materialize(suite: Suite, cache: Path) -> dict[tuple[str, int | None], Recording]:
    """(recording name, recording seed) -> a local file and its sha256, for every recording of the suite."""
    out: dict[tuple[str, int | None], Recording] = {}
    for spec in suite.recordings.values():
        if spec.sim:
            for seed in spec.seeds:
                p = sim_recording(spec, seed, cache)
                out[(spec.name, seed)] = Recording(p, sha256_file(p), spec.topic_map)
        else:
            p = spec.path if spec.path is not None else url_recording(spec, cache)
            if not p.exists():
                raise ReplayError(f"recording {spec.name}: {p} does not exist")
            sha = sha256_file(p) if p.is_file() else hashlib.sha256(str(p.resolve()).encode()).hexdigest()
            out[(spec.name, None)] = Recording(p, sha, spec.topic_map)
    return out


# ---------------------------------------------------------------------------------------
# Cells, cache, rows


@dataclass(frozen=True, slots=True)
class CellJob:
    """A cell with everything needed to run it: where its recording is, where its run goes."""

    cell: Cell
    recording: Recording
    run_dir: Path
    key: str


def cell_key(cell: Cell, recording: Recording, code: str) -> str:
    """sha256 of the cell's inputs (see the module docstring)."""
    doc = {"recording_sha256": recording.sha256, "pipeline": cell.pipeline, "config": cell.config,
           "seed": cell.seed, "topic_map": recording.topic_map, "code_version": code}
    program = _external_program(cell.pipeline)
    if program:  # an external pipeline (docs/external.md): its program is an input too (a rebuild is a new run)
        doc["program"] = program
    return hashlib.sha256(canonical(doc).encode()).hexdigest()


def _external_program(pipeline: str) -> dict[str, Any]:
    """An external pipeline's identity (``determinism.PROGRAM_FIELDS``); {} for any other pipeline."""
    from slamreplay.replay.engine.declared import DeclaredPlugin
    from slamreplay.replay.engine.pipeline import pipeline_origin, pipeline_plugins

    if not isinstance(pipeline_plugins().get(pipeline), DeclaredPlugin):
        return {}
    try:
        origin = pipeline_origin(pipeline)
    except (KeyError, ReplayError):
        return {}
    return {k: origin.get(k) for k in PROGRAM_FIELDS}  # what makes a program that program, said once


def plan(suite: Suite, recordings: dict[tuple[str, int | None], Recording], out: Path, code: str
         ) -> tuple[list[CellJob], set[str]]:
    """Every cell of ``suite`` as a job in results directory ``out``, and the keys served from cache."""
    jobs, cached = [], set()
    for cell in suite.cells():
        rec = recordings[(cell.recording, cell.recording_seed)]
        key = cell_key(cell, rec, code)
        job = CellJob(cell, rec, out / "runs" / f"{cell.label}-{key[:12]}", key)
        jobs.append(job)
        if is_cached(job):
            cached.add(key)
    return jobs, cached


def is_cached(job: CellJob) -> bool:
    """A finished, succeeded run made for this key is in the job's run directory."""
    try:
        manifest = json.loads((job.run_dir / "manifest.json").read_text())
        stamp = json.loads((job.run_dir / "cell.json").read_text())
    except (OSError, json.JSONDecodeError):
        return False
    return (manifest.get("status") == "succeeded" and stamp.get("key") == job.key
            and (job.run_dir / "metrics.json").is_file())


def clear_run_dir(job: CellJob) -> None:
    """Remove what a failed or interrupted earlier attempt left, so the run can start afresh."""
    if job.run_dir.exists():
        shutil.rmtree(job.run_dir)
    job.run_dir.parent.mkdir(parents=True, exist_ok=True)


def stamp_run(job: CellJob) -> None:
    """Mark the run directory with the key it was made for (after the run finished)."""
    if job.run_dir.is_dir():
        atomic_write(job.run_dir / "cell.json", canonical({"key": job.key, "cell": job.cell.to_json()}) + "\n")


def row(job: CellJob, code: str, error: str | None = None, cached: bool = False) -> dict[str, Any]:
    """The results.jsonl row of a cell, from its run directory (or from ``error`` without one)."""
    out: dict[str, Any] = {**job.cell.to_json(), "key": job.key, "run_dir": str(job.run_dir),
                           "recording_path": str(job.recording.path), "recording_sha256": job.recording.sha256,
                           "code_version": code, "cached": cached, "status": "failed", "error": error,
                           "config_hash": None, "metrics": {}, "better": {}, "tolerance": {}, "units": {},
                           "wall_s": None, "peak_rss_mib": None, "git_commit": None}
    try:
        manifest = json.loads((job.run_dir / "manifest.json").read_text())
    except (OSError, json.JSONDecodeError):
        out["error"] = error or "the run left no manifest"
        return out
    timings = manifest.get("timings", {})
    out.update(status=manifest.get("status", "failed"), error=manifest.get("error") or error,
               config_hash=manifest.get("config_hash"), wall_s=timings.get("wall_s"),
               peak_rss_mib=timings.get("max_rss_mib"), git_commit=manifest.get("slamreplay", {}).get("git_commit"))
    if (deterministic := determinism_of(manifest)) is not None:  # checked: an external program (external.md)
        out["deterministic"] = deterministic
    if out["status"] == "succeeded":
        try:
            metrics = json.loads((job.run_dir / "metrics.json").read_text())["metrics"]
        except (OSError, json.JSONDecodeError, KeyError) as err:
            out.update(status="failed", error=f"unreadable metrics.json: {err}")
            return out
        add_metrics(out, metrics)
    return out


ROW_METRIC_KEYS = ("metrics", "better", "tolerance", "rel_tolerance", "units", "targets", "optional")


def add_metrics(row: dict[str, Any], metrics: dict[str, Any]) -> None:
    """Copy a metrics.json ``metrics`` mapping into a results row: values, directions (and targets), tolerances,
    units; under the current names (``metric_registry.normalize``)."""
    for key in ROW_METRIC_KEYS:
        row.setdefault(key, {})
    for name, m in sorted(normalize(metrics).items()):
        row["metrics"][name] = m["value"]
        row["better"][name] = m.get("better", "none")
        row["tolerance"][name] = m.get("tolerance", 0.0)
        row["rel_tolerance"][name] = m.get("rel_tolerance", 0.0)
        row["units"][name] = m.get("unit", "")
        if m.get("target") is not None:
            row["targets"][name] = m["target"]
        if m.get("optional"):
            row["optional"][name] = m["optional"]


def normalized_row(row: dict[str, Any]) -> dict[str, Any]:
    """A results row of any version with its metrics under the current names and directions."""
    values = row.get("metrics") or {}
    entries = {name: {"value": v, "better": row.get("better", {}).get(name, "none"),
                      "tolerance": row.get("tolerance", {}).get(name, 0.0),
                      "rel_tolerance": row.get("rel_tolerance", {}).get(name, 0.0),
                      "unit": row.get("units", {}).get(name, ""),
                      **({"target": row["targets"][name]} if name in row.get("targets", {}) else {}),
                      **({"optional": row["optional"][name]} if name in row.get("optional", {}) else {})}
               for name, v in values.items()}
    out = {k: v for k, v in row.items() if k not in ROW_METRIC_KEYS}
    add_metrics(out, entries)
    return out


def write_results(out: Path, rows: Iterable[dict[str, Any]]) -> None:
    """results.jsonl, whole or not at all."""
    text = "".join(json.dumps(r, sort_keys=True, default=str) + "\n" for r in rows)
    atomic_write(out / "results.jsonl", text)


def read_results(out: Path) -> list[dict[str, Any]]:
    """The rows of a results directory; ReplayError when it has none or they are unreadable."""
    path = out / "results.jsonl"
    try:
        lines = path.read_text().splitlines()
    except FileNotFoundError:
        raise ReplayError(f"{out} has no results.jsonl: it is not a suite results directory "
                          f"(make one with `slamreplay suite run SUITE.toml --out {out}`)") from None
    rows = []
    for i, line in enumerate(lines, 1):
        try:
            rows.append(normalized_row(json.loads(line)))
        except json.JSONDecodeError as err:
            raise ReplayError(f"{path}:{i}: not a JSON row: {err}") from None
    return rows


RunCell = Callable[[CellJob], str | None]  # runs one cell into job.run_dir; an error message or None


def run_suite(suite: Suite, out: Path, code: str, run_cells: Callable[[list[CellJob]], Iterable[tuple[CellJob,
              str | None]]], *, cache: Path | None = None, rev: str | None = None,
              progress: Callable[[int, int], None] | None = None) -> list[dict[str, Any]]:
    """Run every cell of ``suite`` not cached in ``out``; the rows of results.jsonl (also written).

    ``run_cells(jobs)`` runs the jobs (serially, in a process pool, on Ray, in another
    revision's environment) and yields ``(job, error or None)`` as each one ends, in any order.
    """
    if out.exists() and not out.is_dir():
        raise ReplayError(f"--out {out} is a file: give a results directory (new, or one a suite wrote)")
    if out.is_dir() and any(out.iterdir()) and not (out / "suite.json").is_file():
        raise ReplayError(f"--out {out} holds other files: give a new directory or one a suite wrote")
    out.mkdir(parents=True, exist_ok=True)
    recordings = materialize(suite, cache or cache_dir())
    jobs, cached = plan(suite, recordings, out, code)
    todo = [j for j in jobs if j.key not in cached]
    about = {"format": RESULTS_FORMAT, "suite": str(suite.path), "suite_name": suite.name,
             "suite_sha256": suite.sha256, "code_version": code, "rev": rev, "cells": len(jobs)}

    def write_about(finished: bool) -> None:
        atomic_write(out / "suite.json", json.dumps(about | {"finished": finished}, indent=2, sort_keys=True) + "\n")

    write_about(False)
    by_key = {j.key: row(j, code, cached=True) for j in jobs if j.key in cached}
    order = [j.key for j in jobs]
    total, done = len(order), len(cached)
    if progress:
        progress(done, total)
    for job in todo:
        clear_run_dir(job)
    write_results(out, [by_key[k] for k in order if k in by_key])
    for job, error in run_cells(todo):
        stamp_run(job)
        by_key[job.key] = row(job, code, error)
        done += 1
        write_results(out, [by_key[k] for k in order if k in by_key])
        if progress:
            progress(done, total)
    rows = [by_key[k] for k in order]
    write_results(out, rows)
    write_about(True)  # last: until here, compare refuses this directory as unfinished
    return rows


def unfinished(out: Path) -> str | None:
    """Why the results directory ``out`` is not a finished suite run (None: it is, or it is no suite's).

    ``suite.json`` says ``finished: false`` from the start of ``suite run`` until its last row is
    written, so a run that is still going, or was killed, is never read as a whole suite.
    """
    try:
        about = json.loads((out / "suite.json").read_text())
    except (OSError, json.JSONDecodeError):
        return None
    if not isinstance(about, dict):
        return None
    try:
        rows = len((out / "results.jsonl").read_text().splitlines())
    except OSError:
        rows = 0
    cells = about.get("cells")
    if about.get("finished") is False or (isinstance(cells, int) and rows < cells):
        return (f"{out} is an unfinished suite run ({rows} of {cells} cells have results): it is running now or "
                f"was stopped; finish it with `slamreplay suite run {about.get('suite', 'SUITE.toml')} --out {out}` "
                f"(finished cells are reused)")
    return None
