"""Recordings: streamed uploads, content addressing, validation, recovery of damaged uploads.

An upload is written in chunks to a temporary file beside the store while its sha256 is
computed, so it is never whole in memory; the size limit is enforced as it arrives. It is
accepted only when ``RecordingReader`` can open it, and then stored as
``recordings/<sha256>.mcap``: the same file twice is one recording. An upload that starts
like an MCAP but cannot be read (truncated, corrupt index) is kept in
``recordings/damaged/<sha256>.mcap`` and the answer offers ``POST /recordings/{id}/recover``,
which salvages its readable messages into a new, valid recording. File names from users
are only labels: every path is built from a hex digest.
"""

from __future__ import annotations

import hashlib
import os
import re
import shutil
import time
import uuid
from collections.abc import AsyncIterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from starlette.concurrency import run_in_threadpool

from slamreplay.api.service.errors import (
    ConflictError,
    NotFoundError,
    NotMcapError,
    TooLargeError,
    UnreadableError,
    disk_full_error,
    is_disk_full,
)
from slamreplay.api.service.settings import Settings
from slamreplay.api.service.store import RecordingRow, Store
from slamreplay.recorder.errors import DamageError, RecorderError
from slamreplay.recorder.recover import RecoveryReport, recover
from slamreplay.replay.engine.reader import MCAP_MAGIC, RecordingReader
from slamreplay.replay.errors import ReplayError
from slamreplay.replay.runs.run import sha256_file

_CLI_HINT = re.compile(r"[.;,]? *[Ss]alvage (it|its messages|the readable messages) with `slamreplay recover[^`]*`\.?")
_UNSAFE = re.compile(r"[^A-Za-z0-9._ -]+")


@dataclass(frozen=True, slots=True)
class Stored:
    """An accepted recording; ``created`` False when the same file was stored before."""

    recording: RecordingRow
    created: bool
    report: RecoveryReport | None = None  # when salvaged from a damaged upload ...
    recovered_from: str | None = None  # ... whose sha256 this is


def clean_filename(name: str | None) -> str:
    """A display label from a user's file name: its last component, safe characters only."""
    base = re.split(r"[\\/]", name or "")[-1]
    base = _UNSAFE.sub("_", base).strip(" .")[:200]
    return base or "recording.mcap"


def _not_mcap_hint(head: bytes) -> str:
    """What to do about an upload that does not start like an MCAP, guessed from how it starts."""
    if head[:6] == MCAP_MAGIC[:6]:
        return ("; its line breaks were removed, as `curl -d`/`--data` does: send the file unchanged with "
                "curl --data-binary @run.mcap URL/recordings or curl -F file=@run.mcap URL/recordings")
    if head.startswith(b"--"):
        return ("; it looks like a multipart form sent without its Content-Type: let curl build it, "
                "curl -F file=@run.mcap URL/recordings")
    return ("; upload an .mcap recording, raw (curl --data-binary @run.mcap 'URL/recordings?filename=run.mcap') "
            "or as a form (curl -F file=@run.mcap URL/recordings); ROS 2 bags in MCAP storage: the .mcap inside")


def _topics(reader: RecordingReader) -> list[dict[str, Any]]:
    return [{"topic": t.file_topic, "read_as": t.logical_topic, "schema_name": t.schema_name,
             "encoding": t.message_encoding, "messages": t.message_count} for t in reader.info.topics]


