"""``create_app(settings)``: the built dashboard as static files, ``/config.json`` for it, and the
models' evaluation and benchmark results from the artifact registry.

The dashboard uses hash routes (``/#/playground``), so every page is ``index.html``; nothing needs a
server-side fallback. When ``web/dist`` has not been built, ``/`` says how to build it instead of 404.
"""

from __future__ import annotations

import logging
from pathlib import Path

from fastapi import FastAPI
from fastapi.responses import HTMLResponse, JSONResponse, Response
from fastapi.staticfiles import StaticFiles
from pydantic import BaseModel

from neuroanimator.artifacts import registry
from services.common import tenancy
from services.common.docs import add_offline_docs
from services.common.limits import limit_bodies
from services.web.settings import Settings

log = logging.getLogger(__name__)
MEASUREMENTS = (registry.EVAL_FILE, registry.BENCH_FILE)

NOT_BUILT = """<!doctype html><html><head><meta charset="utf-8"><title>NeuroAnimator</title></head>
<body style="font-family: sans-serif; margin: 3em">
<h1>The dashboard is not built</h1>
<p>There is no <code>{dist}/index.html</code>. Build it with <code>make up</code>, or
<code>cd web &amp;&amp; npm ci &amp;&amp; npm run build</code>, then reload this page.</p>
</body></html>"""


def create_app(settings: Settings | None = None) -> FastAPI:
    settings = settings or Settings()
    app = FastAPI(title="NeuroAnimator dashboard", version="0.1.0", docs_url=None, redoc_url=None)
    add_offline_docs(app)  # /docs and /redoc with packaged assets, before the dashboard's mount at /
    limit_bodies(app, settings.max_body_bytes)  # the dashboard takes no bodies: any is small
    _add_config(app, settings)
    _add_measurements(app, settings.roots(), keys_on=bool(settings.api_keys.strip()))
    _add_dashboard(app, settings.web_dist)  # last: mounted at /, it would shadow the routes after it
    return app


def _add_config(app: FastAPI, settings: Settings) -> None:
    """``/config.json`` and ``/healthz``."""
    config = {
        "emulator_url": settings.emulator_url,
        "controller_url": settings.controller_url,
        "trainer_url": settings.trainer_url or None,
    }

    @app.get("/config.json")
    def get_config() -> JSONResponse:
        """Where the browser finds the emulator, controller and trainer services (the trainer: null
        when there is none)."""
        return JSONResponse(config, headers={"Cache-Control": "no-store"})

    @app.get("/healthz")
    def healthz() -> dict[str, str]:
        return {"status": "ok"}


def _answer(found: BaseModel | None, what: str) -> Response:
    """A measurement as JSON, or 404 naming ``what`` was not measured."""
    if found is None:
        return JSONResponse({"error": "not_measured", "message": f"no {what}"}, status_code=404)
    # JSON text from pydantic: a non-finite number is null there (JSON has no NaN)
    return Response(
        found.model_dump_json(), media_type="application/json", headers={"Cache-Control": "no-cache"}
    )


def _unreadable(exc: registry.ArtifactError, what: str) -> Response:
    """404 for a model, version or super-step that is not there; 500 for a measurement that is but
    cannot be read."""
    if exc.what in ("model", "version", "substeps"):
        return JSONResponse({"error": "not_measured", "message": f"no {what}: {exc}"}, status_code=404)
    log.warning("cannot read %s: %s", what, exc)
    return JSONResponse({"error": "unreadable", "message": f"{what} cannot be read"}, status_code=500)


def _model_result(root: registry.Root, model: str, name: str) -> BaseModel | None:
    """A model's evaluation (``eval.json``) or benchmark (``bench.json``) over its current versions."""
    return (
        registry.model_eval(root, model) if name == registry.EVAL_FILE else registry.model_bench(root, model)
    )


def _add_measurements(app: FastAPI, root: registry.Root, keys_on: bool) -> None:
    """``/artifacts/{model}[/{version}]/{name}``: the models' evaluations and benchmarks."""

    def shown(model: str) -> bool:
        """The dashboard's server takes no API key: with keys on, it answers only for models everybody
        sees (no owner file, or published), as the other services do for a key that is not the owner's."""
        return not keys_on or tenancy.visible(tenancy.read(root, model), caller="", operator=False)

    @app.get("/artifacts/{model}")
    def measured(model: str) -> JSONResponse:
        """Which of a model's measurements ``/artifacts/{model}/{name}`` has (``{"model", "measured":
        ["eval.json", "bench.json"]}``), so that the dashboard asks for those alone: a model uploaded
        and trained has an evaluation but no benchmark, and a 404 per model is noise in the console."""
        listed = []
        for name in MEASUREMENTS if shown(model) else ():
            try:
                if _model_result(root, model, name) is None:
                    continue
            except registry.ArtifactError as exc:
                if exc.what in ("model", "version", "substeps"):
                    continue  # unreadable ones are listed: asking for them says what is wrong
            listed.append(name)
        return JSONResponse({"model": model, "measured": listed}, headers={"Cache-Control": "no-cache"})

    @app.get("/artifacts/{model}/{name}")
    def measurements(model: str, name: str) -> Response:
        """A model's evaluation or benchmark over its current versions (``eval.json``: ``ModelEval``,
        ``bench.json``: ``ModelBench``), when measured."""
        what = f"{name} for model {model!r}"
        if name not in MEASUREMENTS or not shown(model):
            return _answer(None, what)
        try:
            found = _model_result(root, model, name)
        except registry.ArtifactError as exc:
            return _unreadable(exc, what)
        return _answer(found, what)

    @app.get("/artifacts/{model}/{version}/{name}")
    def version_measurements(model: str, version: str, name: str) -> Response:
        """One version's evaluation or benchmark (``VersionEval``, ``VersionBench``), when measured."""
        what = f"{name} for version {version!r} of model {model!r}"
        if name not in MEASUREMENTS or not shown(model):
            return _answer(None, what)
        try:
            path = registry.resolve(root, model, version)
            found = registry.read_eval(path) if name == registry.EVAL_FILE else registry.read_bench(path)
        except registry.ArtifactError as exc:
            return _unreadable(exc, what)
        return _answer(found, what)


def _add_dashboard(app: FastAPI, dist: Path) -> None:
    """The built dashboard at ``/``, or a page that says how to build it."""
    if (dist / "index.html").is_file():
        app.mount("/", StaticFiles(directory=dist, html=True), name="dashboard")
    else:
        log.warning("no built dashboard in %s; / explains how to build it", dist)

        @app.get("/", response_class=HTMLResponse)
        def not_built() -> str:
            return NOT_BUILT.format(dist=dist)
