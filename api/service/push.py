"""Runs made elsewhere: ``POST /runs`` takes a run directory (a tar, gzipped or not) that CI, a laptop's
``suite run``, ``evaluate`` or an external program made, checks it, and lists it beside the server's own runs.

What is checked, before anything is kept (each refusal is one line, 422, and stores nothing):

- the archive: only regular files and folders, relative names of letters, digits and ``_ . + -`` (none starting with
  a dot), at most `MAX_DEPTH` deep and `MAX_FILES` files, at most ``SLAMREPLAY_MAX_UPLOAD_BYTES`` unpacked;
- ``manifest.json`` (at most `MAX_JSON_BYTES`): a run's manifest of a format this server reads (``format`` 1), with
  its pipeline, seed, status (``succeeded`` or ``failed``), config and the recording's sha256; every artifact it
  lists is there with the size and sha256 it says (a run that lies about its files is refused);
- ``metrics.json`` of a succeeded run: ``{"metrics": {NAME: {"value": number or null, ...}}}``;
- the recording: the server must hold the file whose sha256 the manifest names (upload it first; ``slamreplay
  push`` does, from the path the manifest records or ``--recording``), so that a pushed run and the server's own
  runs of the same recording are compared as runs of one recording.

A run is kept as a job that ended as its manifest says (its times, metrics and the code's commit from the
manifest), made by whoever pushed it, with its ``source``: who pushed it, from which address, the ``origin`` the
client named (a host, a CI job) and the run's own id. Pushing the same run (its manifest's ``run_id``) again answers
with the job it became.
"""

from __future__ import annotations

import json
import math
import re
import shutil
import tarfile
import time
import uuid
import zlib
from collections.abc import AsyncIterator
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path, PurePosixPath
from typing import Any

from slamreplay.api.service.errors import NotFoundError, TooLargeError
from slamreplay.api.service.store import JobRow, Store
from slamreplay.api.service.store_runs import Labels
from slamreplay.replay.errors import ReplayError
from slamreplay.replay.runs.run import ARTIFACT_NAME, sha256_file

MAX_FILES = 2000
MAX_DEPTH = 4
MAX_JSON_BYTES = 16 << 20
PART_RE = re.compile(r"[A-Za-z0-9_+-][A-Za-z0-9_.+-]{0,127}")  # an artifact name (ARTIFACT_NAME) fits
PIPELINE_RE = re.compile(r"[A-Za-z0-9_.:-]{1,100}")
METRIC_RE = re.compile(r"[A-Za-z_][A-Za-z0-9_]{0,99}")
SHA256_RE = re.compile(r"[0-9a-f]{64}")
ENDED = ("succeeded", "failed")


class PushError(ReplayError):
    """A pushed run this server does not take: one line saying what is wrong (a 422)."""


@dataclass(frozen=True, slots=True)
class PushedRun:
    """What a checked run directory says of itself."""

    manifest: dict[str, Any]
    metrics: dict[str, float | None]
    folder: Path  # the unpacked run directory (a temporary folder beside the runs)

    @property
    def recording_sha256(self) -> str:
        return str(self.manifest["recording"]["sha256"])

    @property
    def run_id(self) -> str:
        return str(self.manifest.get("run_id") or "")


async def spool(chunks: AsyncIterator[bytes], into: Path, limit: int) -> int:
    """Write a request body to ``into``; TooLargeError past ``limit`` bytes."""
    size = 0
    with open(into, "xb") as f:
        async for chunk in chunks:
            size += len(chunk)
            if size > limit:
                raise TooLargeError(f"a pushed run is at most {limit} bytes (SLAMREPLAY_MAX_UPLOAD_BYTES)")
            f.write(chunk)
    return size


def _member_path(name: str) -> PurePosixPath:
    path = PurePosixPath(name)
    parts = [p for p in path.parts if p != "."]
    if path.is_absolute() or not parts or len(parts) > MAX_DEPTH or any(not PART_RE.fullmatch(p) for p in parts):
        raise PushError(f"the archive holds {name[:120]!r}: a run's files have relative names of letters, digits "
                        f"and _ . + - (none starting with a dot), at most {MAX_DEPTH} folders deep")
    return PurePosixPath(*parts)


