"""``/recordings/live``: live Foxglove WebSocket streams recorded on the server (``slamreplay record live`` there).

Not one of the importers' ``POST /recordings/record/NAME`` routes (api/service/record_routes.py): those run a source
to its end within the request and answer with the file, the same options always making the same recording. A live
stream runs until told, so it is a task: ``POST /recordings/live`` starts it (answering once it records, or with
the one-line reason it cannot), ``GET /recordings/live`` and ``/recordings/live/ID`` show it while it grows
(messages and rate per topic, bytes, gaps, the lines it said), ``POST /recordings/live/ID/stop`` ends it, and
its file is then stored like any upload (id: the sha256) and named in ``recording``. It also ends by itself at
``duration_s``. The server makes the connection, to a URL a client chose: off unless the operator sets
``SLAMREPLAY_ALLOW_LIVE_RECORDING=true`` (403 otherwise).

Each recording runs in a thread of its own (network and file I/O; never the event loop) and writes into
``recordings/.live-ID/``; a server stopped cleanly stops its recordings first and stores them. A server that is
killed leaves ``recordings/.live-ID/live.mcap.partial``: when it starts again, each such folder is salvaged
(:func:`slamreplay.recorder.importers.live_salvage.salvage_live`: every message flushed, at most a second before
the kill) and stored like an upload, or listed as failed with the reason; either way listed, as ended.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import shutil
import threading
import time
import uuid
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, Literal

from fastapi import APIRouter, Depends, FastAPI, Request
from pydantic import BaseModel, ConfigDict, Field
from starlette.concurrency import run_in_threadpool

from slamreplay.api.service.auth import record as audit_record
from slamreplay.api.service.deps import ERRORS, RecordingsDep, SettingsDep, require_token
from slamreplay.api.service.errors import ApiError, ForbiddenError, NotFoundError
from slamreplay.api.service.models import RecordingOut
from slamreplay.recorder.errors import RecorderError

MAX_DURATION_S = 7 * 24 * 3600.0
START_TIMEOUT_S = 30.0  # connecting and the first advertise (wait_s) take less
STOP_TIMEOUT_S = 60.0  # the last chunk, the summary and storing the file take less
LINES_KEPT = 50
FOLDER_PREFIX = ".live-"
TASK_FILE = "task.json"  # the url and start of the recording in its folder, for a salvage after a kill

State = Literal["connecting", "recording", "stopping", "done", "failed"]


class LiveIn(BaseModel):
    model_config = ConfigDict(extra="forbid")

    url: str = Field(description="the Foxglove WebSocket server, e.g. ws://robot.local:8765", min_length=1,
                     max_length=2000)
    topics: list[str] = Field(default=[], max_length=200, description=(
        "channels to record: names, globs (/robot/*) or re:REGEX; empty: every channel slamreplay can read"))
    topic_map: dict[str, str] = Field(default={}, description="channel -> logical topic, e.g. "
                                                              '{"/robot/pose": "/ground_truth/pose"}')
    duration_s: float | None = Field(default=None, gt=0, le=MAX_DURATION_S,
                                     description="seconds to record (default: until POST .../stop)")
    base_frame: str = Field(default="base_link", min_length=1, max_length=200, description=(
        "ROS 2: the robot's tf frame (laser scans are moved into it; /tf gives its pose)"))
    odom_frame: str = Field(default="odom", min_length=1, max_length=200, description=(
        "ROS 2: without an odometry channel, odometry is base_frame in this frame, composed through /tf"))
    ground_truth_frame: str | None = Field(default=None, min_length=1, max_length=200, description=(
        "ROS 2: ground truth is base_frame in this frame (e.g. map), composed through /tf"))


class LiveTopicOut(BaseModel):
    topic: str = Field(description="the server's channel")
    maps_to: str = Field(description="the logical topic it is recorded as")
    messages: int
    rate_hz: float
    bad: int = Field(description="messages that did not decode (skipped)")
    stopped: bool = Field(description="silent for 5 of its periods while connected, or unadvertised")


class LiveOut(BaseModel):
    id: str
    url: str
    state: State
    started_at: datetime
    elapsed_s: float
    connected: bool
    messages: int
    bytes: int = Field(description="size of the file so far")
    gaps: int = Field(description="times the connection dropped and came back, each written into the recording")
    topics: list[LiveTopicOut]
    lines: list[str] = Field(description="what it said (channels, skips, losses, gaps), the last 50")
    error: str | None = None
    end_reason: str | None = None
    recording: RecordingOut | None = Field(default=None, description="the stored recording, once done")
    links: dict[str, str]


@dataclass(eq=False)
class LiveTask:
    """One live recording on the server: its thread, the recorder, what it said, how it ended."""

    id: str
    url: str
    folder: Path
    live: Any  # LiveRecording
    started_at: datetime = field(default_factory=lambda: datetime.now(timezone.utc))
    lines: list[str] = field(default_factory=list)
    state: State = "connecting"
    error: str | None = None
    end_reason: str | None = None
    stored: Any = None  # RecordingRow
    thread: threading.Thread | None = None

    def say(self, line: str) -> None:
        self.lines.append(line)
        del self.lines[:-LINES_KEPT]
        if line.startswith("recording ") and self.state == "connecting":
            self.state = "recording"

    def out(self) -> LiveOut:
        if self.live is None:  # salvaged at start-up: what was stored is what it recorded
            from slamreplay.recorder.importers.foxglove_live import LiveStatus

            n = self.stored.message_count if self.stored is not None else 0
            s = LiveStatus(0.0, False, (), n, self.stored.size if self.stored is not None else 0, 0)
        else:
            s = self.live.status()
        return LiveOut(id=self.id, url=self.url, state=self.state, started_at=self.started_at, elapsed_s=s.elapsed_s,
                       connected=s.connected, messages=s.messages, bytes=s.bytes_on_disk, gaps=s.gaps,
                       topics=[LiveTopicOut(topic=c.topic, maps_to=c.maps_to, messages=c.written, rate_hz=c.rate_hz,
                                            bad=c.bad, stopped=c.stopped) for c in s.topics],
                       lines=list(self.lines), error=self.error, end_reason=self.end_reason,
                       recording=RecordingOut.of(self.stored) if self.stored is not None else None,
                       links={"self": f"/recordings/live/{self.id}", "stop": f"/recordings/live/{self.id}/stop"})


class LiveRegistry:
    """The server's live recordings, by id (running and ended ones, until the server stops)."""

    def __init__(self) -> None:
        self.tasks: dict[str, LiveTask] = {}
        self.lock = threading.Lock()

    def start(self, body: LiveIn, recordings: Any) -> LiveTask:
        """Start a recording; once it records, the task; RecorderError (422) with its reason when it cannot."""
        from slamreplay.recorder.importers.foxglove_live import LiveOptions, LiveRecording
        from slamreplay.recorder.importers.foxglove_ws import check_url

        check_url(body.url)
        task_id = uuid.uuid4().hex[:12]
        folder = recordings.settings.recordings_dir / f"{FOLDER_PREFIX}{task_id}"
        folder.mkdir()
        options = LiveOptions(url=body.url, out=folder / "live.mcap", topics=tuple(body.topics),
                              topic_map=dict(body.topic_map), duration_s=body.duration_s, base_frame=body.base_frame,
                              odom_frame=body.odom_frame, ground_truth_frame=body.ground_truth_frame)
        task = LiveTask(task_id, body.url, folder, None)
        (folder / TASK_FILE).write_text(json.dumps({"url": body.url, "started_at": task.started_at.isoformat()}))
        task.live = LiveRecording(options, say=task.say)
        task.thread = threading.Thread(target=self._run, args=(task, recordings), name=f"live-{task_id}", daemon=True)
        with self.lock:
            self.tasks[task_id] = task
        task.thread.start()
        deadline = time.monotonic() + START_TIMEOUT_S
        while task.state == "connecting" and time.monotonic() < deadline:
            time.sleep(0.02)
        if task.state == "failed":
            with self.lock:
                del self.tasks[task_id]
            raise RecorderError(task.error or "the recording failed to start")
        return task

    def _run(self, task: LiveTask, recordings: Any) -> None:
        try:
            summary = task.live.run()
            task.state = "stopping"
            task.end_reason = summary.end_reason
            task.stored = self._store(task, summary.path, recordings)
            task.state = "done"
        except Exception as err:  # noqa: BLE001 -- whatever ends the thread is the task's error, never lost
            task.error = str(err) or type(err).__name__
            task.state = "failed"
        finally:
            if task.state == "done":
                shutil.rmtree(task.folder, ignore_errors=True)

    @staticmethod
    def _store(task: LiveTask, path: Path, recordings: Any) -> Any:
        sha = hashlib.sha256()
        with open(path, "rb") as f:
            while block := f.read(1 << 20):
                sha.update(block)
        staged = recordings.settings.recordings_dir / f".upload-{sha.hexdigest()[:16]}-live-{task.id}.partial"
        shutil.move(path, staged)
        label = f"live-{task.started_at:%Y%m%dT%H%M%SZ}-{task.id}.mcap"
        return recordings.accept_local(staged, sha.hexdigest(), label).recording

    def salvage(self, recordings: Any) -> list[LiveTask]:
        """The live recordings a killed server left (``recordings/.live-ID/``), each salvaged and stored like an
        upload (state ``done``) or ``failed`` with the reason, listed as ended; their folders removed."""
        from slamreplay.recorder.importers.live_salvage import Salvaged, live_leftovers, salvage_live

        found = []
        for folder in live_leftovers(recordings.settings.recordings_dir, FOLDER_PREFIX):
            try:
                meta = json.loads((folder / TASK_FILE).read_text())
            except (OSError, ValueError):  # killed before it wrote it
                meta = {}
            started = datetime.fromtimestamp(folder.stat().st_mtime, timezone.utc)
            with contextlib.suppress(TypeError, ValueError):
                started = datetime.fromisoformat(meta.get("started_at"))
            task = LiveTask(folder.name[len(FOLDER_PREFIX):], str(meta.get("url", "")), folder, None,
                            started_at=started)
            retry = False  # the folder is kept for the next start when salvaging or storing failed, not the file
            try:
                got = salvage_live(folder)
            except Exception as err:  # noqa: BLE001 -- one folder's trouble must not stop the server starting
                got = Salvaged(folder, "failed", reason=f"salvaging it failed: {type(err).__name__}: {err}")
                retry = True
            task.say(got.line())
            task.state = "failed"
            if got.path is None:
                task.error = f"the server stopped while recording; {got.reason}"
            else:
                task.end_reason = ("the server stopped while recording: salvaged at its restart" if got.how ==
                                   "recovered" else "ended before the server stopped: stored at its restart")
                try:
                    task.stored = self._store(task, got.path, recordings)
                    task.state = "done"
                except (RecorderError, ApiError, OSError) as err:
                    task.error = f"the salvaged recording cannot be stored: {err}"
                    retry = True
            if not retry:
                shutil.rmtree(folder, ignore_errors=True)
            with self.lock:
                self.tasks[task.id] = task
            found.append(task)
        return found

    def get(self, task_id: str) -> LiveTask:
        task = self.tasks.get(task_id)
        if task is None:
            raise NotFoundError(f"no live recording {task_id!r} on this server (GET /recordings/live lists them)")
        return task

    def stop(self, task_id: str) -> LiveTask:
        """Stop a recording and wait until its file is stored (or it failed)."""
        task = self.get(task_id)
        if task.live is not None:  # None: salvaged at start-up, ended already
            task.live.stop()
        if task.thread is not None:
            task.thread.join(STOP_TIMEOUT_S)
        return task

    def stop_all(self) -> None:
        for task in list(self.tasks.values()):
            if task.live is not None:
                task.live.stop()
        for task in list(self.tasks.values()):
            if task.thread is not None:
                task.thread.join(STOP_TIMEOUT_S)


