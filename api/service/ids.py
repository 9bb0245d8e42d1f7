"""Ids as the page shows them: a whole recording, job or suite id, or an unambiguous prefix of one (at least 4
hex digits; the page shows 8), resolved against the job store. Used by the routes' middleware
(`slamreplay.api.service.idprefix`) and by the services for ids in request bodies (a job's recording, a
suite's recordings).
"""

from __future__ import annotations

import re

from slamreplay.api.service.errors import ConflictError, NotFoundError
from slamreplay.api.service.store import Store

MIN_PREFIX = 4
# kind -> (table, length of a whole id)
KINDS = {"recording": ("recordings", 64), "job": ("jobs", 32), "suite": ("suites", 32)}
HEX = re.compile(r"[0-9a-f]+")


def _what(kinds: tuple[str, ...]) -> str:
    return " or ".join(kinds)


def is_whole(text: str, kinds: tuple[str, ...]) -> bool:
    """Whether ``text`` has the form of a whole id of one of ``kinds`` (lowercase hex of its length)."""
    return bool(HEX.fullmatch(text)) and len(text) in {KINDS[k][1] for k in kinds}


def resolve_id(store: Store, text: str, kinds: tuple[str, ...]) -> str:
    """The whole id that ``text`` (a whole id or a prefix of one) names among ``kinds``.

    Raises
    ------
    NotFoundError
        ``text`` is not hex, is longer than an id, shorter than 4 digits, or starts no id.
    ConflictError
        ``text`` starts several ids (they are named).
    """
    what = _what(kinds)
    if is_whole(text, kinds):
        return text
    if not HEX.fullmatch(text) or len(text) > max(KINDS[k][1] for k in kinds):
        shown = text if len(text) <= 80 else text[:77] + "..."
        raise NotFoundError(f"{what} {shown!r} not found: an id is lowercase hex digits (or the first 8 of them, "
                            "as the page shows)")
    if len(text) < MIN_PREFIX:
        raise NotFoundError(f"{what} {text!r} not found: give at least {MIN_PREFIX} hex digits of its id")
    found = [i for k in kinds for i in store.ids_starting(KINDS[k][0], text)]
    if not found:
        raise NotFoundError(f"no {what} id starts with {text}")
    if len(found) > 1:
        more = "" if len(found) < 10 else " and more"
        raise ConflictError(f"{what} id prefix {text} is ambiguous: it starts {', '.join(found)}{more}; "
                            "give more digits")
    return found[0]
