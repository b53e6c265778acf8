"""Websocket real-time mode: the server pushes a state every Δt (scaled down here) with the latest
controls; a slow or vanished client holds up nobody and is noticed; its session outlives it."""

from __future__ import annotations

import asyncio
import base64
import itertools
import json
import os
import socket
import threading
import time
from collections.abc import Callable, Iterator
from typing import Any

import numpy as np
import pytest
import uvicorn
from fastapi import FastAPI
from fastapi.testclient import TestClient
from starlette.types import Message, Receive, Scope, Send
from websockets.sync.client import connect

from neuroanimator.contracts.emulator import SessionCreate
from services.emulator import binary
from services.emulator.app import create_app
from services.emulator.service import EmulatorService
from services.emulator.settings import Settings
from services.emulator.ws import SessionSocketRoute
from services.emulator.ws.transport import LatestQueue
from tests.helpers import service_of


def _drain_until_started(ws: Any) -> None:
    for _ in range(1000):
        msg = ws.receive_json()
        if msg["type"] == "started":
            return
    raise AssertionError("no started message")


def test_realtime_pushes_states_at_about_the_period(make_client: Callable[..., TestClient]) -> None:
    client = make_client(ws_realtime_scale=0.1)  # test models: Δt = 0.1 s -> one state per 10 ms
    sid = client.post("/sessions", json={"model": "pendulum-active", "seed": 3}).json()["id"]
    with client.websocket_connect(f"/ws/sessions/{sid}") as ws:
        ws.send_json({"type": "start", "mode": "realtime", "seq": 1})
        started = ws.receive_json()
        assert started["type"] == "started" and started["mode"] == "realtime" and started["seq"] == 1
        assert started["period_s"] == pytest.approx(0.01) and started["super_timestep"] == pytest.approx(0.1)
        t0 = time.monotonic()
        states = []
        while time.monotonic() - t0 < 0.5:
            states.append(ws.receive_json())
        ws.send_json({"type": "start", "mode": "lockstep"})
        _drain_until_started(ws)
        ws.send_json({"type": "step", "controls": [0, 0, 0], "seq": 5})  # lock-step works again
        after = ws.receive_json()
    assert all(m["type"] == "state" for m in states)
    steps = [m["steps"] for m in states]
    assert steps == sorted(set(steps))  # one state per step, in order
    assert 10 <= len(states) <= 80, len(states)  # ~50 expected; loose on purpose
    assert after["seq"] == 5 and after["steps"] > steps[-1]
    assert client.get(f"/sessions/{sid}").json()["steps"] == after["steps"]


def test_realtime_latest_controls_win(make_client: Callable[..., TestClient]) -> None:
    client = make_client(ws_realtime_scale=0.1)
    emu = service_of(client).registry.get("pendulum-active").emulator
    sid = client.post("/sessions", json={"model": "pendulum-active", "seed": 3}).json()["id"]
    c = np.array([0.5, -1.0, 1.5], np.float32)
    with client.websocket_connect(f"/ws/sessions/{sid}?mode=realtime") as ws:
        assert ws.receive_json()["type"] == "started"
        ws.send_json({"type": "controls", "controls": [2, 2, 2], "seq": 1})
        ws.send_json({"type": "controls", "controls": [-2, -2, -2], "seq": 2})
        ws.send_json({"type": "controls", "controls": c.tolist(), "seq": 3})
        seen = []
        for _ in range(200):
            m = ws.receive_json()
            assert m["type"] == "state"
            seen.append(m)
            pairs = [(a, b) for a, b in itertools.pairwise(seen) if b["seq"] == 3]
            if any(b["steps"] == a["steps"] + 1 for a, b in pairs):
                break
        ws.send_json({"type": "step", "controls": [0, 0, 0], "seq": 9})
        for _ in range(100):  # a step message in real-time mode is a typed error; the stream goes on
            m = ws.receive_json()
            if m["type"] == "error":
                assert m["error"] == "wrong_mode" and m["seq"] == 9
                break
    seqs = [m["seq"] for m in seen]
    first3 = seqs.index(3)
    assert all(s == 3 for s in seqs[first3:])  # once the latest controls are in, older never return
    a, b = next((a, b) for a, b in itertools.pairwise(seen) if b["seq"] == 3 and b["steps"] == a["steps"] + 1)
    want = emu.step(np.asarray([a["state"]], np.float32), c[None])[0]
    np.testing.assert_allclose(np.asarray(b["state"], np.float32), want, rtol=0, atol=1e-6)


