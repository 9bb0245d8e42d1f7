"""The replay layer's one base exception."""

from __future__ import annotations


class ReplayError(Exception):
    """A replay could not start or finish because of its input; the message says what to do."""
