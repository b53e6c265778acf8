"""``create_app(settings)``: the emulator service as a FastAPI app, plus health and metrics."""

from __future__ import annotations

import asyncio
import contextlib
import gc
import logging
from collections.abc import AsyncIterator, Callable

from fastapi import FastAPI, Response
from fastapi.middleware.cors import CORSMiddleware
from fastapi.responses import JSONResponse, PlainTextResponse

from services.common.auth import ApiKeyMiddleware, ApiKeys
from services.common.docs import add_offline_docs
from services.common.limits import limit_bodies
from services.common.openapi import METRICS_RESPONSES, METRICS_TYPE, document_errors, readiness_responses
from services.emulator.deps import ServiceDep
from services.emulator.error_mapping import add_http_handlers
from services.emulator.fastpath import BinaryStepRoute
from services.emulator.persistence import Persistence
from services.emulator.routes import models, sessions, step
from services.emulator.service import EmulatorService
from services.emulator.settings import Settings
from services.emulator.ws import SessionSocketRoute

log = logging.getLogger(__name__)


def create_app(settings: Settings | None = None) -> FastAPI:
    """The app for these settings; artifacts are loaded now, so it is ready when this returns."""
    settings = settings or Settings()
    service = EmulatorService(settings)
    keys = ApiKeys.of(settings)
    persistence = Persistence(service)
    app = FastAPI(
        title="NeuroAnimator emulator service",
        version="0.1.0",
        lifespan=_lifespan(settings, service, persistence, keys),
        docs_url=None,
        redoc_url=None,
    )
    add_offline_docs(app)  # /docs and /redoc with packaged assets: they work offline
    app.state.service = service
    app.state.persistence = persistence
    _add_middleware(app, settings, service, keys)
    add_http_handlers(app)
    for r in (models.router, sessions.router, step.router):
        app.include_router(r)
    _add_ops_routes(app, persistence)
    document_errors(app)
    return app


def _lifespan(
    settings: Settings, service: EmulatorService, persistence: Persistence, keys: ApiKeys
) -> Callable[[FastAPI], contextlib.AbstractAsyncContextManager[None]]:
    """What the app does when it starts (restore sessions, start the sweeper and the checkpoints)
    and when it stops (stop them, close the service)."""

    @contextlib.asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        await persistence.start()  # restores this replica's sessions; Redis down: starts degraded
        # Everything loaded so far (libraries, emulators, restored sessions) lives as long as the process:
        # move it out of the collector's view, and collect young objects less often, so that the
        # collector's pauses (which land on whichever step is in flight) stay short under load.
        gc.collect()
        gc.freeze()
        gc.set_threshold(*settings.gc_thresholds)
        sweeper = asyncio.create_task(service.sweep_forever(), name="session-sweeper")
        checkpointer = None
        if persistence.enabled:
            checkpointer = asyncio.create_task(persistence.run_forever(), name="session-checkpoints")
        log.info(
            "emulator service up",
            extra={
                "models": service.registry.models(),
                "api_keys": len(keys),
                "persistence": persistence.status,
            },
        )
        try:
            yield
        finally:
            for task in (sweeper, checkpointer):
                if task is not None:
                    task.cancel()
                    with contextlib.suppress(asyncio.CancelledError):
                        await task
            await persistence.close()
            await service.close()

    return lifespan


def _add_middleware(app: FastAPI, settings: Settings, service: EmulatorService, keys: ApiKeys) -> None:
    """The fast paths, the key check, the body limits and CORS, innermost first."""
    # innermost first: the binary POST /step and websocket fast paths see the caller the key check set
    app.add_middleware(BinaryStepRoute, service=service)
    app.add_middleware(SessionSocketRoute, service=service)
    if keys.enabled:
        app.add_middleware(ApiKeyMiddleware, keys=keys)
    # every body bounded before it is read (even by a caller without a key): large ones on the stepping
    # and pose endpoints only
    big = settings.max_body_bytes
    json_step = settings.max_json_body_bytes
    limit_bodies(
        app,
        settings.small_body_bytes,
        per_path=[("/step", big), ("/models/[^/]+/poses", big)],
        json_per_path=[("/step", json_step, step.json_batch_too_large(json_step))],
    )
    origins = settings.cors_list()
    if origins:  # added last, so outermost: preflight requests are answered before the key check
        app.add_middleware(
            CORSMiddleware,
            allow_origins=origins,
            allow_methods=["*"],
            allow_headers=["*"],
            max_age=600,
        )


def _add_ops_routes(app: FastAPI, persistence: Persistence) -> None:
    """``/healthz``, ``/readyz`` and ``/metrics``."""

    @app.get("/healthz", tags=["ops"])
    async def healthz() -> dict[str, str]:
        """Liveness: the process answers."""
        return {"status": "ok"}

    @app.get(
        "/readyz",
        tags=["ops"],
        response_class=JSONResponse,
        responses=readiness_responses("no models loaded"),
    )
    async def readyz(service: ServiceDep) -> Response:
        """Readiness: at least one emulator is loaded (503 otherwise); says whether sessions persist."""
        names = service.registry.models()
        # "off", "ok" or "degraded" (Redis unreachable: serving, not persisting), asked of Redis now
        p = await persistence.check()
        if not names:
            return JSONResponse({"status": "no models loaded", "persistence": p}, status_code=503)
        return JSONResponse({"status": "ready", "persistence": p})

    @app.get("/metrics", tags=["ops"], response_class=PlainTextResponse, responses=METRICS_RESPONSES)
    async def metrics(service: ServiceDep) -> Response:
        """Prometheus metrics: step latency, batch sizes, ORT time, sessions, divergences."""
        service.update_gauges()
        return Response(service.metrics.render(), media_type=METRICS_TYPE)
