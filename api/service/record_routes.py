"""``POST /recordings/record/NAME``: a recording made on the server by an importer, one route per importer.

The routes are generated from the importer registry (the entry-point group ``slamreplay.importers``, the
one ``slamreplay record`` builds its sub-commands from): every importer that says ``service = True``
(it needs no input from the server's disk: the simulators) gets a route whose JSON body is its options,
typed from its own argument parser, so ``/docs`` documents each. ``GET /importers`` lists them all, with
why an importer is not offered (it reads files or folders of the machine it runs on: record it where
the data is, then upload the file).

The importer runs in the request's worker thread, writes into a temporary folder of the recordings
directory, and its file is stored like an upload (same checks, same id: the sha256), so the same
options and seed give the same recording and the second request answers 200 with it.
"""

from __future__ import annotations

import argparse
import hashlib
import shutil
import tempfile
from pathlib import Path
from typing import Annotated, Any

from fastapi import APIRouter, Depends, FastAPI, Request, Response
from pydantic import BaseModel, ConfigDict, Field, StrictBool, StrictFloat, StrictInt, StrictStr, create_model
from starlette.concurrency import run_in_threadpool

from slamreplay.api.service.auth import record as audit_record
from slamreplay.api.service.deps import ERRORS, RecordingsDep, require_token
from slamreplay.api.service.models import RecordingOut
from slamreplay.recorder.errors import RecorderError
from slamreplay.recorder.sources import Importer, get_importer, importer_plugins

# Strict types: in lax mode pydantic reads JSON true as the number 1 (a fuzzer's sensor_range_m: true made a
# recording); a float option takes a JSON integer too.
_SCALARS: dict[str, Any] = {"int": StrictInt, "float": StrictFloat | StrictInt, "bool": StrictBool, "str": StrictStr,
                             "seed_value": Annotated[StrictInt, Field(ge=0, lt=2**63)]}


class OptionOut(BaseModel):
    name: str = Field(description="the JSON key (the command-line option without its dashes, '-' as '_')")
    option: str = Field(description="the `slamreplay record` option")
    type: str
    default: Any = None
    choices: list[Any] | None = None
    help: str = ""


class ImporterOut(BaseModel):
    name: str
    help: str
    offered: bool = Field(description="whether POST /recordings/record/NAME runs it on this server")
    why_not: str | None = None
    route: str | None = None
    options: list[OptionOut] = []


class _RaisingParser(argparse.ArgumentParser):
    """An argument parser whose errors are exceptions (an HTTP 422), never an exit."""

    def error(self, message: str) -> Any:  # type: ignore[override]
        raise RecorderError(message)


def _parser(importer: Importer) -> _RaisingParser:
    parser = _RaisingParser(prog=f"record {importer.name}", add_help=False)
    importer.add_arguments(parser)
    return parser


def _options(importer: Importer) -> list[tuple[argparse.Action, str]]:
    """(action, JSON key) of each option the service accepts: all but --out and the file options."""
    skip = {"out", *getattr(importer, "file_options", ())}
    return [(a, a.option_strings[-1].lstrip("-").replace("-", "_")) for a in _parser(importer)._actions
            if a.option_strings and a.dest not in skip and a.dest != "help"]


def _type_name(action: argparse.Action) -> str:
    if action.choices is not None:
        return "|".join(map(str, action.choices))
    name = getattr(action.type, "__name__", "str") if action.type is not None else "str"
    return {"seed_value": "int"}.get(name, name)  # a range-checked int is an int to a client


def why_not_offered(importer: Importer) -> str | None:
    """Why the service does not run ``importer`` (None: it does)."""
    if not getattr(importer, "service", False):
        positional = [a.dest for a in _parser(importer)._actions if not a.option_strings]
        if positional:
            return (f"it reads {', '.join(positional)} from the machine it runs on: run `slamreplay record "
                    f"{importer.name}` where the data is, then upload the recording (POST /recordings)")
        return "the importer does not say it may run on a server (service = True)"
    return None


def describe(name: str) -> ImporterOut:
    plugin = importer_plugins()[name]
    if plugin.error is not None:
        return ImporterOut(name=name, help="", offered=False, why_not=f"the plugin is broken: {plugin.error}")
    importer = get_importer(name)
    why = why_not_offered(importer)
    options = [OptionOut(name=key, option=a.option_strings[-1], type=_type_name(a), default=a.default,
                         choices=list(a.choices) if a.choices is not None else None, help=a.help or "")
               for a, key in _options(importer)] if why is None else []
    return ImporterOut(name=name, help=importer.help, offered=why is None, why_not=why,
                       route=f"/recordings/record/{name}" if why is None else None, options=options)


