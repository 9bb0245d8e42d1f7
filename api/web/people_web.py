"""``/ui/people``: an admin's page of the server's people: add someone, change a role, disable or enable, give a
new token; the same as ``slamreplay users`` (api/cli/users_cli.py), by an admin signed in on the page.

A new token is shown once, on the answer to the form that made it (never stored, never cached); every change
goes into the audit trail by the admin who made it. No change may leave the server without an active admin
(the page refuses it; ``slamreplay users`` on the server's machine can always add one). On a server without
people the page says how to make it a team's with the command line, as adding the first person there would
shut out whoever is using it now.
"""

from __future__ import annotations

from typing import Annotated, Any

from fastapi import APIRouter, Depends, Request
from fastapi import Path as PathParam
from fastapi.responses import HTMLResponse
from starlette.concurrency import run_in_threadpool

from slamreplay.api.service.auth import record, server_mode
from slamreplay.api.service.people import NAME_RE, ROLES, PeopleError
from slamreplay.api.service.store import Store
from slamreplay.api.web.pages import page_response, web_session

UserName = Annotated[str, PathParam(pattern=NAME_RE.pattern)]
page = APIRouter(dependencies=[Depends(web_session)], include_in_schema=False)


def _store(request: Request) -> Store:
    store: Store = request.app.state.jobs.store
    return store


def _show(request: Request, status: int = 200, **ctx: Any) -> HTMLResponse:
    store = _store(request)
    resp = page_response(request, "people.html", status, people=store.users(), roles=ROLES,
                         team=server_mode(request) == "people", **ctx)
    resp.headers["Cache-Control"] = "no-store"  # it may show a token
    return resp


def _admins_left(store: Store, name: str, role: str | None, disabled: bool) -> int:
    """Active admins once ``name`` has ``role`` (None: unchanged) and is ``disabled`` or not."""
    count = 0
    for u in store.users():
        r, off = (role or u.role, disabled) if u.name == name else (u.role, not u.active)
        count += r == "admin" and not off
    return count


@page.get("/ui/people")
def people_page(request: Request) -> HTMLResponse:
    return _show(request)


@page.post("/ui/people")
async def add_person(request: Request) -> HTMLResponse:
    """Add a person; the answer shows their token, once."""
    form = await request.form()
    name, role = str(form.get("name", "")).strip(), str(form.get("role", ""))
    store = _store(request)
    if await run_in_threadpool(server_mode, request) != "people":
        return await run_in_threadpool(_show, request, 409, problem="add the first people with the command line on "
                                       "the server: slamreplay users add NAME --role admin")
    try:
        token = await run_in_threadpool(store.add_user, name, role)
    except PeopleError as err:
        return await run_in_threadpool(_show, request, 422, problem=str(err))
    await run_in_threadpool(record, request, "user-add", name, role)
    return await run_in_threadpool(_show, request, token=token, token_for=name)


@page.post("/ui/people/{name}")
async def change_person(request: Request, name: UserName) -> HTMLResponse:
    """``do``: ``role`` (with ``role``), ``disable``, ``enable`` or ``token`` (the answer shows the new token)."""
    form = await request.form()
    do, role = str(form.get("do", "")), str(form.get("role", "")) or None
    store = _store(request)

    def change() -> dict[str, Any]:
        user = store.user(name)
        if user is None:
            raise PeopleError(f"no user {name!r}")
        if do not in ("role", "disable", "enable", "token"):
            raise PeopleError(f"nothing to do: {do!r} is not role, disable, enable or token")
        if do in ("role", "disable") and _admins_left(store, name, role if do == "role" else None,
                                                      do == "disable" or not user.active) == 0:
            raise PeopleError(f"{name} is the last active admin: make someone else an admin first")
        if do == "role":
            store.set_role(name, role or "")
            record(request, "user-role", name, role)
            return {"done": f"{name} is now a{'n' if role == 'admin' else ''} {role}"}
        if do in ("disable", "enable"):
            store.set_disabled(name, do == "disable")
            record(request, f"user-{do}", name)
            return {"done": f"{name} is {do}d" + (": their token and sessions no longer work" if do == "disable"
                                                   else "")}
        token = store.new_user_token(name)
        record(request, "user-token", name, "a new token; the old one and its page sessions ended")
        return {"token": token, "token_for": name}

    try:
        ctx = await run_in_threadpool(change)
    except PeopleError as err:
        return await run_in_threadpool(_show, request, 422, problem=str(err))
    return await run_in_threadpool(_show, request, **ctx)
