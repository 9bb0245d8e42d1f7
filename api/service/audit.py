"""The audit trail: the entries routes add after each change, the job page's "submitted by" lines, and the trail
itself for admins (``GET /audit`` as JSON, filtered by who, action and since; ``/ui/audit`` draws it:
``slamreplay.api.web.audit_web``).

Entries are written by `slamreplay.api.service.auth.record` (who: the request's person, or ``anonymous`` /
``token holder`` on a server without people; when; the client's address) into the store's ``audit`` table
(api/service/people.py).
"""

from __future__ import annotations

import calendar
import re
import time
from datetime import datetime, timezone
from typing import Annotated

from fastapi import APIRouter, Depends, Query, Request
from pydantic import BaseModel
from starlette.requests import Request as StarletteRequest

from slamreplay.api.service.auth import record
from slamreplay.api.service.deps import ERRORS, get_jobs, require_token
from slamreplay.api.service.people import ACTIONS, AuditEntry
from slamreplay.api.service.store import JobRow, Store
from slamreplay.api.service.store_runs import Labels
from slamreplay.api.service.suites import SuiteRow, SuiteService
from slamreplay.replay.errors import ReplayError

SHOWN = 200
# what the job page says of each action on a job
JOB_WORDS = {"submit": "submitted", "push": "pushed (made elsewhere)", "cancel": "cancelled",
             "label": "named, tagged or annotated", "delete": "deleted"}
JOB_ACTIONS = ("submit", "push", "cancel", "label", "delete")
SUITE_ACTIONS = ("suite", "run-on-commit")


def submitted_text(job: JobRow) -> str:
    """An entry's detail for a job: ``odometry on 1a2b3c4d, seed 0``."""
    return f"{job.pipeline} on recording {job.recording_id[:8]}, seed {job.seed}" + (
        f", commit {job.rev[:10]}" if job.rev else "")


def record_suite(request: StarletteRequest, suites: SuiteService, row: SuiteRow, rev: str | None = None) -> None:
    """Entries for a suite sent (``suite``, or ``run-on-commit`` with ``rev``) and for each job it queued."""
    _, _, cells = suites.get(row.id)
    new = [c for c in cells if not c.reused]
    detail = f"{row.name}: {len(cells)} cells, {len(new)} new jobs" + (f", commit {rev[:10]}" if rev else "")
    record(request, "run-on-commit" if rev else "suite", row.id, detail)
    for c in dict((c.job.id, c) for c in new).values():
        record(request, "submit", c.job.id, f"{submitted_text(c.job)}; suite {row.name}")


def label_job(request: StarletteRequest, store: Store, job_id: str, labels: Labels) -> JobRow | None:
    """Set a job's name, tags and note and add the change to the trail; None when the job is unknown."""
    job = store.set_labels(job_id, labels)
    if job is not None:
        note = (labels.note or "").splitlines()[0][:80] if labels.note else ""
        record(request, "label", job_id, f"name {labels.name or ''!r}, tags {' '.join(labels.tags) or '-'}, "
                                         f"note {note!r}")
    return job


def when(t: float) -> str:
    return time.strftime("%Y-%m-%d %H:%M:%S", time.gmtime(t))


def job_people(store: Store, job_id: str) -> list[dict[str, str]]:
    """What people did to a job, oldest first: ``{"words": "submitted", "who", "when", "address"}``."""
    rows = store.audit_entries(target=job_id, limit=100)
    return [{"words": JOB_WORDS[e.action], "who": e.who, "when": when(e.at), "address": e.address}
            for e in reversed(rows) if e.action in JOB_WORDS]


def parse_since(text: str | None) -> float | None:
    """``2025-05-01`` or ``2025-05-01T12:00`` (UTC) as a time; ApiError (422) saying the form otherwise."""
    if not text or not text.strip():
        return None
    text = text.strip()
    for fmt in ("%Y-%m-%d", "%Y-%m-%dT%H:%M", "%Y-%m-%dT%H:%M:%S", "%Y-%m-%d %H:%M"):
        try:
            return float(calendar.timegm(time.strptime(text, fmt)))
        except ValueError:
            continue
    raise ReplayError(f"since {text[:40]!r}: give a UTC date, 2025-05-01, or a time, 2025-05-01T12:00")


def entry_href(e: AuditEntry) -> str | None:
    if e.target is None or not re.fullmatch(r"[0-9a-f]{32}", e.target):
        return None
    if e.action in JOB_ACTIONS:
        return f"/ui/jobs/{e.target}"
    return f"/ui/suites/{e.target}" if e.action in SUITE_ACTIONS else None


class AuditOut(BaseModel):
    seq: int
    at: datetime
    who: str
    address: str
    action: str
    target: str | None
    detail: str | None


router = APIRouter(dependencies=[Depends(require_token)], responses=ERRORS, tags=["service"])
Who = Annotated[str | None, Query(max_length=100, description="only this person's entries")]
Action = Annotated[str | None, Query(max_length=40, description=f"only this action: {', '.join(ACTIONS)}")]
Since = Annotated[str | None, Query(max_length=40, description="UTC date or time: 2025-05-01 or 2025-05-01T12:00")]


def entries(request: Request, who: str | None, action: str | None, since: str | None,
             before: int | None, limit: int) -> list[AuditEntry]:
    store = get_jobs(request).store
    return store.audit_entries(who=who or None, action=action or None, since=parse_since(since), before=before,
                               limit=limit)


@router.get("/audit")
def audit_trail(request: Request, who: Who = None, action: Action = None, since: Since = None,
                before: Annotated[int | None, Query(ge=1, description="entries older than this seq")] = None,
                limit: Annotated[int, Query(ge=1, le=1000)] = SHOWN) -> list[AuditOut]:
    """Every change, newest first (admins only): who, when, from which address, what and on what."""
    return [AuditOut(seq=e.seq, at=datetime.fromtimestamp(e.at, timezone.utc), who=e.who, address=e.address,
                     action=e.action, target=e.target, detail=e.detail)
            for e in entries(request, who, action, since, before, limit)]
