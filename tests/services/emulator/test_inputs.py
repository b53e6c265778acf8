"""The one in-range check of every transport: the trained range's own edges are in range (float32 bounds,
float32 inputs), just beyond them is clipped, over REST, the binary batch and websockets alike."""

from __future__ import annotations

import numpy as np
import pytest
from fastapi.testclient import TestClient

from neuroanimator.core.manifest import ControlInput
from neuroanimator.core.model_spec import ForceInput
from services.emulator import binary
from services.emulator.errors import BadInput
from services.emulator.inputs import InputRange

OCTET = {"content-type": "application/octet-stream"}


def _range() -> InputRange:
    # 32.4 rounds up in float32 (32.400001525878906) and -0.1 rounds down (-0.10000000149011612): an
    # input at either edge, once float32, lies beyond the float64 bound by a rounding error
    controls = [
        ControlInput(name="main_jet", low=0.0, high=32.4, limit_low=0.0, limit_high=32.4),
        ControlInput(name="trim", low=-0.1, high=0.7, limit_low=-0.1, limit_high=0.7),
    ]
    forces = [ForceInput(name="push", body="b", component=0, low=-2.3, high=2.3)]
    return InputRange(controls, forces)


@pytest.mark.parametrize("edge", ["low", "high"])
def test_the_edges_are_in_range_in_every_form(edge: str) -> None:
    r = _range()
    values = [0.0, -0.1, -2.3] if edge == "low" else [32.4, 0.7, 2.3]
    checked = r.check_lists(values[:2], values[2:], "model 'm'")
    assert not checked.clipped and checked.clipped_controls == [] and checked.clipped_forces == []
    np.testing.assert_array_equal(checked.row, np.asarray(values, np.float32))
    row = np.asarray(values, np.float32)
    assert not r.check_row(row).clipped
    assert r.fits(tuple(row.tolist()))  # a binary frame's values, unpacked as Python floats


def test_just_beyond_the_edges_is_clipped_to_them() -> None:
    r = _range()
    hi = np.nextafter(np.asarray([32.4, 0.7, 2.3], np.float32), np.float32(np.inf))
    lo = np.nextafter(np.asarray([0.0, -0.1, -2.3], np.float32), np.float32(-np.inf))
    for beyond, edge in ((hi, r.high), (lo, r.low)):
        assert not r.fits(tuple(beyond.tolist()))
        checked = r.check_row(beyond)
        assert checked.clipped_controls == [0, 1] and checked.clipped_forces == [0]
        np.testing.assert_array_equal(checked.row, edge)
    checked = r.check_lists([40.0, 0.0], [0.0], "model 'm'")
    assert checked.clipped_controls == [0] and checked.row[0] == np.float32(32.4)


def test_nan_is_named_not_clipped() -> None:
    r = _range()
    with pytest.raises(BadInput) as exc:
        r.check_row(np.asarray([1.0, 0.0, np.nan], np.float32))
    assert exc.value.code == "not_finite" and exc.value.field == "forces[0]"
    assert not r.fits((1.0, 0.0, float("nan")))


# ---------------------------------------------------------------- every transport, at the lander's edges
def _edges(client: TestClient) -> list[list[float]]:
    """The lander's lowest and highest inputs, from its manifest (main_jet's high is 32.4)."""
    controls = client.get("/models/lander").json()["controls"]
    assert controls[0]["name"] == "main_jet" and controls[0]["high"] == 32.4
    return [[c["low"] for c in controls], [c["high"] for c in controls]]


def _lander(client: TestClient) -> str:
    sid: str = client.post("/sessions", json={"model": "lander", "seed": 1}).json()["id"]
    return sid


def test_edges_over_rest_and_the_json_batch(client: TestClient) -> None:
    for u in _edges(client):
        r = client.post(f"/sessions/{_lander(client)}/step", json={"controls": u}).json()
        assert r["clipped"] is False and r["clipped_controls"] == []
        res = client.post("/step", json={"items": [{"session": _lander(client), "controls": u}]}).json()
        assert res["results"][0]["clipped"] is False
    beyond = client.post(f"/sessions/{_lander(client)}/step", json={"controls": [32.41, 0, 0, 0]}).json()
    assert beyond["clipped"] is True and beyond["clipped_controls"] == [0]


def test_edges_over_the_binary_batch(client: TestClient) -> None:
    low, high = _edges(client)
    u = np.asarray([low, high, [32.41, 0, 0, 0]], np.float32)
    body = binary.encode_batch_request([_lander(client) for _ in range(3)], u)
    status, _ = binary.decode_batch_response(client.post("/step", content=body, headers=OCTET).content)
    assert status.tolist() == [binary.OK, binary.OK, binary.CLIPPED]


def test_edges_over_websockets(client: TestClient) -> None:
    low, high = _edges(client)
    with client.websocket_connect(f"/ws/sessions/{_lander(client)}?format=binary") as ws:
        assert ws.receive_json()["type"] == "started"
        for u in (low, high):
            ws.send_json({"type": "step", "controls": u})  # answered in binary on this connection
            assert binary.decode_ws_state(ws.receive_bytes())[2] == binary.OK
            ws.send_bytes(binary.encode_ws_frame(1, np.asarray(u, np.float32)))
            assert binary.decode_ws_state(ws.receive_bytes())[2] == binary.OK
        ws.send_bytes(binary.encode_ws_frame(2, np.asarray([32.41, 0, 0, 0], np.float32)))
        assert binary.decode_ws_state(ws.receive_bytes())[2] == binary.CLIPPED
    with client.websocket_connect(f"/ws/sessions/{_lander(client)}") as ws:
        for u in (low, high):
            ws.send_json({"type": "step", "controls": u})
            msg = ws.receive_json()
            assert msg["type"] == "state" and msg["clipped"] is False
        ws.send_json({"type": "step", "controls": [32.41, 0, 0, 0]})
        assert ws.receive_json()["clipped_controls"] == [0]
