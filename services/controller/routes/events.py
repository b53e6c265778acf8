"""A job's events, live: ``GET /jobs/{id}/events`` (server-sent events) and ``/ws/jobs/{id}`` (websocket).

Both replay the job's event stream from Redis from the start (or, for SSE, after ``Last-Event-ID``)
and then follow it: ``status`` (queued, running, re-queued with why), ``progress`` (one per
iteration: the ``on_progress`` dict of ``run_job`` and the attempt) and one last ``end`` (the final
status), after which the stream closes. Browsers' ``EventSource`` cannot send headers, so with API
keys on these two take ``?api_key=<key>`` as well.

When Redis goes away mid-stream, both end with an ``error`` event (``{"error": "redis_unavailable",
"message"}``) rather than being cut: a client knows to reconnect (SSE: with ``Last-Event-ID``) later.
A websocket for a job the key does not own (or that does not exist) is accepted and closed with code
4404, as documented, not refused with an HTTP status the browser's API cannot read.
"""

from __future__ import annotations

import contextlib
import json
import logging
from typing import Annotated

import redis
import redis.asyncio as aioredis
from fastapi import APIRouter, Header, Request, WebSocket
from fastapi.responses import StreamingResponse
from starlette.concurrency import run_in_threadpool
from starlette.websockets import WebSocketDisconnect

from neuroanimator.contracts.emulator import ErrorBody
from services.common import job_events as sse
from services.common.auth import OwnerDep, get_owner
from services.common.job_events import REDIS_GONE, SSE_RESPONSES, follow
from services.controller.deps import StoreDep
from services.controller.routes.jobs import owned
from services.controller.store import JobStore

log = logging.getLogger(__name__)
router = APIRouter(tags=["events"])


@router.get(
    "/jobs/{job_id}/events",
    response_class=StreamingResponse,
    responses={**SSE_RESPONSES, 404: {"model": ErrorBody}},
)
async def job_events(
    job_id: str,
    request: Request,
    store: StoreDep,
    owner: OwnerDep,
    last_event_id: Annotated[str | None, Header(description="resume after this event id")] = None,
) -> StreamingResponse:
    """Server-sent events of a job: ``status``, ``progress`` per iteration, then one ``end``."""
    await run_in_threadpool(owned, store, job_id, owner)
    aredis: aioredis.Redis = request.app.state.aredis
    keepalive = request.app.state.settings.sse_keepalive_s
    return sse.job_events(aredis, store, job_id, last_event_id, keepalive)


@router.websocket("/ws/jobs/{job_id}")
async def job_events_ws(websocket: WebSocket, job_id: str) -> None:
    """The same events as JSON messages ``{"event": ..., "data": {...}}``; closes after ``end``."""
    store: JobStore = websocket.app.state.store
    await websocket.accept()  # first: a close before it would reach the browser as HTTP 403
    try:
        rec = await run_in_threadpool(store.record, job_id, await get_owner())
    except redis.RedisError:
        await websocket.send_json({"event": "error", "data": REDIS_GONE})
        await websocket.close(code=1011, reason="Redis unavailable")
        return
    if rec is None:
        await websocket.close(code=4404, reason=f"no job {job_id!r}"[:120])
        return
    aredis: aioredis.Redis = websocket.app.state.aredis
    keepalive = websocket.app.state.settings.sse_keepalive_s
    try:
        async for event, _eid, data in follow(aredis, store, job_id, "0", keepalive):
            if event:
                await websocket.send_json({"event": event, "data": json.loads(data)})
        await websocket.close(code=1000)
    except WebSocketDisconnect:
        pass
    except (redis.RedisError, OSError) as exc:
        log.warning("job websocket ended: Redis unreachable", extra={"job": job_id, "error": str(exc)})
        with contextlib.suppress(WebSocketDisconnect, RuntimeError):
            await websocket.send_json({"event": "error", "data": REDIS_GONE})
            await websocket.close(code=1011, reason="Redis unavailable")