def _body_model(importer: Importer) -> type[BaseModel]:
    """The JSON body of ``importer``'s route: one optional field per option, typed like the option."""
    fields: dict[str, Any] = {}
    for action, key in _options(importer):
        tp = _SCALARS.get(getattr(action.type, "__name__", "str") if action.type else "str", StrictStr)
        if action.choices is not None:
            tp = StrictStr
        fields[key] = (tp | None, Field(default=None, description=f"{action.option_strings[-1]}: {action.help}"))
    model: type[BaseModel] = create_model(  # type: ignore[call-overload]
        f"Record{''.join(w.title() for w in importer.name.replace('_', '-').split('-'))}In",
        __config__=ConfigDict(extra="forbid"), **fields)
    return model


def _argv(importer: Importer, body: BaseModel, out: Path) -> list[str]:
    argv = ["--out", str(out)]
    by_key = {key: action for action, key in _options(importer)}
    for key, value in body.model_dump(exclude_none=True).items():
        option = by_key[key].option_strings[-1]
        argv += [option, str(value).lower() if isinstance(value, bool) else str(value)]
    return argv


def _record(importer: Importer, body: BaseModel, recordings: Any) -> Any:
    """Run the importer into a temporary folder of the recordings directory and store its file."""
    root = recordings.settings.recordings_dir
    with tempfile.TemporaryDirectory(dir=root, prefix=".record-") as tmp:
        out = Path(tmp) / f"{importer.name}.mcap"
        options = vars(_parser(importer).parse_args(_argv(importer, body, out)))
        importer.record(options, lambda done, total: None, lambda text: None)
        given = sorted(body.model_dump(exclude_none=True).items())
        label = "-".join([importer.name, *(f"{k}{v}" for k, v in given)])
        sha = hashlib.sha256()
        with open(out, "rb") as f:
            while block := f.read(1 << 20):
                sha.update(block)
        staged = root / f".upload-{sha.hexdigest()[:16]}-{Path(tmp).name}.partial"
        shutil.move(out, staged)
        return recordings.accept_local(staged, sha.hexdigest(), label[:200] + ".mcap")


def _route(name: str, importer: Importer) -> Any:
    Body = _body_model(importer)

    async def record(request: Request, body: Any, response: Response, recordings: RecordingsDep) -> RecordingOut:
        stored = await run_in_threadpool(_record, get_importer(name), body, recordings)
        state = "new" if stored.created else "already stored"
        await run_in_threadpool(audit_record, request, "record", stored.recording.id,
                                f"{name}: {stored.recording.filename} ({state})")
        response.status_code = 201 if stored.created else 200
        return RecordingOut.of(stored.recording)

    # the body's model is made here, per importer: give FastAPI the objects, not the module's string annotations
    record.__annotations__.update(request=Request, body=Body, response=Response, recordings=RecordingsDep,
                                  RecordingOut=RecordingOut)
    record.__annotations__["return"] = RecordingOut

    record.__doc__ = (f"`slamreplay record {name}` on the server: {importer.help}. The body holds its options "
                      f"(unset ones keep their defaults); 201 with the new recording, 200 when the same file was "
                      f"stored before.")
    return record


STORED: dict[int | str, dict[str, Any]] = {
    201: {"description": "recorded and stored as a new recording"},
    200: {"model": RecordingOut, "description": "the same file (same sha256) was stored before: its recording; "
                                                 "nothing new is stored"}}


def install_record_routes(app: FastAPI) -> None:
    """``GET /importers`` and one ``POST /recordings/record/NAME`` per importer the service may run."""
    router = APIRouter(dependencies=[Depends(require_token)], responses=ERRORS, tags=["recordings"])

    @router.get("/importers")
    def list_importers() -> list[ImporterOut]:
        """Every importer of `slamreplay record`: whether this server runs it, its options, or why not."""
        return [describe(name) for name in importer_plugins()]

    for name, plugin in importer_plugins().items():
        if plugin.error is not None:
            continue
        importer = get_importer(name)
        if why_not_offered(importer) is None:
            router.add_api_route(f"/recordings/record/{name}", _route(name, importer), methods=["POST"],
                                 status_code=201, response_model=RecordingOut, name=f"record_{name}",
                                 summary=f"Record {name} on the server", responses=STORED)
    app.include_router(router)