@pytest.mark.parametrize("frames", ["json", "binary"])
def test_realtime_goes_on_with_the_last_lockstep_inputs(
    make_client: Callable[..., TestClient], frames: str
) -> None:
    """The README's example: lock-step steps, then real time with no controls message: each real-time
    step uses the last lock-step step's controls (not zeros), in JSON and in binary frames."""
    client = make_client(ws_realtime_scale=0.1)
    emu = service_of(client).registry.get("pendulum-active").emulator
    sid = client.post("/sessions", json={"model": "pendulum-active", "seed": 3}).json()["id"]
    c = np.array([0.5, -1.0, 1.5], np.float32)
    with client.websocket_connect(f"/ws/sessions/{sid}") as ws:
        for seq in range(3):
            if frames == "json":
                ws.send_json({"type": "step", "controls": c.tolist(), "seq": seq})
                ws.receive_json()
            else:
                ws.send_bytes(binary.encode_ws_frame(seq, c))  # the answer: a JSON state
                ws.receive_json()
        ws.send_json({"type": "start", "mode": "realtime", "format": "json"})
        _drain_until_started(ws)
        a, b = ws.receive_json(), ws.receive_json()
    assert b["steps"] == a["steps"] + 1
    want = emu.step(np.asarray([a["state"]], np.float32), c[None])[0]
    np.testing.assert_allclose(np.asarray(b["state"], np.float32), want, rtol=0, atol=1e-6)


def test_realtime_binary_frames(make_client: Callable[..., TestClient]) -> None:
    client = make_client(ws_realtime_scale=0.1)
    sid = client.post("/sessions", json={"model": "pendulum-active", "seed": 3}).json()["id"]
    with client.websocket_connect(f"/ws/sessions/{sid}?mode=realtime&format=binary") as ws:
        assert ws.receive_json()["format"] == "binary"
        ws.send_bytes(binary.encode_ws_frame(42, np.array([9.0, 0, 0], np.float32)))
        for _ in range(200):
            seq, steps, status, state = binary.decode_ws_state(ws.receive_bytes())
            if seq == 42:
                break
        assert status == binary.CLIPPED and steps >= 1 and state.shape == (6,)


def test_latest_queue_drops_oldest() -> None:
    import asyncio

    async def run() -> tuple[list[int], int]:
        q: LatestQueue[int] = LatestQueue(2)
        for i in range(5):
            q.put(i)
        return [await q.get(), await q.get()], q.dropped

    assert asyncio.run(run()) == ([3, 4], 3)


# ---------------------------------------------------------------- a real server over loopback
@pytest.fixture
def live(make_settings: Callable[..., Any]) -> Iterator[tuple[FastAPI, int]]:
    """The service in a uvicorn thread with fast websocket pings and a 1 ms real-time period."""
    app = create_app(make_settings(ws_realtime_scale=0.01, ws_send_timeout_s=0.5))
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    cfg = uvicorn.Config(
        app, host="127.0.0.1", port=port, log_level="warning", ws_ping_interval=0.2, ws_ping_timeout=0.3
    )
    server = uvicorn.Server(cfg)
    th = threading.Thread(target=server.run, daemon=True)
    th.start()
    deadline = time.monotonic() + 20
    while not server.started:
        assert time.monotonic() < deadline and th.is_alive(), "uvicorn did not start"
        time.sleep(0.02)
    yield app, port
    server.should_exit = True
    th.join(10)