def unpack(archive: Path, into: Path, limit: int) -> None:
    """Unpack a run's tar into the new folder ``into``, refusing links, devices, odd names and more than ``limit``
    bytes; the archive may hold the run directory itself or its files (one top folder is taken off)."""
    try:
        tar = tarfile.open(archive, mode="r:*")  # noqa: SIM115 -- closed by the with below
    except (tarfile.TarError, OSError, EOFError) as err:
        raise PushError(f"the pushed body is not a tar archive of a run directory ({err}): send "
                        "`tar -czf - -C RUN_DIR .` or use `slamreplay push`") from None
    members: list[tuple[PurePosixPath, tarfile.TarInfo]] = []
    total = 0
    with tar:
        try:
            for m in tar:
                if len(members) >= MAX_FILES:
                    raise PushError(f"the archive holds more than {MAX_FILES} files: a run directory has far fewer")
                if not (m.isfile() or m.isdir()):
                    raise PushError(f"the archive holds {m.name[:120]!r}, which is not a file or a folder (links and "
                                    "devices are not taken)")
                if m.name.strip("/.") == "":
                    continue
                total += m.size if m.isfile() else 0
                if total > limit:
                    raise TooLargeError(f"the pushed run unpacks to more than {limit} bytes "
                                        "(SLAMREPLAY_MAX_UPLOAD_BYTES)")
                members.append((_member_path(m.name), m))
            tops = {p.parts[0] for p, _ in members}
            strip = len(tops) == 1 and not any(len(p.parts) == 1 and m.isfile() for p, m in members)
            into.mkdir()
            for path, m in members:
                rel = PurePosixPath(*path.parts[1:]) if strip else path
                if not rel.parts:
                    continue
                target = into.joinpath(*rel.parts)
                if m.isdir():
                    target.mkdir(parents=True, exist_ok=True)
                    continue
                target.parent.mkdir(parents=True, exist_ok=True)
                src = tar.extractfile(m)
                if src is None:
                    raise PushError(f"cannot read {m.name[:120]!r} in the archive")
                with src, open(target, "xb") as out:
                    shutil.copyfileobj(src, out, 1 << 20)
        except (tarfile.TarError, EOFError, zlib.error) as err:
            raise PushError(f"the archive is damaged ({type(err).__name__}: {err}): make it again") from None
        except FileExistsError as err:
            raise PushError(f"the archive holds {Path(err.filename or '?').name!r} twice") from None


def _json(folder: Path, name: str) -> Any:
    path = folder / name
    if not path.is_file():
        raise PushError(f"the run has no {name}: push a run directory as `slamreplay run` (or `suite run`, "
                        "`evaluate`) made it")
    if path.stat().st_size > MAX_JSON_BYTES:
        raise PushError(f"{name} is {path.stat().st_size:,} bytes: at most {MAX_JSON_BYTES:,}")
    try:
        return json.loads(path.read_bytes(), parse_constant=lambda c: None)
    except (ValueError, UnicodeDecodeError) as err:
        raise PushError(f"{name} is not JSON: {err}") from None


