"""Service settings: environment variables, overridden by `slamreplay serve` options.

| variable | default | meaning |
| --- | --- | --- |
| ``SLAMREPLAY_DATA_DIR`` | ``.`` | holds ``recordings/`` (uploads, by sha256) and ``runs/`` (a directory per job, |
| | | the job database ``runs/jobs.sqlite``, comparison recordings in ``runs/diffs/``) |
| ``SLAMREPLAY_TOKEN`` | unset | when set, every route but ``/healthz`` needs ``Authorization: Bearer <token>`` |
| ``SLAMREPLAY_WORKERS`` | ``2`` | worker processes, i.e. jobs running at once |
| ``SLAMREPLAY_MAX_UPLOAD_BYTES`` | 2 GiB | larger uploads are refused with 413 |
| ``SLAMREPLAY_EXECUTOR`` | ``local`` | where jobs run: ``local`` (spawned worker processes) |
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any, Literal

from fastapi import Request
from pydantic import BaseModel, ConfigDict, Field

ENV_PREFIX = "SLAMREPLAY_"
ENV_FIELDS = ("data_dir", "token", "workers", "max_upload_bytes", "executor")


class Settings(BaseModel):
    """What the service needs to know; immutable once the app is built."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    data_dir: Path = Path(".")
    token: str | None = Field(default=None, min_length=1, repr=False)
    workers: int = Field(default=2, ge=1, le=64)
    max_upload_bytes: int = Field(default=2 << 30, ge=1)
    executor: Literal["local"] = "local"

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
                values[name] = raw
        values.update({k: v for k, v in overrides.items() if v is not None})
        return cls(**values)

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
        """Create the data directories (the data directory itself must exist)."""
        if not self.data_dir.is_dir():
            raise FileNotFoundError(f"data directory {self.data_dir} does not exist: create it first")
        for d in (self.recordings_dir, self.recordings_dir / "damaged", self.runs_dir, self.runs_dir / "diffs"):
            d.mkdir(exist_ok=True)


def get_settings(request: Request) -> Settings:
    """FastAPI dependency: the settings the app was built with."""
    settings: Settings = request.app.state.settings
    return settings
