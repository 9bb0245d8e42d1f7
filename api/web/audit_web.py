"""The audit trail as a page, for admins: ``/ui/audit``, filtered by who, action and since, older entries a page at a
time (the trail itself and its JSON: ``slamreplay.api.service.audit``)."""

from __future__ import annotations

from typing import Annotated
from urllib.parse import urlencode

from fastapi import APIRouter, Depends, Query, Request
from fastapi.responses import HTMLResponse

from slamreplay.api.service.audit import SHOWN, Action, Since, Who, entries, entry_href, when
from slamreplay.api.service.deps import get_jobs
from slamreplay.api.service.people import ACTIONS
from slamreplay.api.web.pages import PAGE_ERRORS, error_response, page_response, web_session

page = APIRouter(dependencies=[Depends(web_session)], include_in_schema=False)


@page.get("/ui/audit")
def audit_page(request: Request, who: Who = None, action: Action = None, since: Since = None,
               before: Annotated[int | None, Query(ge=1)] = None) -> HTMLResponse:
    try:
        rows = entries(request, who, action, since, before, SHOWN + 1)
    except PAGE_ERRORS as err:
        return error_response(request, err)
    more = len(rows) > SHOWN
    rows = rows[:SHOWN]
    shown = [{"e": e, "when": when(e.at), "href": entry_href(e)} for e in rows]
    query = {k: v for k, v in (("who", who), ("action", action), ("since", since)) if v}
    older = None
    if more and rows:
        older = "/ui/audit?" + urlencode({**query, "before": rows[-1].seq})
    return page_response(request, "audit.html", entries=shown, who=who or "", action=action or "",
                         since=since or "", people=get_jobs(request).store.audit_people(), actions=ACTIONS,
                         older=older, filtered=bool(query or before))
