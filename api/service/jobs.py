"""Jobs: validation before queueing, the scheduler threads that feed the executor, cancellation.

One scheduler thread per executor slot claims the oldest queued job from the store, runs it
through the executor (blocking that thread, never the event loop) and records the outcome.
Submitting only inserts a row and wakes the threads, so queued jobs survive a restart: at
start-up, jobs left running by the previous server are re-queued once, then everything
queued runs.

No job runs twice at once: ``Store.claim_next`` hands a queued job to one scheduler thread (one
write transaction), and the only way back from ``running`` to ``queued`` is the re-queue at
start-up, which runs only under the data directory's lock (``slamreplay.api.service.datalock``). That
lock is held by the server and by every local worker it started, so it is free only once none
of the previous server's processes can still be running a job.

With a storage URL (``Settings.storage_url``) tasks name locations there instead of the
data directory: the recording is copied there before its first job, and the run directory
is copied back into ``runs/`` when the job ends, so every route reads local files.
"""

from __future__ import annotations

import json
import logging
import threading
import uuid
from pathlib import Path
from typing import Any

from slamreplay.api.service import storage
from slamreplay.api.service.datalock import DataDirLock
from slamreplay.api.service.errors import ConflictError, NotFoundError
from slamreplay.api.service.executor import Executor, Outcome, Task
from slamreplay.api.service.settings import Settings
from slamreplay.api.service.store import JobRow, Store
from slamreplay.api.service.store_runs import Labels
from slamreplay.replay.engine.pipeline import all_pipelines, get_pipeline, resolve_config
from slamreplay.replay.errors import ReplayError
from slamreplay.replay.metric_registry import normalize
from slamreplay.replay.runs.diff_view import write_comparison_rrd

log = logging.getLogger("slamreplay.jobs")


