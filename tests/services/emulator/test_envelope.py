"""Every step reply says when the new state is outside the envelope of the training states (REST, the
JSON and binary batches, websocket JSON and binary frames); an artifact without an envelope never does."""

from __future__ import annotations

import json
import shutil
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
from fastapi.testclient import TestClient

from services.emulator import binary

OCTET = {"content-type": "application/octet-stream"}
HOVER = [16.2, 0.0, 0.0, 0.0]  # the main jet's 10 N per unit balance 100 kg under lunar gravity


def _states(client: TestClient) -> tuple[list[float], list[float]]:
    """A lander state in the middle of its envelope, and the same with a vertical velocity ten times
    beyond the fastest fall of its training data."""
    detail = client.get("/models/lander").json()
    env = {g["group"]: g for g in detail["envelope"]}
    assert env["position"]["low"] == [None] * 3  # no floor: the lander is translation-invariant
    mid = [(lo + hi) / 2 for lo, hi in zip(env["velocity"]["low"], env["velocity"]["high"], strict=True)]
    spin = [
        (lo + hi) / 2 for lo, hi in zip(*(env["angular_velocity"][k] for k in ("low", "high")), strict=True)
    ]
    inside = [0.0, 0.0, 10.0, 1.0, 0.0, 0.0, 0.0, *mid, *spin]
    outside = [*inside[:9], 10 * env["velocity"]["low"][2], *spin]
    return inside, outside


def _session(client: TestClient, state: list[float]) -> str:
    sid: str = client.post("/sessions", json={"model": "lander", "state": state}).json()["id"]
    return sid


def test_rest_and_the_json_batch(client: TestClient) -> None:
    inside, outside = _states(client)
    out = client.post(f"/sessions/{_session(client, outside)}/step", json={"controls": HOVER}).json()
    assert out["outside_envelope"] is True and out["outside_groups"] == ["velocity"]
    ok = client.post(f"/sessions/{_session(client, inside)}/step", json={"controls": HOVER}).json()
    assert ok["outside_envelope"] is False and ok["outside_groups"] == []
    items = [{"session": _session(client, s), "controls": HOVER} for s in (outside, inside)]
    res = client.post("/step", json={"items": items}).json()["results"]
    assert [r["outside_envelope"] for r in res] == [True, False]
    assert res[0]["outside_groups"] == ["velocity"]
    # several steps: said when any of the new states is out
    many = client.post(f"/sessions/{_session(client, outside)}/step", json={"controls": HOVER, "steps": 3})
    assert many.json()["outside_envelope"] is True


def test_binary_batch(client: TestClient) -> None:
    inside, outside = _states(client)
    ids = [_session(client, outside), _session(client, inside), "r0-gone"]
    body = binary.encode_batch_request(ids, np.asarray([HOVER] * 3, np.float32))
    r = client.post("/step", content=body, headers=OCTET)
    status, _ = binary.decode_batch_response(r.content)
    assert status.tolist() == [binary.OK, binary.OK, binary.UNKNOWN]
    flags = binary.decode_batch_outside(r.content)
    assert flags is not None and flags.tolist() == [True, False, False]


def test_websockets(client: TestClient) -> None:
    inside, outside = _states(client)
    for state, want in ((outside, True), (inside, False)):
        with client.websocket_connect(f"/ws/sessions/{_session(client, state)}") as ws:
            ws.send_json({"type": "step", "controls": HOVER})
            msg = ws.receive_json()
            assert msg["outside_envelope"] is want
            assert msg["outside_groups"] == (["velocity"] if want else [])
        with client.websocket_connect(f"/ws/sessions/{_session(client, state)}?format=binary") as ws:
            ws.receive_json()  # started
            ws.send_bytes(binary.encode_ws_frame(1, np.asarray(HOVER, np.float32)))
            assert binary.ws_state_outside(ws.receive_bytes()) is want


def test_an_artifact_without_an_envelope_is_never_flagged(
    service_root: Path, tmp_path: Path, make_client: Callable[..., TestClient]
) -> None:
    model_dir = tmp_path / "lander"
    shutil.copytree(service_root / "lander", model_dir)
    for manifest in model_dir.glob("*/manifest.json"):
        data: dict[str, Any] = json.loads(manifest.read_text())
        del data["envelope"]
        manifest.write_text(json.dumps(data))
    client = make_client(artifacts_dir=tmp_path)
    assert client.get("/models/lander").json()["envelope"] is None
    state = [0.0, 0.0, 10.0, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0, -1e4, 0.0, 0.0, 0.0]
    out = client.post(f"/sessions/{_session(client, state)}/step", json={"controls": HOVER}).json()
    assert out["outside_envelope"] is False and out["outside_groups"] == []


def test_a_value_the_data_never_moved_is_bounded_by_its_groups_scale() -> None:
    """A node's y in a body that swims in its plane of symmetry: constant in the data, so its bounds
    are 1% of the group's widest range either side, not a float rounding error."""
    from services.emulator.envelope import GROUP_FLOOR, widened

    low = np.array([-4.0, 0.2 - 1e-6, -0.5, -np.inf])
    high = np.array([6.0, 0.2 + 1e-6, 0.5, np.inf])
    lo, hi = widened(low, high)
    assert GROUP_FLOOR * 10.0 == 0.1
    np.testing.assert_allclose(lo[:3], [-4.0, 0.1, -0.5])  # the wide ones as they were
    np.testing.assert_allclose(hi[:3], [6.0, 0.3, 0.5])
    assert lo[3] == -np.inf and hi[3] == np.inf  # unbounded stays unbounded
    # a group with no bounds at all is left alone
    free = np.array([-np.inf, -np.inf])
    assert widened(free, -free)[0].tolist() == free.tolist()
