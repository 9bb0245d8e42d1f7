"""Request and response bodies of the HTTP API (the only Pydantic models of the project)."""

from __future__ import annotations

import json
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator

from slamreplay.api.service.store import JobRow, RecordingRow
from slamreplay.api.service.store_runs import MAX_NAME, MAX_NOTE, MAX_TAGS, Labels
from slamreplay.recorder.recover import RecoveryReport

SHA256 = r"^[0-9a-f]{64}$"
JOB_ID = r"^[0-9a-f]{32}$"
JobStatusName = Literal["queued", "running", "succeeded", "failed", "cancelled", "interrupted"]


def _time(t: float) -> datetime:
    return datetime.fromtimestamp(t, timezone.utc)


def _maybe_time(t: float | None) -> datetime | None:
    return None if t is None else _time(t)


class ErrorOut(BaseModel):
    detail: str | list[dict[str, Any]] = Field(description="what is wrong and what to do; for a malformed request, "
                                                          "a list of the fields at fault (FastAPI validation)")
    recover: dict[str, str] | None = Field(default=None, description="damaged upload: the id and URL that salvage it")


class TopicOut(BaseModel):
    topic: str
    read_as: str | None = Field(description="the slamreplay topic it is read as; null: not used by pipelines")
    schema_name: str
    encoding: str
    messages: int


class DroppedRangeOut(BaseModel):
    start: int = Field(description="first byte left out (offset in the damaged upload)")
    end: int = Field(description="one past the last byte left out")
    bytes: int
    reason: str


class RecoveryOut(BaseModel):
    from_id: str = Field(description="sha256 of the damaged upload")
    messages: int = Field(description="messages kept")
    channels: int
    lost: int = Field(description="messages lost: exact when lost_exact, else a lower bound")
    lost_exact: bool = Field(description="lost is counted against the file's Statistics record")
    expected: int | None = Field(description="messages the damaged file's statistics count; null when unreadable")
    dropped: list[DroppedRangeOut] = Field(description="byte ranges left out, each with its reason")
    notes: list[str]
    stopped_at: str | None = Field(description="where and why reading stopped; null when no damage was found")

    @classmethod
    def of(cls, report: RecoveryReport, from_id: str) -> RecoveryOut:
        return cls(from_id=from_id, messages=report.messages, channels=report.channels, lost=report.lost,
                   lost_exact=report.lost_exact, expected=report.expected,
                   dropped=[DroppedRangeOut(start=a, end=b, bytes=b - a, reason=why) for a, b, why in report.dropped],
                   notes=list(report.notes), stopped_at=report.stopped_at)


class RecordingOut(BaseModel):
    id: str = Field(description="sha256 of the file")
    filename: str
    size_bytes: int
    message_count: int
    start_ns: int
    end_ns: int
    duration_s: float
    topics: list[TopicOut]
    created_at: datetime
    links: dict[str, str]
    recovered: RecoveryOut | None = None

    @classmethod
    def of(cls, rec: RecordingRow, report: RecoveryReport | None = None, from_id: str | None = None) -> RecordingOut:
        recovered = None if report is None else RecoveryOut.of(report, from_id or "")
        return cls(id=rec.id, filename=rec.filename, size_bytes=rec.size, message_count=rec.message_count,
                   start_ns=rec.start_ns, end_ns=rec.end_ns, duration_s=(rec.end_ns - rec.start_ns) / 1e9,
                   topics=[TopicOut(**t) for t in rec.topics], created_at=_time(rec.created),
                   links={"self": f"/recordings/{rec.id}", "download": f"/recordings/{rec.id}/download",
                          "jobs": f"/jobs?recording={rec.id}"}, recovered=recovered)


class JobSpec(BaseModel):
    """What to run: a stored recording through a pipeline with a config and a seed."""

    model_config = ConfigDict(extra="forbid")

    # Checked by the service, not a pattern: a prefix of an id names it, and a malformed one is a 404 with the id.
    recording_id: str = Field(min_length=1, max_length=200, description="id (sha256) of an uploaded recording, or "
                                                                        "an unambiguous prefix of it (the page "
                                                                        "shows 8 digits)")
    pipeline: str = Field(min_length=1, max_length=100, description="a pipeline name (see `slamreplay pipelines`)")
    config: dict[str, Any] = Field(default_factory=dict, description="config key -> value; defaults for the rest")
    seed: int = Field(default=0, ge=0, le=2**63 - 1)
    topic_map: dict[str, str] = Field(default_factory=dict, max_length=100,
                                      description="file topic -> slamreplay topic, for a recording whose topics "
                                                  'have other names, e.g. {"/wheel/odom": "/odom"}')
    name: str | None = Field(default=None, max_length=MAX_NAME, description="what people call the run")
    tags: list[str] = Field(default_factory=list, max_length=MAX_TAGS,
                            description="letters, digits and _ . : / + - (at most 40 characters each)")
    note: str | None = Field(default=None, max_length=MAX_NOTE, description="what people say of it")

    @model_validator(mode="after")
    def _labels_valid(self) -> JobSpec:
        self.labels()  # ValueError: a 422 naming what is wrong
        return self

    def labels(self) -> Labels:
        return Labels.parse(self.name, self.tags, self.note)


