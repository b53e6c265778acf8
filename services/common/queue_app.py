"""``queue_app(...)``: the FastAPI app of a service with a job queue (the controller, the trainer).

Such an API validates and queues jobs and reads their progress from Redis; it runs none itself (its
workers do). When Redis is down it still starts: calls that need Redis answer 503 with a message
(``redis_unavailable``, with ``Retry-After``), and ``/readyz`` says why it is not ready. Every such app
has: offline ``/docs`` and ``/redoc``; API keys (with ``?api_key=`` on event streams); bounded bodies;
CORS for the dashboard; the project's JSON errors; ``/healthz``, ``/readyz`` (Redis, the live workers,
the queue's depth, plus what the service adds) and ``/metrics``; an async Redis client for the event
streams at ``app.state.aredis``, and the settings, store and metrics at ``app.state``.
"""

from __future__ import annotations

import contextlib
import logging
from collections.abc import AsyncIterator, Awaitable, Callable, Sequence
from typing import Any, Protocol
from urllib.parse import urlsplit, urlunsplit

import redis
import redis.asyncio as aioredis
from fastapi import APIRouter, FastAPI, Request, Response
from fastapi.middleware.cors import CORSMiddleware
from fastapi.responses import JSONResponse, PlainTextResponse
from redis.asyncio.retry import Retry
from redis.backoff import ExponentialBackoff

from neuroanimator.contracts.emulator import ErrorBody
from services.common.auth import ApiKeyMiddleware, ApiKeys
from services.common.docs import add_offline_docs
from services.common.errors import ApiError, add_error_handlers
from services.common.job_events import QueryKeyMiddleware
from services.common.jobs import JobStore, QueueFull, QueueSettings
from services.common.limits import limit_bodies
from services.common.openapi import METRICS_RESPONSES, METRICS_TYPE, document_errors, readiness_responses

log = logging.getLogger(__name__)


class QueueMetrics(Protocol):
    """What the app needs of a service's metrics: its text, and the count of refused submissions."""

    rejected: Any

    def render(self) -> bytes: ...


Ready = Callable[[], tuple[dict[str, object], tuple[str, str] | None]]
"""The service's own readiness: (fields for ``/readyz``, and when it is not ready (status, why))."""


def queue_full(exc: QueueFull) -> ApiError:
    """The 503 of a submission to a full queue, naming the limit (``MAX_QUEUE``) as its field."""
    return ApiError(
        503, "queue_full", str(exc), field="MAX_QUEUE", expected=f"<= {exc.limit}", got=exc.depth + 1
    )


def redacted(url: str) -> str:
    """A Redis URL without its password, for messages."""
    parts = urlsplit(url)
    if parts.password:
        host = parts.hostname or ""
        netloc = f"{parts.username or ''}:***@{host}" + (f":{parts.port}" if parts.port else "")
        return urlunsplit(parts._replace(netloc=netloc))
    return url


def connect(settings: QueueSettings) -> redis.Redis:
    """The API's Redis connection (lazy: made before Redis answers)."""
    return redis.Redis.from_url(
        settings.redis_url,
        socket_connect_timeout=settings.redis_timeout_s,
        socket_timeout=settings.redis_timeout_s,
    )


def queue_app(
    settings: QueueSettings,
    *,
    title: str,
    store: JobStore,
    metrics: QueueMetrics,
    routers: Sequence[APIRouter],
    submit_path: str,
    ready: Ready,
    not_ready: str,
    per_path_limits: Sequence[tuple[str, int]] = (),
) -> FastAPI:
    """The app (see the module's text). ``submit_path``: where jobs are POSTed (a refusal there while
    Redis is down is counted); ``ready``: the service's part of ``/readyz``, described by ``not_ready``."""
    keys = ApiKeys.of(settings)
    lifespan = _lifespan(settings, store.r, title, len(keys))
    app = FastAPI(title=title, version="0.1.0", lifespan=lifespan, docs_url=None, redoc_url=None)
    add_offline_docs(app)  # /docs and /redoc with packaged assets: they work offline
    app.state.settings = settings
    app.state.store = store
    app.state.metrics = metrics
    _add_middleware(app, settings, keys, per_path_limits)
    add_error_handlers(app)
    redis_down = _redis_down(metrics, submit_path, redacted(settings.redis_url))
    app.add_exception_handler(redis.ConnectionError, redis_down)
    app.add_exception_handler(redis.TimeoutError, redis_down)
    for r in routers:
        app.include_router(r)
    _add_ops_routes(app, store, metrics, ready, not_ready, redacted(settings.redis_url))
    document_errors(app, everywhere={"503": "Redis (the job queue) does not answer; try again later"})
    return app