def check_run(folder: Path) -> PushedRun:
    """The run in ``folder`` as checked (see the module docstring); PushError says the first thing wrong."""
    m = _json(folder, "manifest.json")
    if not isinstance(m, dict):
        raise PushError("manifest.json is not a JSON object")
    if m.get("format") != 1:
        raise PushError(f"manifest.json has format {m.get('format')!r}: this server reads format 1 (a newer "
                        "slamreplay made it: update the server)")
    pipeline, seed, status = m.get("pipeline"), m.get("seed"), m.get("status")
    if not isinstance(pipeline, str) or not PIPELINE_RE.fullmatch(pipeline):
        raise PushError(f"manifest.json: pipeline {str(pipeline)[:100]!r} is not a pipeline name")
    if isinstance(seed, bool) or not isinstance(seed, int) or not 0 <= seed < 2**63:
        raise PushError(f"manifest.json: seed {seed!r} is not a whole number from 0 to 2^63-1")
    if status not in ENDED:
        raise PushError(f"manifest.json: status {status!r}: only ended runs are pushed ({' or '.join(ENDED)})")
    if not isinstance(m.get("config", {}), dict):
        raise PushError("manifest.json: config is not an object")
    rec = m.get("recording")
    if not isinstance(rec, dict) or not isinstance(rec.get("sha256"), str) or not SHA256_RE.fullmatch(rec["sha256"]):
        raise PushError("manifest.json: recording.sha256 is missing: the run must name the recording it replayed")
    artifacts = m.get("artifacts") or {}
    if not isinstance(artifacts, dict):
        raise PushError("manifest.json: artifacts is not an object")
    for name, info in artifacts.items():
        path = folder / name
        if not isinstance(info, dict) or not ARTIFACT_NAME.fullmatch(str(name)):
            raise PushError(f"manifest.json: artifact {str(name)[:100]!r} is not described as a file")
        if not path.is_file():
            raise PushError(f"manifest.json lists the artifact {name} but the run has no such file")
        if info.get("bytes") is not None and path.stat().st_size != info["bytes"]:
            raise PushError(f"{name} is {path.stat().st_size:,} bytes but the manifest says {info['bytes']:,}")
        if info.get("sha256") is not None and sha256_file(path) != info["sha256"]:
            raise PushError(f"{name} is not the file the manifest describes (its sha256 differs)")
    metrics: dict[str, float | None] = {}
    if status == "succeeded":
        doc = _json(folder, "metrics.json")
        values = doc.get("metrics") if isinstance(doc, dict) else None
        if not isinstance(values, dict):
            raise PushError('metrics.json has no "metrics" object')
        for name, v in values.items():
            if not METRIC_RE.fullmatch(str(name)) or not isinstance(v, dict):
                raise PushError(f"metrics.json: {str(name)[:100]!r} is not a metric (NAME: {{\"value\": ...}})")
            value = v.get("value")
            if value is not None and (isinstance(value, bool) or not isinstance(value, int | float)):
                raise PushError(f"metrics.json: {name} has the value {str(value)[:40]!r}, not a number")
            metrics[name] = None if value is None or not math.isfinite(value) else float(value)
    return PushedRun(m, metrics, folder)


def _time(text: Any) -> float | None:
    try:
        return datetime.fromisoformat(str(text)).timestamp()
    except ValueError:
        return None


def keep(store: Store, runs_dir: Path, run: PushedRun, who: str, address: str, origin: str | None,
         labels: Labels) -> tuple[JobRow, bool]:
    """Keep a checked run as a job (its folder moved to the job's run directory): (the job, whether it is new)."""
    from slamreplay.replay.metric_registry import normalize

    if store.get_recording(run.recording_sha256) is None:
        rec = run.manifest["recording"]
        name = Path(str(rec.get("path") or "")).name or run.recording_sha256[:8]
        raise NotFoundError(f"the run replayed recording {run.recording_sha256[:12]}... ({name}), which this server "
                            "does not hold: upload it first (POST /recordings; `slamreplay push --recording FILE` "
                            "does it for you)")
    if run.run_id:
        known = store.pushed_job(run.run_id)
        if known is not None:
            shutil.rmtree(run.folder, ignore_errors=True)
            return known, False
    m = run.manifest
    timings = m.get("timings") if isinstance(m.get("timings"), dict) else {}
    commit = (m.get("slamreplay") or {}).get("git_commit") if isinstance(m.get("slamreplay"), dict) else None
    host = m.get("host") if isinstance(m.get("host"), dict) else {}
    source = {"pushed_by": who, "address": address, "origin": origin, "run_id": run.run_id or None,
              "pushed_at": time.time(), "platform": host.get("platform"),
              "slamreplay": (m.get("slamreplay") or {}).get("version") if isinstance(m.get("slamreplay"), dict)
              else None}
    job_id = uuid.uuid4().hex
    target = runs_dir / job_id
    run.folder.rename(target)
    metrics = normalize({k: v for k, v in run.metrics.items() if v is not None})
    try:
        job = store.add_pushed_job(job_id, run.recording_sha256, str(m["pipeline"]), dict(m.get("config") or {}),
                                   int(m["seed"]), str(m["status"]), m.get("error") if m["status"] == "failed" else
                                   None, _time(timings.get("started_at")), _time(timings.get("finished_at")),
                                   metrics, who, source, commit if isinstance(commit, str) else None, labels)
    except BaseException:
        shutil.rmtree(target, ignore_errors=True)
        raise
    return job, True