def _registry(request: Request) -> LiveRegistry:
    registry: LiveRegistry = request.app.state.live_recordings
    return registry


def install_live_routes(app: FastAPI) -> None:
    """The ``/recordings/live`` routes; live recordings a killed server left salvaged when the server starts, and
    those running stopped (and stored) when it stops."""
    registry = LiveRegistry()
    app.state.live_recordings = registry
    router = APIRouter(dependencies=[Depends(require_token)], responses=ERRORS, tags=["recordings"])

    @router.post("/recordings/live", status_code=201, summary="Record a live robot (Foxglove WebSocket) on the server")
    async def start_live(body: LiveIn, request: Request, recordings: RecordingsDep,
                         settings: SettingsDep) -> LiveOut:
        """Connect to ``url`` and record the chosen channels until ``duration_s`` or ``POST .../stop``; 201 once it
        records (422 with the reason when the server cannot be reached or offers nothing to record)."""
        if not settings.allow_live_recording:
            raise ForbiddenError("this service records live streams only when its operator allows it "
                                 "(SLAMREPLAY_ALLOW_LIVE_RECORDING=true): the server connects to the URL you give")
        task = await run_in_threadpool(registry.start, body, recordings)
        await run_in_threadpool(audit_record, request, "record", task.id, f"live: {body.url}")
        return task.out()

    @router.get("/recordings/live")
    def list_live() -> list[LiveOut]:
        """Live recordings of this server since it started: running ones first, then ended ones, newest first."""
        ended = ("done", "failed")
        tasks = sorted(registry.tasks.values(), key=lambda t: (t.state in ended, -t.started_at.timestamp()))
        return [t.out() for t in tasks]

    @router.get("/recordings/live/{task_id}")
    def get_live(task_id: str) -> LiveOut:
        """One live recording, as it grows."""
        return registry.get(task_id).out()

    @router.post("/recordings/live/{task_id}/stop")
    async def stop_live(task_id: str, request: Request) -> LiveOut:
        """End the recording, store its file like an upload, and answer with it (``recording``)."""
        task = await run_in_threadpool(registry.stop, task_id)
        await run_in_threadpool(audit_record, request, "stop", task.id, f"live: {task.url}")
        return task.out()

    app.include_router(router)
    inner = app.router.lifespan_context

    @asynccontextmanager
    async def lifespan(a: FastAPI) -> AsyncIterator[Any]:
        async with inner(a) as state:  # the data directory is this server's now: what a killed one left is salvaged
            await run_in_threadpool(registry.salvage, a.state.recordings)
            try:
                yield state
            finally:
                await run_in_threadpool(registry.stop_all)

    app.router.lifespan_context = lifespan
