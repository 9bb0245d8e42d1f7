"""The service's own errors; each carries its HTTP status. One handler in app.py turns them, and
ReplayError/RecorderError (bad input to the platform: 422), into ``{"detail": message, ...}``."""

from __future__ import annotations

import errno
import sqlite3
from typing import Any


class ApiError(Exception):
    """An error with an HTTP status and optional extra fields for the response body."""

    status = 400

    def __init__(self, detail: str, **extra: Any) -> None:
        super().__init__(detail)
        self.detail = detail
        self.extra = extra


class ForbiddenError(ApiError):
    """The service's operator does not allow this (an external pipeline: SLAMREPLAY_ALLOW_EXTERNAL_PIPELINES)."""

    status = 403


class NotFoundError(ApiError):
    """An id that names nothing."""

    status = 404


class ConflictError(ApiError):
    """The request clashes with the current state (cancelling a finished job, deleting a recording in use)."""

    status = 409


class TooLargeError(ApiError):
    """An upload over the size limit."""

    status = 413


class NotMcapError(ApiError):
    """An upload that is not an MCAP file at all."""

    status = 415


class UnreadableError(ApiError):
    """An upload that is an MCAP but cannot be read (truncated, corrupt index); ``recover`` says how to salvage it."""

    status = 422


class UnauthorizedError(ApiError):
    """A missing or wrong bearer token."""

    status = 401


class InsufficientStorageError(ApiError):
    """The data directory's disk is full: nothing was stored; the service keeps serving."""

    status = 507


DISK_FULL_ERRNOS = (errno.ENOSPC, errno.EDQUOT)
SQLITE_FULL = 13  # SQLite's result code (sqlite3.SQLITE_FULL from Python 3.11; 3.10 names no codes)


def is_disk_full(exc: BaseException) -> bool:
    """Whether ``exc`` (or an error it was raised from) is a full disk: ENOSPC/EDQUOT, or SQLite's SQLITE_FULL."""
    seen: BaseException | None = exc
    for _ in range(5):  # follow ``raise ... from err`` a few steps
        if seen is None:
            return False
        if isinstance(seen, OSError) and seen.errno in DISK_FULL_ERRNOS:
            return True
        if isinstance(seen, sqlite3.Error) and (getattr(seen, "sqlite_errorcode", None) == SQLITE_FULL
                                                or "database or disk is full" in str(seen)):
            return True
        seen = seen.__cause__ or seen.__context__
    return False


def disk_full_error(what: str) -> InsufficientStorageError:
    """The 507 answer for a full disk met while doing ``what``."""
    return InsufficientStorageError(f"no space left on the device of the service's data directory while {what}: "
                                    "nothing was stored; retry once space has been freed (delete recordings or "
                                    "runs, or give SLAMREPLAY_DATA_DIR a larger disk)")
