"""``/docs`` (Swagger UI) and ``/redoc`` (ReDoc) with their scripts and styles served by the service itself.

FastAPI's own pages load Swagger UI, ReDoc, a favicon and (ReDoc) Google Fonts from CDNs, so they are
blank on a machine without internet. Here the same pages load them from ``DOCS_ASSETS``, a folder of the
installed ``fastapi-offline`` package (pinned in pyproject.toml; it ships ``swagger-ui-bundle.js``,
``swagger-ui.css``, ``redoc.standalone.js`` and a favicon), mounted at ``ASSETS_URL``. Every URL in the
pages is relative to the app's ``root_path``, so the docs also work behind a proxy's path prefix.

A service builds its app with ``docs_url=None, redoc_url=None`` and calls ``add_offline_docs(app)``.
"""

from __future__ import annotations

import functools
from importlib.resources import files
from pathlib import Path

from fastapi import FastAPI, Request
from fastapi.openapi.docs import get_redoc_html, get_swagger_ui_html, get_swagger_ui_oauth2_redirect_html
from fastapi.responses import HTMLResponse, Response
from fastapi.staticfiles import StaticFiles

DOCS_ASSETS = Path(str(files("fastapi_offline") / "static"))
ASSETS_URL = "/docs-assets"
ASSET_FILES = ("swagger-ui-bundle.js", "swagger-ui.css", "redoc.standalone.js", "favicon.png")
# No validator badge: Swagger UI would otherwise send the document to validator.swagger.io.
SWAGGER_PARAMETERS = {"validatorUrl": None}
# ReDoc 2 draws Redocly's logo (in its "API docs by Redocly" link) from a CDN whatever its options say:
# its script is served with that URL replaced by an empty image.
REDOCLY_LOGO = b"https://cdn.redoc.ly/redoc/logo-mini.svg"
EMPTY_IMAGE = b"data:image/gif;base64,R0lGODlhAQABAAAAACH5BAEKAAEALAAAAAABAAEAAAICTAEAOw=="
# And the pages may load nothing from another origin, whatever a later version of the assets asks for.
# Their own bootstrap scripts are inline; ReDoc's search runs in a blob: worker.
CONTENT_SECURITY_POLICY = (
    "default-src 'self'; script-src 'self' 'unsafe-inline'; style-src 'self' 'unsafe-inline'; "
    "img-src 'self' data:; font-src 'self' data:; worker-src 'self' blob:; connect-src 'self'"
)


@functools.cache
def redoc_js() -> bytes:
    """ReDoc's script as packaged, but for Redocly's logo (an empty image: nothing to ask a CDN for)."""
    return (DOCS_ASSETS / "redoc.standalone.js").read_bytes().replace(REDOCLY_LOGO, EMPTY_IMAGE)


def add_offline_docs(app: FastAPI, docs_url: str = "/docs", redoc_url: str = "/redoc") -> None:
    """Serve Swagger UI at ``docs_url`` and ReDoc at ``redoc_url`` from the packaged assets.

    The app must have been made with ``docs_url=None, redoc_url=None`` (FastAPI's CDN pages off).
    """
    if app.docs_url is not None or app.redoc_url is not None:
        raise ValueError("make the app with docs_url=None, redoc_url=None: these pages replace FastAPI's")
    missing = [name for name in ASSET_FILES if not (DOCS_ASSETS / name).is_file()]
    if missing:
        raise RuntimeError(
            f"the docs assets {missing} are missing from {DOCS_ASSETS} (reinstall fastapi-offline)"
        )
    openapi_url = app.openapi_url or "/openapi.json"
    oauth2_redirect_url = app.swagger_ui_oauth2_redirect_url or "/docs/oauth2-redirect"

    @app.get(f"{ASSETS_URL}/redoc.standalone.js", include_in_schema=False)  # before the folder's mount
    async def redoc_script() -> Response:
        return Response(redoc_js(), media_type="text/javascript", headers={"Cache-Control": "max-age=3600"})

    app.mount(ASSETS_URL, StaticFiles(directory=DOCS_ASSETS), name="docs-assets")

    def local_only(page: HTMLResponse) -> HTMLResponse:
        page.headers["Content-Security-Policy"] = CONTENT_SECURITY_POLICY
        return page

    def prefix(request: Request) -> str:
        return str(request.scope.get("root_path", "")).rstrip("/")

    @app.get(docs_url, include_in_schema=False)
    async def swagger_ui(request: Request) -> HTMLResponse:
        root = prefix(request)
        return local_only(
            get_swagger_ui_html(
                openapi_url=root + openapi_url,
                title=f"{app.title} - Swagger UI",
                oauth2_redirect_url=root + oauth2_redirect_url,
                swagger_js_url=f"{root}{ASSETS_URL}/swagger-ui-bundle.js",
                swagger_css_url=f"{root}{ASSETS_URL}/swagger-ui.css",
                swagger_favicon_url=f"{root}{ASSETS_URL}/favicon.png",
                swagger_ui_parameters={**SWAGGER_PARAMETERS, **(app.swagger_ui_parameters or {})},
            )
        )

    @app.get(oauth2_redirect_url, include_in_schema=False)
    async def swagger_ui_redirect() -> HTMLResponse:
        return get_swagger_ui_oauth2_redirect_html()

    @app.get(redoc_url, include_in_schema=False)
    async def redoc(request: Request) -> HTMLResponse:
        root = prefix(request)
        return local_only(
            get_redoc_html(
                openapi_url=root + openapi_url,
                title=f"{app.title} - ReDoc",
                redoc_js_url=f"{root}{ASSETS_URL}/redoc.standalone.js",
                redoc_favicon_url=f"{root}{ASSETS_URL}/favicon.png",
                with_google_fonts=False,
            )
        )