class JobService:
    """Queue, run and cancel jobs; owns the scheduler threads."""

    def __init__(self, settings: Settings, store: Store, executor: Executor, lock: DataDirLock | None = None) -> None:
        self.settings = settings
        self.store = store
        self.executor = executor
        self.lock = lock if lock is not None else DataDirLock(settings.data_dir)
        self._wake = threading.Condition()
        self._stopping = threading.Event()
        self._threads: list[threading.Thread] = []

    # -- lifecycle -------------------------------------------------------------------------

    def hold_data_dir(self) -> None:
        """Take the data directory's lock (a no-op when this service holds it already).

        Raises ``DataDirInUseError`` naming the server that holds it."""
        self.lock.acquire()

    def start(self) -> None:
        """Take the data directory's lock, re-queue jobs a previous server left running, start the executor
        and the scheduler threads. Raises ``DataDirInUseError`` (before touching any job) when another server holds
        the data directory."""
        self.hold_data_dir()
        share_fd = getattr(self.executor, "share_fd", None)  # local workers hold the lock too (see above)
        if share_fd is not None:
            share_fd(self.lock.fd)
        all_pipelines()  # import them now rather than in the first POST /jobs
        requeued, interrupted = self.store.recover_after_restart()
        if requeued or interrupted:
            log.warning("after a restart: re-queued %d interrupted job(s), gave up on %d", len(requeued),
                        len(interrupted))
        self.executor.start()
        for i in range(self.executor.slots):
            t = threading.Thread(target=self._loop, name=f"slamreplay-scheduler-{i}", daemon=True)
            t.start()
            self._threads.append(t)

    def stop(self) -> None:
        """Stop claiming jobs and stop the workers; running jobs stay ``running`` and are re-queued at start-up."""
        self._stopping.set()
        self.wake()
        self.executor.close()
        for t in self._threads:
            t.join(5.0)
        self.lock.release()

    def wake(self) -> None:
        with self._wake:
            self._wake.notify_all()

    def _loop(self) -> None:
        while not self._stopping.is_set():
            try:
                job = self.store.claim_next()
            except Exception:  # a locked or failing database must not kill the scheduler
                log.exception("could not claim a job")
                job = None
            if job is None:
                with self._wake:
                    self._wake.wait(1.0)
                continue
            try:
                outcome = self.executor.run(self.task_of(job))
            except storage.StorageError as err:
                outcome = Outcome("failed", f"storage: {err}")
            except Exception as err:  # the executor itself failed (e.g. no process could start): fail this job
                log.exception("executor failed on job %s", job.id)
                outcome = Outcome("failed", f"the executor could not run this job: {type(err).__name__}: {err}")
            if outcome.status == "interrupted":
                continue  # left running on purpose: the next start re-queues it
            outcome = self._collect(job.id, outcome)
            self._record_end(job.id, outcome)

    def _record_end(self, job_id: str, outcome: Outcome) -> None:
        """Write how a job ended, retrying (backing off to 5 s) while the database is busy or its disk is full,
        so no job stays ``running`` while the server lives; at a stop it is re-queued at start-up."""
        attempt = 0
        metrics = self.metric_values(job_id) if outcome.status == "succeeded" else None
        commit = self.code_commit(job_id)
        while True:
            try:
                self.store.finish_job(job_id, outcome.status, outcome.error, metrics, commit)
                return
            except Exception:
                attempt += 1
                log.exception("could not record the end of job %s (try %d)", job_id, attempt)
            if self._stopping.wait(min(0.1 * 2 ** attempt, 5.0)):
                return

    def metric_values(self, job_id: str) -> dict[str, float]:
        """{metric: value} from a run's metrics.json under the metrics' current names, copied into the store so
        that the runs table never opens thousands of files; {} when the file is missing or unreadable."""
        try:
            doc = json.loads((self.run_dir(job_id) / "metrics.json").read_text())
            return normalize({k: float(v["value"]) for k, v in doc.get("metrics", {}).items()})
        except (OSError, ValueError, TypeError, KeyError, AttributeError):
            return {}

    def code_commit(self, job_id: str) -> str | None:
        """The commit of the code that made a run, as its manifest records it; None when not known."""
        try:
            sha = json.loads((self.run_dir(job_id) / "manifest.json").read_text())["slamreplay"]["git_commit"]
        except (OSError, ValueError, TypeError, KeyError):
            return None
        return sha if isinstance(sha, str) and 7 <= len(sha) <= 64 else None

    def task_of(self, job: JobRow) -> Task:
        """The task of ``job``; with a storage URL, its recording is copied there first (once)."""
        recording, run_dir = str(self.named_recording(job.recording_id)), str(self.run_dir(job.id))
        base = self.settings.storage_url
        if base is not None:
            remote = storage.join(base, "recordings", f"{job.recording_id}.mcap")
            if not storage.exists(remote):
                storage.put_file(Path(recording), remote)
            recording, run_dir = remote, storage.join(base, "runs", job.id)
        return Task(job.id, recording, job.pipeline, job.config, job.seed, run_dir, str(self.settings.db_path),
                    dict(job.topic_map or {}), job.rev, str(self.rev_cache))

    def _collect(self, job_id: str, outcome: Outcome) -> Outcome:
        """With a storage URL, copy the run directory back into ``runs/`` (what it has, however the job ended)."""
        if self.settings.storage_url is None:
            return outcome
        try:
            storage.get_dir(storage.join(self.settings.storage_url, "runs", job_id), self.run_dir(job_id))
        except storage.StorageError as err:
            log.warning("job %s: could not copy its run back from storage: %s", job_id, err)
            if outcome.status == "succeeded":
                return Outcome("failed", f"the run ended but could not be copied back from storage: {err}")
        return outcome

    # -- locations ---------------------------------------------------------------------------

    def recording_path(self, recording_id: str) -> Path:
        return self.settings.recordings_dir / f"{recording_id}.mcap"

    def named_recording(self, recording_id: str) -> Path:
        """The recording under the name it was uploaded with (a link in ``recordings/named/<id>/``), so that a run's
        log, errors and viewer title say ``sim.mcap`` rather than its sha256; the stored file itself when the
        link cannot be made (no row, or a file system without links)."""
        path = self.recording_path(recording_id)
        rec = self.store.get_recording(recording_id)
        if rec is None:
            return path
        name = Path(rec.filename).name.strip() or "recording.mcap"
        if name in (".", "..") or name.startswith("."):
            name = "recording" + name
        if not name.endswith(".mcap"):
            name += ".mcap"
        link = self.settings.recordings_dir / "named" / recording_id / name
        try:
            if not link.is_symlink():
                link.parent.mkdir(parents=True, exist_ok=True)
                link.symlink_to(Path("..") / ".." / path.name)
        except OSError:
            return path
        return link

    def run_dir(self, job_id: str) -> Path:
        return self.settings.runs_dir / job_id

    @property
    def rev_cache(self) -> Path:
        """Where jobs of other git revisions build them: ``<data dir>/cache/revs/<sha>`` (a worktree and its
        environment, ``slamreplay.replay.runs.revisions``)."""
        return self.settings.data_dir.resolve() / "cache"

    # -- requests ------------------------------------------------------------------------------

    def submit(self, recording_id: str, pipeline: str, config: dict[str, Any], seed: int,
               topic_map: dict[str, str] | None = None, rev: str | None = None, made_by: str | None = None,
               labels: Labels | None = None) -> JobRow:
        """Validate and queue a job.

        ``recording_id``: a whole id or an unambiguous prefix of one; ``topic_map``: file topic -> slamreplay
        topic, applied when the recording is read; ``rev``: the full commit sha whose code runs it (resolved by the
        caller), None for the service's own; ``made_by``: who submits it; ``labels``: its name, tags and note.
        ReplayError (422) names an unknown pipeline or config key, a
        bad topic map, or the topics the pipeline needs that the recording lacks (and the pipelines it fits);
        NotFoundError an unknown recording, ConflictError an ambiguous prefix.
        """
        from slamreplay.api.service.ids import resolve_id
        from slamreplay.api.service.submit_checks import check_fit, parse_topic_map

        pipeline_cls = get_pipeline(pipeline)
        if getattr(pipeline_cls, "declaration", None) is not None and not self.settings.allow_external_pipelines:
            from slamreplay.api.service.errors import ForbiddenError

            raise ForbiddenError(f"pipeline {pipeline} is an external program (docs/external.md); this service runs "
                                 f"external pipelines only when its operator allows it "
                                 f"(SLAMREPLAY_ALLOW_EXTERNAL_PIPELINES=true)")
        resolve_config(pipeline_cls, config)
        try:
            json.dumps(config, allow_nan=False)
        except ValueError as err:
            raise ReplayError(f"config must be plain JSON values: {err}") from err
        topic_map = parse_topic_map(topic_map)
        try:
            recording_id = resolve_id(self.store, recording_id, ("recording",))
        except NotFoundError as err:
            raise NotFoundError(f"{err}; upload it with POST /recordings first") from None
        rec = self.store.get_recording(recording_id)
        if rec is not None:  # else add_job answers 404 below
            check_fit(rec, pipeline_cls, topic_map)
        job = self.store.add_job(uuid.uuid4().hex, recording_id, pipeline, config, seed, topic_map or None, rev,
                                 made_by, labels)
        if job is None:
            raise NotFoundError(f"recording {recording_id} not found; upload it with POST /recordings first")
        self.wake()
        return job

    def get(self, job_id: str) -> JobRow:
        """The job; NotFoundError when unknown, saying who deleted it and when if it was deleted."""
        job = self.store.get_job(job_id)
        if job is None:
            raise self.missing(job_id)
        return job

    def missing(self, job_id: str) -> NotFoundError:
        """The 404 of a job id the store does not hold: a deleted job's says who deleted it and when."""
        stone = self.store.tombstone(job_id)
        return NotFoundError(f"job {job_id} not found" if stone is None else f"job {job_id} was {stone.text}")

    def cancel(self, job_id: str) -> JobRow:
        """Cancel a queued or running job; ConflictError when it has already ended."""
        job, before = self.store.cancel_job(job_id)
        if job is None:
            raise self.missing(job_id)
        if before == "running":
            self.executor.cancel(job_id)
        elif before != "queued":
            raise ConflictError(f"job {job_id} has already ended ({before}); there is nothing to cancel")
        return job

    def artifact(self, job_id: str, name: str) -> Path:
        """A file of a job's run directory; NotFoundError saying why it is not there (yet)."""
        job = self.get(job_id)
        path = self.run_dir(job_id) / name
        if not path.is_file():
            why = {"queued": "it has not started", "running": "it is still running",
                   "cancelled": "it was cancelled"}.get(job.status, f"its status is {job.status}")
            raise NotFoundError(f"job {job_id} has no {name}: {why}")
        return path

    def finished_run(self, job_id: str) -> Path:
        """The run directory of a succeeded job; ConflictError when the job has not succeeded."""
        job = self.get(job_id)
        if job.status != "succeeded":
            raise ConflictError(f"job {job_id} is {job.status}; only succeeded jobs can be compared")
        return self.run_dir(job_id)

    def comparison_rrd(self, a: str, b: str) -> Path:
        """One .rrd holding both runs (made once per pair, then served from ``runs/diffs/``)."""
        run_a, run_b = self.finished_run(a), self.finished_run(b)
        out = self.settings.runs_dir / "diffs" / f"{a}-{b}.rrd"
        if not out.is_file():
            from slamreplay.replay.runs.diff import diff_runs

            diff = diff_runs(run_a, run_b, compare_rrd=False)
            diff.a, diff.b = self.run_label(a), self.run_label(b)  # its summary's title: not server paths
            write_comparison_rrd(self._labelled(run_a, diff.a), self._labelled(run_b, diff.b), out, diff)
        return out

    def run_label(self, job_id: str) -> str:
        """``name-or-id8: pipeline on sim.mcap, seed 0``: a run as the user knows it."""
        job = self.get(job_id)
        rec = self.store.get_recording(job.recording_id)
        name = rec.filename if rec is not None else job.recording_id[:8]
        return f"{job.name or job.id[:8]}: {job.pipeline} on {name}, seed {job.seed}"

    def _labelled(self, run_dir: Path, label: str) -> Path:
        """A link to ``run_dir`` named by ``label`` (a comparison's views are named by their run directories),
        or ``run_dir`` itself when the link cannot be made."""
        safe = "".join(ch if ch.isalnum() or ch in " .,:_-" else "_" for ch in label)[:120].strip() or run_dir.name
        link = self.settings.runs_dir / "diffs" / ".labels" / run_dir.name / safe
        try:
            if not link.is_symlink():
                link.parent.mkdir(parents=True, exist_ok=True)
                link.symlink_to(run_dir.resolve(), target_is_directory=True)
        except OSError:
            return run_dir
        return link
