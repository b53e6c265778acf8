"""Websocket lock-step mode: controls in, next state out; malformed messages get a typed error and the
connection keeps working."""

from __future__ import annotations

import numpy as np
import pytest
from fastapi.testclient import TestClient
from starlette.websockets import WebSocketDisconnect

from services.emulator import binary


def test_lock_step_equals_rest(client: TestClient) -> None:
    a = client.post("/sessions", json={"model": "lander", "seed": 2}).json()
    b = client.post("/sessions", json={"model": "lander", "seed": 2}).json()
    u = [0.0, 0.5, -0.5, 0.0]
    with client.websocket_connect(f"/ws/sessions/{a['id']}") as ws:
        for k in range(3):
            ws.send_json({"type": "step", "controls": u, "seq": k})
            msg = ws.receive_json()
            assert msg["type"] == "state" and msg["seq"] == k and msg["steps"] == k + 1
            rest = client.post(f"/sessions/{b['id']}/step", json={"controls": u}).json()
            np.testing.assert_array_equal(msg["state"], rest["state"])
        ws.send_json({"type": "ping", "seq": 9})
        assert ws.receive_json() == {"type": "pong", "seq": 9}
    assert client.get(f"/sessions/{a['id']}").json()["steps"] == 3  # kept after the disconnect


@pytest.mark.parametrize(
    ("send", "error", "needle"),
    [
        ("not json", "malformed_json", "not JSON"),
        ('{"type": "jump"}', "invalid_request", "type"),
        ('{"controls": [0, 0, 0]}', "invalid_request", "type"),
        ('{"type": "step", "controls": [0, 0], "seq": 4}', "wrong_length", "controls must have 3 values"),
        (
            '{"type": "step", "controls": [0, NaN, 0], "seq": 5}',
            "invalid_request",
            "controls[1]: Input should be a finite number",
        ),
        ('{"type": "step", "controls": ["a", 0, 0]}', "invalid_request", "controls[0]"),
        ("[1, 2]", "invalid_request", "body"),
        ("[" * 5000, "malformed_json", "nests arrays and objects too deep"),
        ('{"type": "step", "controls": [1' + "0" * 5000 + ", 0, 0]}", "malformed_json", "more digits"),
    ],
    ids=lambda v: v if len(v) < 60 else f"{v[:20]}...({len(v)} characters)",
)
def test_malformed_message_gets_typed_error_and_connection_survives(
    client: TestClient, send: str, error: str, needle: str
) -> None:
    sid = client.post("/sessions", json={"model": "pendulum-active", "seed": 1}).json()["id"]
    other = client.post("/sessions", json={"model": "pendulum-active", "seed": 1}).json()["id"]
    with (
        client.websocket_connect(f"/ws/sessions/{sid}") as ws,
        client.websocket_connect(f"/ws/sessions/{other}") as ws2,
    ):
        ws.send_text(send)
        msg = ws.receive_json()
        assert msg["type"] == "error" and msg["error"] == error and needle in msg["message"], msg
        if '"seq": ' in send:
            assert msg["seq"] == int(send.split('"seq": ')[1].rstrip("}"))
        ws.send_json({"type": "step", "controls": [0.1, 0.2, 0.3]})
        ok = ws.receive_json()
        assert ok["type"] == "state" and ok["steps"] == 1
        ws2.send_json({"type": "step", "controls": [0.1, 0.2, 0.3]})
        assert ws2.receive_json()["state"] == ok["state"]  # the other client saw nothing of it


def test_binary_frames_round_trip_equal_to_json(client: TestClient) -> None:
    a = client.post("/sessions", json={"model": "lander", "seed": 4}).json()["id"]
    b = client.post("/sessions", json={"model": "lander", "seed": 4}).json()["id"]
    u = np.array([10.0, 0.3, -0.2, 0.1], np.float32)
    with (
        client.websocket_connect(f"/ws/sessions/{a}?format=binary") as wb,
        client.websocket_connect(f"/ws/sessions/{b}") as wj,
    ):
        started = wb.receive_json()
        assert (
            started["type"] == "started" and started["format"] == "binary" and started["mode"] == "lockstep"
        )
        for k in range(3):
            wb.send_bytes(binary.encode_ws_frame(k, u))
            seq, steps, status, state = binary.decode_ws_state(wb.receive_bytes())
            wj.send_json({"type": "step", "controls": u.tolist(), "seq": k})
            msg = wj.receive_json()
            assert (seq, steps, status) == (k, k + 1, binary.OK)
            np.testing.assert_array_equal(state, np.asarray(msg["state"], np.float32))
        wb.send_bytes(binary.encode_ws_frame(None, np.array([99.0, 0, 0, 0], np.float32)))
        seq, steps, status, _ = binary.decode_ws_state(wb.receive_bytes())
        assert (seq, steps, status) == (None, 4, binary.CLIPPED)
        # a JSON step on a binary-format connection is answered in binary too
        wb.send_json({"type": "step", "controls": u.tolist(), "seq": 7})
        assert binary.decode_ws_state(wb.receive_bytes())[:2] == (7, 5)


@pytest.mark.parametrize(
    ("frame", "error", "needle"),
    [
        (b"\x00\x00\x80\x3f", "bad_magic", "must start with b'NAWC'"),
        (binary.encode_ws_frame(1, np.zeros(2, np.float32)), "wrong_length", "is 20 bytes"),
        (binary.encode_ws_frame(2, np.array([0, np.nan, 0], np.float32)), "not_finite", "controls[1] is nan"),
    ],
)
def test_malformed_binary_frame_gets_json_error(
    client: TestClient, frame: bytes, error: str, needle: str
) -> None:
    sid = client.post("/sessions", json={"model": "pendulum-active", "seed": 1}).json()["id"]
    with client.websocket_connect(f"/ws/sessions/{sid}") as ws:
        ws.send_bytes(frame)
        msg = ws.receive_json()
        assert msg["type"] == "error" and msg["error"] == error and needle in msg["message"], msg
        ws.send_json({"type": "step", "controls": [0, 0, 0]})
        assert ws.receive_json()["steps"] == 1


def test_bad_query_mode_is_error_and_close(client: TestClient) -> None:
    sid = client.post("/sessions", json={"model": "pendulum-active", "seed": 1}).json()["id"]
    with client.websocket_connect(f"/ws/sessions/{sid}?mode=fast") as ws:
        msg = ws.receive_json()
        assert msg["type"] == "error" and msg["field"] == "mode"
        with pytest.raises(WebSocketDisconnect) as exc:
            ws.receive_json()
        assert exc.value.code == 4422


def test_unknown_session_gets_error_then_close(client: TestClient) -> None:
    with client.websocket_connect("/ws/sessions/r0-nope") as ws:
        msg = ws.receive_json()
        assert msg["type"] == "error" and msg["error"] == "unknown_session"
        with pytest.raises(WebSocketDisconnect) as exc:
            ws.receive_json()
        assert exc.value.code == 4404
