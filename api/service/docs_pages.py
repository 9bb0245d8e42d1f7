"""The interactive API docs, ``/docs`` (Swagger UI) and ``/redoc`` (ReDoc), from files installed with the package.

FastAPI's own docs pages load Swagger UI and ReDoc from a CDN, so without internet ``/docs``
was blank. These pages are FastAPI's same HTML pointed at the copies that the
``fastapi-offline`` package ships (MIT; swagger-ui-dist 5 and redoc 2), served here under
``/docs/assets/``: opening them fetches nothing from another host. Swagger UI's validator
badge (an image from validator.swagger.io) is off for the same reason, and ReDoc's sidebar
logo, which its script loads from cdn.redoc.ly whatever the options, is an empty image (the
"API docs by Redocly" credit stays).
"""

from __future__ import annotations

import base64
import hashlib
import re
from functools import lru_cache
from pathlib import Path

from fastapi import FastAPI, Request
from fastapi.openapi.docs import get_redoc_html, get_swagger_ui_html
from fastapi.responses import HTMLResponse, Response
from fastapi.staticfiles import StaticFiles

ASSETS = "/docs/assets"
FAVICON = "/favicon.ico"  # the web page's own icon (api/web/web.py)
REDOC_LOGO = "https://cdn.redoc.ly/redoc/logo-mini.svg"
EMPTY_IMAGE = "data:image/svg+xml,%3Csvg xmlns='http://www.w3.org/2000/svg'/%3E"


def assets_dir() -> Path:
    """The folder of Swagger UI's and ReDoc's files in the installed ``fastapi-offline``."""
    import fastapi_offline

    return Path(fastapi_offline.__file__).parent / "static"


@lru_cache(maxsize=1)
def redoc_script() -> str:
    """ReDoc's script with its one link to another host (the sidebar logo) replaced by an empty image."""
    text = (assets_dir() / "redoc.standalone.js").read_text(encoding="utf-8")
    return text.replace(REDOC_LOGO, EMPTY_IMAGE)


INLINE_SCRIPT = re.compile(r"<script>(.*?)</script>", re.S)


def with_policy(page: HTMLResponse) -> HTMLResponse:
    """``page`` with a Content-Security-Policy that lets exactly its own inline scripts run (by their sha256), its
    scripts and styles from this server, and the inline styles Swagger UI and ReDoc add as they draw."""
    text = bytes(page.body).decode()
    hashes = " ".join("'sha256-" + base64.b64encode(hashlib.sha256(m.encode()).digest()).decode() + "'"
                      for m in INLINE_SCRIPT.findall(text))
    page.headers["Content-Security-Policy"] = (
        f"default-src 'self'; script-src 'self' {hashes}; style-src 'self' 'unsafe-inline'; img-src 'self' data:; "
        "connect-src 'self'; worker-src 'self' blob:; object-src 'none'; base-uri 'none'; form-action 'self'")
    return page


def install_docs(app: FastAPI, openapi_url: str = "/openapi.json") -> None:
    """``/docs``, ``/redoc`` and their assets on ``app`` (call only when the docs are public: no token)."""

    @app.get(f"{ASSETS}/redoc.standalone.js", include_in_schema=False)
    def redoc_js() -> Response:  # before the mount, which would serve the file as shipped
        return Response(redoc_script(), media_type="text/javascript; charset=utf-8",
                        headers={"Cache-Control": "max-age=86400"})

    app.mount(ASSETS, StaticFiles(directory=assets_dir()), name="docs-assets")

    @app.get("/docs", include_in_schema=False)
    def swagger_ui(request: Request) -> HTMLResponse:
        root = request.scope.get("root_path", "")
        return with_policy(get_swagger_ui_html(openapi_url=root + openapi_url, title=f"{app.title}: API (Swagger UI)",
                                   swagger_js_url=f"{root}{ASSETS}/swagger-ui-bundle.js",
                                   swagger_css_url=f"{root}{ASSETS}/swagger-ui.css",
                                   swagger_favicon_url=root + FAVICON,
                                   swagger_ui_parameters={"validatorUrl": None}))

    @app.get("/redoc", include_in_schema=False)
    def redoc(request: Request) -> HTMLResponse:
        root = request.scope.get("root_path", "")
        return with_policy(get_redoc_html(openapi_url=root + openapi_url, title=f"{app.title}: API (ReDoc)",
                              redoc_js_url=f"{root}{ASSETS}/redoc.standalone.js", redoc_favicon_url=root + FAVICON,
                              with_google_fonts=False))
