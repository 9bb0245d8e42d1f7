"""Service settings: environment variables, overridden by `slamreplay serve` options.

| variable | default | meaning |
| --- | --- | --- |
| ``SLAMREPLAY_DATA_DIR`` | ``.`` | holds ``recordings/`` (uploads, by sha256) and ``runs/`` (a directory per job, |
| | | the job database ``runs/jobs.sqlite``, comparison recordings in ``runs/diffs/``) |
| ``SLAMREPLAY_TOKEN`` | unset | when set, every route but ``/healthz`` needs ``Authorization: Bearer <token>`` |
| | | (not used once the data directory has people: ``slamreplay users``, api/service/auth.py) |
| ``SLAMREPLAY_WORKERS`` | ``2`` | worker processes, i.e. jobs running at once |
| ``SLAMREPLAY_MAX_UPLOAD_BYTES`` | 2 GiB | larger uploads are refused with 413 |
| ``SLAMREPLAY_EXECUTOR`` | ``local`` | where jobs run: ``local`` (spawned worker processes) or ``ray`` |
| | | (Ray tasks; ``pip install -e '.[ray]'``) |
| ``SLAMREPLAY_RAY_ADDRESS`` | unset | the Ray cluster to join (``ray://host:10001``, ``auto``); unset: start a |
| | | local Ray instance with ``workers`` CPUs |
| ``SLAMREPLAY_STORAGE_URL`` | unset | where workers find recordings and write runs (``s3://bucket/prefix``, |
| | | ``file:///shared/slam``): recordings are copied there, runs copied back to |
| | | ``runs/`` when they end; unset: workers use ``recordings/`` and ``runs/`` in place |
| ``SLAMREPLAY_JOB_MEMORY_MIB`` | unset | resident memory limit of a job's process (its imports included, about |
| | | 200 MiB); a job past it fails with "job exceeded its memory limit of N MiB" |
| ``SLAMREPLAY_JOB_TIMEOUT_S`` | unset | wall-time limit of a job, from its start in a worker |
| ``SLAMREPLAY_ALLOWED_HOSTS`` | unset | host names served besides 127.0.0.1, localhost, ::1 and the address |
| | | ``serve`` is bound to, comma-separated: ``slam.lan,10.0.0.5``, ``*.example.org``, ``*`` for |
| | | any (slamreplay.api.service.siteguard); another ``Host`` is a 400 |
| ``SLAMREPLAY_HEADER_TIMEOUT_S`` | ``10`` | a request's header must be whole this long after its first byte (or |
| | | after the connection, for the first request), else 408 and closed (slamreplay.api.service.timeouts) |
| ``SLAMREPLAY_BODY_TIMEOUT_S`` | ``30`` | longest wait for the next bytes of a request body, else 408 and closed |
| ``SLAMREPLAY_MIN_BODY_RATE`` | ``1024`` | lowest average body rate in bytes/s, checked from ``BODY_TIMEOUT_S`` |
| | | after the request's start, else 408 (0: no rate) |
| ``SLAMREPLAY_ALLOW_EXTERNAL_PIPELINES`` | ``false`` | run jobs of external pipelines (programs declared in TOML by |
| | | the operator, ``SLAMREPLAY_PIPELINES``: docs/external.md); otherwise such a job is refused with 403 |
| ``SLAMREPLAY_ALLOW_LIVE_RECORDING`` | ``false`` | let clients start recordings of live Foxglove WebSocket streams |
| | | from the server (``POST /recordings/live``: it connects to the URL a client names); otherwise 403 |
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any, Literal

from fastapi import Request
from pydantic import BaseModel, ConfigDict, Field, field_validator

from slamreplay.api.service.limits import JobLimits
from slamreplay.api.service.timeouts import BODY_TIMEOUT_S, HEADER_TIMEOUT_S, MIN_BODY_RATE

ENV_PREFIX = "SLAMREPLAY_"
ENV_FIELDS = ("data_dir", "token", "workers", "max_upload_bytes", "executor", "ray_address", "storage_url",
              "job_memory_mib", "job_timeout_s", "allowed_hosts", "header_timeout_s", "body_timeout_s",
              "min_body_rate", "allow_external_pipelines", "allow_live_recording")
LIST_FIELDS = ("allowed_hosts",)  # comma-separated in the environment


class Settings(BaseModel):
    """What the service needs to know; immutable once the app is built."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    data_dir: Path = Path(".")
    token: str | None = Field(default=None, min_length=1, repr=False)
    workers: int = Field(default=2, ge=1, le=64)
    max_upload_bytes: int = Field(default=2 << 30, ge=1)
    executor: Literal["local", "ray"] = "local"
    ray_address: str | None = Field(default=None, min_length=1)
    storage_url: str | None = Field(default=None, min_length=1)
    job_memory_mib: int | None = Field(default=None, ge=64)
    job_timeout_s: float | None = Field(default=None, gt=0)
    allowed_hosts: tuple[str, ...] = ()
    header_timeout_s: float = Field(default=HEADER_TIMEOUT_S, gt=0)
    body_timeout_s: float = Field(default=BODY_TIMEOUT_S, gt=0)
    min_body_rate: int = Field(default=MIN_BODY_RATE, ge=0)
    allow_external_pipelines: bool = False  # programs declared in TOML run only when the operator says so
    allow_live_recording: bool = False  # the server connects to a client's ws:// URL only when the operator says so

    @field_validator("allowed_hosts")
    @classmethod
    def _host_names(cls, hosts: tuple[str, ...]) -> tuple[str, ...]:
        for host in hosts:
            if not host or any(c.isspace() or c in "/@?#," for c in host):
                raise ValueError(f"{host!r} is not a host name: give names or addresses such as slam.lan, 10.0.0.5, "
                                 "*.example.org or *, not URLs")
        return hosts

    @classmethod
    def from_env(cls, env: Mapping[str, str] | None = None, **overrides: Any) -> Settings:
        """Settings from ``SLAMREPLAY_*`` variables; ``overrides`` that are not None win.

        Raises pydantic.ValidationError naming the variable's field when a value is invalid.
        """
        env = os.environ if env is None else env
        values: dict[str, Any] = {}
        for name in ENV_FIELDS:
            raw = env.get(ENV_PREFIX + name.upper())
            if raw is not None and raw != "":
                values[name] = tuple(v.strip() for v in raw.split(",") if v.strip()) if name in LIST_FIELDS else raw
        values.update({k: v for k, v in overrides.items() if v is not None})
        return cls(**values)

    @property
    def job_limits(self) -> JobLimits:
        return JobLimits(self.job_memory_mib, self.job_timeout_s)

    @property
    def recordings_dir(self) -> Path:
        return self.data_dir.resolve() / "recordings"

    @property
    def runs_dir(self) -> Path:
        return self.data_dir.resolve() / "runs"

    @property
    def db_path(self) -> Path:
        return self.runs_dir / "jobs.sqlite"

    def make_dirs(self) -> None:
        """Create the data directory (with its parents) and the directories in it."""
        self.data_dir.mkdir(parents=True, exist_ok=True)
        for d in (self.recordings_dir, self.recordings_dir / "damaged", self.runs_dir, self.runs_dir / "diffs"):
            d.mkdir(exist_ok=True)


def get_settings(request: Request) -> Settings:
    """FastAPI dependency: the settings the app was built with."""
    settings: Settings = request.app.state.settings
    return settings
