"""The recorder's one base exception."""

from __future__ import annotations


class RecorderError(Exception):
    """A recording could not be written, read, decoded or recovered; the message says why and what to do."""


class CodecError(RecorderError):
    """A message could not be encoded or decoded."""


class DamageError(RecorderError):
    """A recording's bytes are damaged; the message names the record and its byte offset."""