class RecordingService:
    """Upload, list, fetch, delete and recover recordings."""

    def __init__(self, settings: Settings, store: Store) -> None:
        self.settings = settings
        self.store = store

    def sweep(self) -> list[str]:
        """Remove what uploads and recoveries cut off by a server stop left (temporary files no row names);
        the names removed. Called at start-up: a server is the only writer of its data directory."""
        left = [*self.settings.recordings_dir.glob(".upload-*.partial"),
                *self.settings.recordings_dir.glob(".recover-*.mcap")]
        for p in left:
            p.unlink(missing_ok=True)
        made = [p for p in self.settings.recordings_dir.glob(".record-*") if p.is_dir()]  # record routes' folders
        for p in made:
            shutil.rmtree(p, ignore_errors=True)
        return sorted(p.name for p in [*left, *made])

    def path(self, recording_id: str) -> Path:
        return self.settings.recordings_dir / f"{recording_id}.mcap"

    def damaged_path(self, recording_id: str) -> Path:
        return self.settings.recordings_dir / "damaged" / f"{recording_id}.mcap"

    def get(self, recording_id: str) -> RecordingRow:
        rec = self.store.get_recording(recording_id)
        if rec is None:
            raise NotFoundError(f"recording {recording_id} not found")
        return rec

    def file(self, recording_id: str) -> tuple[RecordingRow, Path]:
        rec = self.get(recording_id)
        path = self.path(recording_id)
        if not path.is_file():
            raise NotFoundError(f"recording {recording_id} is registered but its file is missing from the store")
        return rec, path

    def delete(self, recording_id: str) -> None:
        """Delete a recording and its file; ConflictError while a queued or running job uses it."""
        outcome = self.store.delete_recording(recording_id)
        if outcome == "missing":
            raise NotFoundError(f"recording {recording_id} not found")
        if outcome == "busy":
            n = self.store.active_jobs_of(recording_id)
            raise ConflictError(f"recording {recording_id} is used by {n} queued or running job(s); "
                           f"cancel them (DELETE /jobs/{{id}}) or wait for them to finish")
        self.path(recording_id).unlink(missing_ok=True)
        shutil.rmtree(self.settings.recordings_dir / "named" / recording_id, ignore_errors=True)  # JobService's link

    async def upload(self, chunks: AsyncIterator[bytes], filename: str | None, declared_size: int | None,
                     recover_damaged: bool) -> Stored:
        """Store an upload; with ``recover_damaged``, salvage it at once when it is damaged."""
        limit = self.settings.max_upload_bytes
        if declared_size is not None and declared_size > limit:
            raise TooLargeError(f"upload of {declared_size} bytes is over the limit of {limit} bytes "
                           f"(SLAMREPLAY_MAX_UPLOAD_BYTES)")
        label = clean_filename(filename)
        tmp = self.settings.recordings_dir / f".upload-{uuid.uuid4().hex}.partial"
        digest, size = hashlib.sha256(), 0
        try:
            try:
                with open(tmp, "xb") as f:
                    async for chunk in chunks:
                        size += len(chunk)
                        if size > limit:
                            raise TooLargeError(f"upload is over the limit of {limit} bytes "
                                                "(SLAMREPLAY_MAX_UPLOAD_BYTES)")
                        digest.update(chunk)
                        f.write(chunk)
            except OSError as err:
                if is_disk_full(err):
                    raise disk_full_error(f"storing the upload {label} ({size:,} bytes received)") from err
                raise
            return await run_in_threadpool(self._accept, tmp, digest.hexdigest(), size, label, recover_damaged)
        finally:
            tmp.unlink(missing_ok=True)

    def accept_local(self, tmp: Path, sha: str, label: str) -> Stored:
        """Store a file made on the server (``POST /recordings/record/NAME``) as an upload is stored; ``tmp`` is
        moved into the store or removed."""
        try:
            return self._accept(tmp, sha, tmp.stat().st_size, clean_filename(label), False)
        finally:
            tmp.unlink(missing_ok=True)

    def _accept(self, tmp: Path, sha: str, size: int, label: str, recover_damaged: bool) -> Stored:
        known = self.store.get_recording(sha)
        if known is not None and self.path(sha).is_file():
            return Stored(known, False)
        if size == 0:
            raise UnreadableError(f"{label} is empty (0 bytes): nothing to store")
        with open(tmp, "rb") as f:
            head = f.read(len(MCAP_MAGIC))
        if head != MCAP_MAGIC:
            raise NotMcapError(f"{label} is not an MCAP file (it starts with {head!r}){_not_mcap_hint(head)}")
        try:
            reader = RecordingReader(tmp)
        except ReplayError as err:
            reason = _CLI_HINT.sub("", str(err).replace(str(tmp), label)).rstrip(" .;,")
            os.replace(tmp, self.damaged_path(sha))
            if recover_damaged:
                return self.recover(sha)
            raise UnreadableError(f"{reason}. It is kept for recovery: POST /recordings/{sha}/recover stores the "
                             f"messages that can be salvaged as a new recording",
                             recover={"id": sha, "url": f"/recordings/{sha}/recover"}) from err
        row = self._row(reader, sha, size, label)
        os.replace(tmp, self.path(sha))
        return Stored(*self.store.add_recording(row))

    def _row(self, reader: RecordingReader, sha: str, size: int, label: str) -> RecordingRow:
        info = reader.info
        return RecordingRow(sha, label, size, _topics(reader), info.message_count, info.start_ns, info.end_ns,
                            time.time())

    def recover(self, damaged_id: str) -> Stored:
        """Salvage a damaged upload into a new recording (its id is the new file's sha256)."""
        src = self.damaged_path(damaged_id)
        if not src.is_file():
            if self.store.get_recording(damaged_id) is not None:
                raise ConflictError(f"recording {damaged_id} is readable already; there is nothing to recover")
            raise NotFoundError(f"no damaged upload {damaged_id} is waiting for recovery (upload the file first)")
        out = self.settings.recordings_dir / f".recover-{uuid.uuid4().hex}.mcap"
        try:
            try:
                report = recover(src, out)
            except DamageError as err:  # not one readable message in it
                src.unlink(missing_ok=True)
                raise UnreadableError(f"nothing could be salvaged from {damaged_id}: "
                                      f"{str(err).replace(str(src), 'it')}") from err
            except RecorderError as err:
                raise UnreadableError(str(err).replace(str(src), damaged_id)) from err
            sha = sha256_file(out)
            row = self._row(RecordingReader(out), sha, out.stat().st_size, f"recovered-{damaged_id[:12]}.mcap")
            os.replace(out, self.path(sha))
        finally:
            out.unlink(missing_ok=True)
        stored, created = self.store.add_recording(row)
        src.unlink(missing_ok=True)
        return Stored(stored, created, report, damaged_id)