def _lifespan(
    settings: QueueSettings, conn: redis.Redis, title: str, keys: int
) -> Callable[[FastAPI], contextlib.AbstractAsyncContextManager[None]]:
    """Open the event streams' async Redis client (``app.state.aredis``) at start; close both clients
    at the end."""

    @contextlib.asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        # Blocking XREADs wait up to SSE_KEEPALIVE_S: the socket timeout must be longer. One quick retry:
        # a pooled connection to a Redis that restarted fails its first command, and without it the
        # first event stream after the restart would end at once with an error event.
        app.state.aredis = aioredis.Redis.from_url(
            settings.redis_url,
            socket_connect_timeout=settings.redis_timeout_s,
            socket_timeout=settings.sse_keepalive_s + 10.0,
            retry=Retry(ExponentialBackoff(cap=0.2, base=0.05), retries=1),
        )
        where = redacted(settings.redis_url)
        log.info(f"{title} up", extra={"redis": where, "queue": settings.queue_name, "api_keys": keys})
        try:
            yield
        finally:
            await app.state.aredis.aclose()
            conn.close()

    return lifespan


def _add_middleware(
    app: FastAPI, settings: QueueSettings, keys: ApiKeys, per_path_limits: Sequence[tuple[str, int]]
) -> None:
    """The key check, the body limits and CORS, innermost first."""
    if keys.enabled:
        app.add_middleware(ApiKeyMiddleware, keys=keys)
        app.add_middleware(QueryKeyMiddleware)
    # before the key check: nobody sends an unbounded body
    limit_bodies(app, settings.max_body_bytes, per_path=per_path_limits)
    origins = settings.cors_list()
    if origins:  # outermost, so that preflight requests are answered before the API-key check
        app.add_middleware(
            CORSMiddleware,
            allow_origins=origins,
            allow_methods=["GET", "POST", "DELETE", "OPTIONS"],
            allow_headers=["Authorization", "X-API-Key", "Content-Type", "Last-Event-ID"],
            expose_headers=["Location"],
        )


def _redis_down(
    metrics: QueueMetrics, submit_path: str, where: str
) -> Callable[[Request, Exception], Awaitable[JSONResponse]]:
    """The handler of a Redis that does not answer: 503 ``redis_unavailable`` with ``Retry-After``."""

    async def redis_down(request: Request, exc: Exception) -> JSONResponse:
        if request.url.path == submit_path and request.method == "POST":
            metrics.rejected.labels("redis_unavailable").inc()
        # where Redis is, and the driver's text (which names host and port), go to the log only
        log.warning("Redis unreachable", extra={"path": request.url.path, "redis": where, "error": str(exc)})
        body = ErrorBody(
            error="redis_unavailable",
            message=f"the job queue is unavailable: Redis does not answer ({type(exc).__name__}); "
            "try again later",
        )
        return JSONResponse(body.model_dump(), status_code=503, headers={"Retry-After": "5"})

    return redis_down


def _add_ops_routes(
    app: FastAPI, store: JobStore, metrics: QueueMetrics, ready: Ready, not_ready: str, where: str
) -> None:
    """``/healthz``, ``/readyz`` and ``/metrics``."""
    conn = store.r

    @app.get("/healthz", tags=["ops"])
    async def healthz() -> dict[str, str]:  # on the event loop: no thread to wait for
        return {"status": "ok"}

    @app.get(
        "/readyz",
        tags=["ops"],
        response_class=JSONResponse,
        responses=readiness_responses(f"Redis does not answer, or {not_ready}"),
    )
    def readyz() -> Response:
        """Ready when Redis answers, the service has what it needs and a worker was heard from lately
        (``WORKER_ALIVE_S``; 503 with the reason if not). ``workers`` counts them."""
        fields, problem = ready()
        try:
            conn.ping()
            workers = store.worker_count()
            depth = store.queue_depth()
        except redis.RedisError as exc:
            log.warning("readyz: Redis unreachable", extra={"redis": where, "error": str(exc)})
            msg = f"Redis does not answer ({type(exc).__name__})"
            return JSONResponse({"status": "redis unavailable", "message": msg}, status_code=503)
        if problem is not None:
            return JSONResponse({"status": problem[0], "message": problem[1]}, status_code=503)
        if workers == 0:  # jobs would be accepted and wait: not ready until a worker is heard from
            body = {"status": "no workers", **fields, "workers": 0, "queue_depth": depth}
            body["message"] = "no worker has been heard from lately: queued jobs wait until one starts"
            return JSONResponse(body, status_code=503)
        return JSONResponse({"status": "ready", **fields, "workers": workers, "queue_depth": depth})

    @app.get("/metrics", tags=["ops"], response_class=PlainTextResponse, responses=METRICS_RESPONSES)
    def metrics_endpoint() -> Response:
        return Response(metrics.render(), media_type=METRICS_TYPE)
