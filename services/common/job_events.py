"""A job's events, live, as server-sent events: ``job_events(...)`` answers ``GET .../{id}/events``.

The stream replays the job's event stream from Redis from the start (or after ``Last-Event-ID``) and
then follows it: ``status`` (queued, running, re-queued with why), ``progress`` and one last ``end``
(the final status), after which it closes. Browsers' ``EventSource`` cannot send headers, so with API
keys on the event streams take ``?api_key=<key>`` as well (``QueryKeyMiddleware``). When Redis goes
away mid-stream, it ends with an ``error`` event (``{"error": "redis_unavailable", "message"}``)
rather than being cut: a client knows to reconnect (with ``Last-Event-ID``) later.
"""

from __future__ import annotations

import json
import logging
import re
from collections.abc import AsyncIterator
from typing import Any
from urllib.parse import parse_qs

import redis
import redis.asyncio as aioredis
from fastapi.responses import StreamingResponse
from starlette.types import ASGIApp, Receive, Scope, Send

from services.common.jobs import JobStore
from services.common.openapi import Responses

log = logging.getLogger(__name__)
STREAM_ID = re.compile(r"^\d+-\d+$")
REDIS_GONE = {
    "error": "redis_unavailable",
    "message": "Redis (the job queue) stopped answering: this stream ends here; reconnect later",
}
SSE_RESPONSES: Responses = {
    200: {
        "content": {"text/event-stream": {}},
        "description": "status, progress and end events (an error event when Redis goes away)",
    }
}


async def follow(
    aredis: aioredis.Redis, store: JobStore, job_id: str, after: str, keepalive_s: float
) -> AsyncIterator[tuple[str, str, str]]:
    """(event, stream id, JSON data) from ``after`` on, until ``end``; ("", "", "") after each idle
    ``keepalive_s``. A job whose records expired ends with ``expired``."""
    key, last = store.keys.events(job_id), after
    while True:
        resp: Any = await aredis.xread({key: last}, count=200, block=max(1, int(keepalive_s * 1000)))
        if not resp:
            if not await aredis.exists(store.keys.job(job_id)):
                yield "end", "", json.dumps({"status": "expired", "reason": "the job's records expired"})
                return
            yield "", "", ""
            continue
        for _key, entries in resp:
            for eid, fields in entries:
                last = eid.decode()
                event = fields[b"event"].decode()
                yield event, last, fields[b"data"].decode()
                if event == "end":
                    return


def job_events(
    aredis: aioredis.Redis, store: JobStore, job_id: str, last_event_id: str | None, keepalive_s: float
) -> StreamingResponse:
    """The SSE response of a job's events (the caller checked that the job is the caller's)."""
    after = last_event_id if last_event_id and STREAM_ID.match(last_event_id) else "0"

    async def body() -> AsyncIterator[str]:
        yield "retry: 2000\n\n"
        try:
            async for event, eid, data in follow(aredis, store, job_id, after, keepalive_s):
                if not event:
                    yield ": keep-alive\n\n"
                    continue
                head = f"id: {eid}\n" if eid else ""
                yield f"{head}event: {event}\ndata: {data}\n\n"
        except (redis.RedisError, OSError) as exc:
            log.warning("event stream ended: Redis unreachable", extra={"job": job_id, "error": str(exc)})
            yield f"event: error\ndata: {json.dumps(REDIS_GONE)}\n\n"

    return StreamingResponse(
        body(),
        media_type="text/event-stream",
        headers={"Cache-Control": "no-cache", "X-Accel-Buffering": "no"},  # no proxy buffering
    )


class QueryKeyMiddleware:
    """Copies ``?api_key=`` into the ``X-API-Key`` header for the event streams: a browser's
    ``EventSource`` cannot set headers (websockets already take the query parameter)."""

    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if (
            scope["type"] == "http"
            and scope["path"].endswith("/events")
            and b"api_key=" in scope["query_string"]
        ):
            key = parse_qs(scope["query_string"].decode()).get("api_key", [""])[0]
            headers = [(k, v) for k, v in scope["headers"] if k != b"x-api-key"]
            scope = {**scope, "headers": [*headers, (b"x-api-key", key.encode())]}
        await self.app(scope, receive, send)