class LabelsPatch(BaseModel):
    """``PATCH /jobs/ID``: the labels to change; a field left out keeps its value, null or "" clears it."""

    model_config = ConfigDict(extra="forbid")

    name: str | None = Field(default=None, max_length=MAX_NAME)
    tags: list[str] | None = Field(default=None, max_length=MAX_TAGS, description="replaces every tag")
    note: str | None = Field(default=None, max_length=MAX_NOTE)

    @model_validator(mode="after")
    def _labels_valid(self) -> LabelsPatch:
        Labels.parse(self.name, self.tags, self.note)
        return self

    def applied_to(self, job: JobRow) -> Labels:
        given = self.model_fields_set
        return Labels.parse(self.name if "name" in given else job.name,
                            self.tags if "tags" in given else list(job.tags),
                            self.note if "note" in given else job.note)


class JobOut(BaseModel):
    id: str
    recording_id: str
    pipeline: str
    config: dict[str, Any]
    seed: int
    topic_map: dict[str, str] = Field(default_factory=dict, description="file topic -> slamreplay topic")
    status: JobStatusName
    progress: float = Field(ge=0.0, le=1.0)
    error: str | None = Field(description="why it failed, was cancelled or interrupted")
    note: str | None = Field(description="what happened to it besides running (e.g. re-queued after a restart), "
                                         "or what someone wrote of it on the web page")
    name: str | None = Field(default=None, description="the name given to it on the web page")
    tags: list[str] = Field(default_factory=list, description="its tags (the web page's runs table filters by them)")
    made_by: str | None = Field(default=None, description="who submitted or pushed it (null: before people)")
    source: dict[str, Any] | None = Field(default=None, description="where a pushed run was made (host, by whom, "
                                                                     "with which command); null: made by this server")
    git_commit: str | None = Field(default=None, description="the code's commit, as the run's manifest records it")
    attempts: int
    created_at: datetime
    started_at: datetime | None
    finished_at: datetime | None
    duration_s: float | None
    metrics: dict[str, float] | None = Field(default=None, description="metric name -> value, once succeeded")
    manifest: dict[str, Any] | None = Field(default=None, description="the run's manifest.json, once written")
    links: dict[str, str]

    @classmethod
    def of(cls, job: JobRow, run_dir: Path | None = None) -> JobOut:
        """The job; with ``run_dir``, also its metrics and manifest when they exist."""
        metrics = dict(job.metrics) if job.status == "succeeded" and job.metrics is not None else None
        manifest = None  # the store's copy of the metrics (a listing); with run_dir, the run's own file
        if run_dir is not None:
            metrics_file, manifest_file = run_dir / "metrics.json", run_dir / "manifest.json"
            if job.status == "succeeded" and metrics_file.is_file():
                doc = json.loads(metrics_file.read_text())
                metrics = {k: v["value"] for k, v in doc.get("metrics", {}).items()}
            if manifest_file.is_file():
                manifest = json.loads(manifest_file.read_text())
        duration = None if job.started is None or job.finished is None else max(job.finished - job.started, 0.0)
        base = f"/jobs/{job.id}"
        links = {"self": base, "recording": f"/recordings/{job.recording_id}"}
        if job.status in ("succeeded", "failed"):
            links |= {"manifest": f"{base}/manifest", "log": f"{base}/log"}
        if job.status == "succeeded":
            links |= {"rrd": f"{base}/rrd", "metrics": f"{base}/metrics"}
        return cls(id=job.id, recording_id=job.recording_id, pipeline=job.pipeline, config=job.config, seed=job.seed,
                   topic_map=dict(job.topic_map or {}), status=job.status, progress=job.progress, error=job.error,
                   note=job.note, name=job.name, tags=list(job.tags), made_by=job.made_by, source=job.source,
                   git_commit=job.git_commit, attempts=job.attempts,
                   created_at=_time(job.created), started_at=_maybe_time(job.started),
                   finished_at=_maybe_time(job.finished),
                   duration_s=duration, metrics=metrics, manifest=manifest, links=links)


class MetricDeltaOut(BaseModel):
    name: str
    a: float | None
    b: float | None
    delta: float | None
    better: str
    tolerance: float
    verdict: str


class DiffOut(BaseModel):
    a: str = Field(description="job id of the baseline")
    b: str = Field(description="job id judged against it")
    changes: list[dict[str, Any]] = Field(description="manifest fields that differ: field, a, b")
    metrics: list[MetricDeltaOut]
    worse: list[str] = Field(description="metrics that got worse beyond their tolerance")
    rrd_equal: bool | None = Field(description="run.rrd content equality; null when it could not be checked")
    rrd_detail: str


class HealthOut(BaseModel):
    status: Literal["ok"]
    version: str
