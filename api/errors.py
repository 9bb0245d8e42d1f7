"""The service's own errors; each carries its HTTP status. One handler in app.py turns them, and
ReplayError/RecorderError (bad input to the platform: 422), into ``{"detail": message, ...}``."""

from __future__ import annotations

from typing import Any


class ApiError(Exception):
    """An error with an HTTP status and optional extra fields for the response body."""

    status = 400

    def __init__(self, detail: str, **extra: Any) -> None:
        super().__init__(detail)
        self.detail = detail
        self.extra = extra


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
