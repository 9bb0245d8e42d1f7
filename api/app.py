"""The whole server: the HTTP service with the web page mounted on it.

``create_app`` is what ``slamreplay serve`` runs and what tests and deployments build: the service
(``slamreplay.api.service.app.create_service``: the API, the job store, an executor) and the pages
(``slamreplay.api.web.web.install_web``), the one place above both rooms.
"""

from __future__ import annotations

from fastapi import FastAPI

from slamreplay.api.service.app import create_service
from slamreplay.api.service.datalock import DataDirLock
from slamreplay.api.service.executor import Executor
from slamreplay.api.service.settings import Settings
from slamreplay.api.web.pages import error_response
from slamreplay.api.web.web import install_web


def create_app(settings: Settings | None = None, executor: Executor | None = None,
               lock: DataDirLock | None = None) -> FastAPI:
    """The service over ``settings.data_dir`` with the web page; the executor runs (and the scheduler starts) with
    the lifespan. ``lock``: the data directory's lock when the caller took it already (``slamreplay serve``); else
    the lifespan takes it, and fails with ``DataDirInUseError`` while another server holds the directory."""
    app = create_service(settings, executor, lock, page_error=error_response)
    install_web(app)
    return app
