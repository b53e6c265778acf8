"""``create_app(settings)``: the built dashboard as static files, and ``/config.json`` for it.

The dashboard uses hash routes (``/#/playground``), so every page is ``index.html``; nothing needs a
server-side fallback. When ``web/dist`` has not been built, ``/`` says how to build it instead of 404.
"""

from __future__ import annotations

import json
import logging
import re

from fastapi import FastAPI
from fastapi.responses import HTMLResponse, JSONResponse
from fastapi.staticfiles import StaticFiles

from services.web.settings import Settings

log = logging.getLogger(__name__)
MEASUREMENTS = ("eval.json", "bench.json")
_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]*$")

NOT_BUILT = """<!doctype html><html><head><meta charset="utf-8"><title>NeuroAnimator</title></head>
<body style="font-family: sans-serif; margin: 3em">
<h1>The dashboard is not built</h1>
<p>There is no <code>{dist}/index.html</code>. Build it with <code>make up</code>, or
<code>cd web &amp;&amp; npm ci &amp;&amp; npm run build</code>, then reload this page.</p>
</body></html>"""


def create_app(settings: Settings | None = None) -> FastAPI:
    settings = settings or Settings()
    app = FastAPI(title="NeuroAnimator dashboard", version="0.1.0", docs_url=None, redoc_url=None)
    config = {"emulator_url": settings.emulator_url, "controller_url": settings.controller_url}

    @app.get("/config.json")
    def get_config() -> JSONResponse:
        """Where the browser finds the emulator and the controller services."""
        return JSONResponse(config, headers={"Cache-Control": "no-store"})

    @app.get("/healthz")
    def healthz() -> dict[str, str]:
        return {"status": "ok"}

    @app.get("/artifacts/{model}/{name}")
    def measurements(model: str, name: str) -> JSONResponse:
        """A model's evaluation or benchmark results (``eval.json``, ``bench.json``), when measured."""
        path = settings.artifacts_dir / model / name
        if name not in MEASUREMENTS or not _NAME.match(model) or not path.is_file():
            return JSONResponse(
                {"error": "not_measured", "message": f"no {name} for model {model!r}"}, status_code=404
            )
        try:
            data = json.loads(path.read_text())
        except (OSError, ValueError) as exc:
            log.warning("cannot read %s: %s", path, exc)
            return JSONResponse(
                {"error": "unreadable", "message": f"{name} of {model!r} is not valid JSON"}, 500
            )
        return JSONResponse(data, headers={"Cache-Control": "no-cache"})

    dist = settings.web_dist
    if (dist / "index.html").is_file():
        app.mount("/", StaticFiles(directory=dist, html=True), name="dashboard")
    else:
        log.warning("no built dashboard in %s; / explains how to build it", dist)

        @app.get("/", response_class=HTMLResponse)
        def not_built() -> str:
            return NOT_BUILT.format(dist=dist)

    return app
