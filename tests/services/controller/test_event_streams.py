"""The live event streams at their edges: a stream whose Redis goes away ends with an ``error`` event
(SSE and websocket), the first stream after Redis restarted does not, and the job websocket of another
key's job is closed with 4404, not refused."""

from __future__ import annotations

import json

import pytest
from starlette.websockets import WebSocketDisconnect

from tests.services.controller.ctl import QUICK, Controller, ctl_fixture  # noqa: F401
from tests.services.private_redis import PrivateRedis, private_redis_fixture  # noqa: F401


def test_another_keys_job_websocket_closes_4404(ctl: Controller) -> None:
    api = ctl.client(api_keys="alpha,beta")
    job_id = api.post("/jobs", json=QUICK, headers={"X-API-Key": "alpha"}).json()["id"]
    for path in (f"/ws/jobs/{job_id}?api_key=beta", "/ws/jobs/nope?api_key=alpha"):
        with pytest.raises(WebSocketDisconnect) as info, api.websocket_connect(path) as ws:
            ws.receive_json()
        assert info.value.code == 4404, path
    with api.websocket_connect(f"/ws/jobs/{job_id}?api_key=alpha") as ws:
        assert ws.receive_json()["event"] == "status"


def test_an_event_stream_takes_its_key_in_the_query_and_plain_calls_do_not(ctl: Controller) -> None:
    """A browser's EventSource cannot send headers: ``?api_key=`` works on ``.../events``, and only there
    (a plain call with its key in the address would leave it in every proxy's log)."""
    api = ctl.client(api_keys="alpha,beta", sse_keepalive_s=0.5)
    job_id = api.post("/jobs", json=QUICK, headers={"X-API-Key": "alpha"}).json()["id"]
    with api.stream("GET", f"/jobs/{job_id}/events?api_key=alpha") as r:
        assert r.status_code == 200
        first = next(line for line in r.iter_lines() if line.startswith("event: "))
    assert first == "event: status"
    assert api.get(f"/jobs/{job_id}/events?api_key=wrong").status_code == 401
    assert api.get(f"/jobs/{job_id}?api_key=alpha").status_code == 401
    assert api.get(f"/jobs/{job_id}", headers={"Authorization": "Bearer alpha"}).status_code == 200


def test_sse_ends_with_an_error_event_when_redis_goes_away(
    ctl: Controller, private_redis: PrivateRedis
) -> None:
    ctl.env["REDIS_URL"] = private_redis.url
    api = ctl.client(sse_keepalive_s=0.5)
    job_id = api.post("/jobs", json=QUICK).json()["id"]  # no worker: it stays queued
    events: list[tuple[str, str]] = []
    with api.stream("GET", f"/jobs/{job_id}/events") as r:
        assert r.status_code == 200
        event = ""
        for line in r.iter_lines():
            if line.startswith("event: "):
                event = line.removeprefix("event: ")
            elif line.startswith("data: "):
                events.append((event, line.removeprefix("data: ")))
                if event == "status":
                    private_redis.stop()
    assert [e for e, _ in events] == ["status", "error"]
    assert json.loads(events[-1][1])["error"] == "redis_unavailable"


def test_the_job_websocket_ends_with_an_error_event_when_redis_goes_away(
    ctl: Controller, private_redis: PrivateRedis
) -> None:
    ctl.env["REDIS_URL"] = private_redis.url
    api = ctl.client(sse_keepalive_s=0.5)
    job_id = api.post("/jobs", json=QUICK).json()["id"]
    with api.websocket_connect(f"/ws/jobs/{job_id}") as ws:
        assert ws.receive_json()["event"] == "status"
        private_redis.stop()
        last = ws.receive_json()
        assert (
            last == {"event": "error", "data": last["data"]} and last["data"]["error"] == "redis_unavailable"
        )
        with pytest.raises(WebSocketDisconnect) as info:
            ws.receive_json()
        assert info.value.code == 1011


def _events(api: object, job_id: str) -> list[str]:
    with api.stream("GET", f"/jobs/{job_id}/events") as r:  # type: ignore[attr-defined]
        assert r.status_code == 200
        return [line.removeprefix("event: ") for line in r.iter_lines() if line.startswith("event: ")]


def test_the_first_streams_after_a_redis_restart_are_whole(
    ctl: Controller, private_redis: PrivateRedis
) -> None:
    """The API's pooled connections to the Redis before its restart are dead: the stream's reads
    reconnect rather than end with ``redis_unavailable``."""
    ctl.env["REDIS_URL"] = private_redis.url
    api = ctl.client()

    def cancelled_job() -> str:  # no worker: cancelled while queued, it has its end event at once
        job_id: str = api.post("/jobs", json=QUICK).json()["id"]
        assert api.delete(f"/jobs/{job_id}").status_code == 202
        return job_id

    assert _events(api, cancelled_job()) == ["status", "end"]
    private_redis.restart()
    assert _events(api, cancelled_job()) == ["status", "end"]
    with api.websocket_connect(f"/ws/jobs/{cancelled_job()}") as ws:
        assert [ws.receive_json()["event"] for _ in range(2)] == ["status", "end"]