def _raw_realtime_client(port: int, sid: str) -> socket.socket:
    """A websocket client that completes the handshake, then never reads nor answers pings."""
    s = socket.socket()
    s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
    s.connect(("127.0.0.1", port))
    key = base64.b64encode(os.urandom(16)).decode()
    s.sendall(
        (
            f"GET /ws/sessions/{sid}?mode=realtime&format=json HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\n"
            f"Upgrade: websocket\r\nConnection: Upgrade\r\nSec-WebSocket-Key: {key}\r\n"
            "Sec-WebSocket-Version: 13\r\n\r\n"
        ).encode()
    )
    head = b""
    while b"\r\n\r\n" not in head:
        head += s.recv(1)
    assert head.startswith(b"HTTP/1.1 101"), head
    return s


def test_slow_and_vanished_clients_block_nobody(live: tuple[FastAPI, int]) -> None:
    app, port = live
    import httpx

    base = f"http://127.0.0.1:{port}"
    slow_id = httpx.post(f"{base}/sessions", json={"model": "lander", "seed": 1}).json()["id"]
    a = httpx.post(f"{base}/sessions", json={"model": "pendulum-active", "seed": 2}).json()
    b = httpx.post(f"{base}/sessions", json={"model": "pendulum-active", "seed": 2}).json()
    raw = _raw_realtime_client(port, slow_id)  # pushed ~1000 states/s, reads none of them
    try:
        deadline = time.monotonic() + 5
        while not any(c.sid == slow_id for c in app.state.service.connections):
            assert time.monotonic() < deadline, "the raw client's connection never started"
            time.sleep(0.01)
        with connect(f"ws://127.0.0.1:{port}/ws/sessions/{a['id']}") as ws:
            for k in range(50):  # lock-step goes on at full speed beside it
                ws.send(f'{{"type": "step", "controls": [0.1, 0.2, 0.3], "seq": {k}}}')
                msg = ws.recv(timeout=5)
                assert f'"seq":{k}' in msg
            rest = httpx.post(
                f"{base}/sessions/{b['id']}/step", json={"controls": [0.1, 0.2, 0.3], "steps": 50}
            ).json()
            got = json.loads(msg)
            np.testing.assert_allclose(got["state"], rest["state"], rtol=0, atol=1e-6)
        # the raw client never answers pings (or reads): the server notices and ends its connection
        deadline = time.monotonic() + 10
        while any(c.sid == slow_id for c in app.state.service.connections):
            assert time.monotonic() < deadline, "the vanished client was not noticed"
            time.sleep(0.05)
    finally:
        raw.close()
    info = httpx.get(f"{base}/sessions/{slow_id}").json()  # kept until its TTL
    assert info["steps"] > 0 and not info["diverged"]


def test_a_client_gone_before_started_leaves_no_ticker(make_settings: Callable[..., Settings]) -> None:
    service = EmulatorService(make_settings(ws_realtime_scale=0.1))  # a tick every 10 ms

    async def main() -> None:
        sess = service.create_session(SessionCreate(model="pendulum-active", seed=0))
        inbox: list[dict[str, Any]] = [{"type": "websocket.connect"}]

        async def receive() -> dict[str, Any]:
            if inbox:
                return inbox.pop(0)
            await asyncio.sleep(3600)
            raise AssertionError("unreachable")

        async def send(message: Message) -> None:
            if message["type"] == "websocket.send":
                raise OSError("the client closed right after the handshake")

        async def app(scope: Scope, receive: Receive, send: Send) -> None:
            raise AssertionError("the route passed a session's websocket on")

        scope = {"type": "websocket", "path": f"/ws/sessions/{sess.id}", "query_string": b"mode=realtime"}
        await SessionSocketRoute(app, service)(scope, receive, send)
        steps = sess.steps
        await asyncio.sleep(0.3)  # more than a real-time period of the test settings
        assert sess.steps == steps
        assert not [t for t in asyncio.all_tasks() if t.get_name().startswith(("ws-tick", "ws-push"))]
        assert not service.connections

    asyncio.run(main())
