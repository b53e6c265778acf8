"""A driven session: the model's own controller (the runner's running controller) sets the controls
every super-step, on every transport; the client sets the driver's parameters and the forces, and a
MuJoCo shadow runs its own copy of the controller. Over the committed runner emulator."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from fastapi.testclient import TestClient

from neuroanimator.catalog import get as physics_get
from neuroanimator.sim.driver import DriverError, check_params

ARTIFACTS = Path(__file__).resolve().parents[3] / "artifacts"


@pytest.fixture
def runner_client(make_client: Callable[..., TestClient]) -> TestClient:
    return make_client(artifacts_dir=ARTIFACTS)


def _root(state: list[float]) -> np.ndarray:
    return np.asarray(state[:3])  # root.pos comes first in the runner's layout


def test_driver_parameters_are_checked_against_the_spec() -> None:
    spec = physics_get("runner").spec.driver
    assert check_params(spec, "runner", {}) == {"speed": 2.0}
    assert check_params(spec, "runner", {"speed": 2.4}) == {"speed": 2.4}  # the top of the range is in it
    for bad, words in (
        ({"speed": 2.41}, "[1.6, 2.4] m/s"),
        ({"speed": float("nan")}, "got nan"),
        ({"pace": 2.0}, "no parameter 'pace'"),
    ):
        with pytest.raises(DriverError, match=words.replace("[", r"\[").replace("]", r"\]")):
            check_params(spec, "runner", bad)
    with pytest.raises(DriverError, match="has no driver"):
        check_params(None, "pendulum-active", {})


def test_the_runner_declares_its_driver(runner_client: TestClient) -> None:
    d = runner_client.get("/models/runner").json()["driver"]
    assert d["name"] == "run" and "factory" not in d
    assert d["params"] == [
        {"name": "speed", "label": "target speed", "unit": "m/s", "low": 1.6, "high": 2.4, "default": 2.0}
    ]


def test_a_driven_session_runs_forward_under_rest_steps_and_takes_a_new_speed(
    runner_client: TestClient,
) -> None:
    r = runner_client.post("/sessions", json={"model": "runner", "driver": {"speed": 1.8}})
    assert r.status_code == 201, r.text
    info = r.json()
    assert info["driver"] == {"speed": 1.8}
    sid = info["id"]
    start = _root(info["state"])
    assert start[2] > 0.8  # a running stride's start, not a random typical state
    # no controls: the driver sets them; a push force is the client's
    r = runner_client.post(f"/sessions/{sid}/step", json={"forces": [0.0, 0.0], "steps": 20})
    assert r.status_code == 200, r.text
    body = r.json()
    assert len(body["states"]) == 20 and body["steps"] == 20
    moved = _root(body["state"]) - start
    assert 0.2 < moved[0] < 1.5 and _root(body["state"])[2] > 0.7  # forward about 0.3 s × 2 m/s, up
    r = runner_client.post(f"/sessions/{sid}/step", json={"forces": [0.0, 0.0], "driver": {"speed": 2.3}})
    assert r.status_code == 200, r.text
    assert runner_client.get(f"/sessions/{sid}").json()["driver"] == {"speed": 2.3}


def test_bad_driver_requests_are_named(runner_client: TestClient) -> None:
    r = runner_client.post("/sessions", json={"model": "runner", "driver": {"speed": 9.0}})
    assert r.status_code == 422 and "[1.6, 2.4]" in r.json()["message"]
    r = runner_client.post("/sessions", json={"model": "runner", "driver": {"speed": "fast"}})
    assert r.status_code == 422
    sid = runner_client.post("/sessions", json={"model": "runner", "driver": {}}).json()["id"]
    r = runner_client.post(f"/sessions/{sid}/step", json={"driver": {"pace": 1.0}})
    assert r.status_code == 422 and "pace" in r.json()["message"]
    assert runner_client.get(f"/sessions/{sid}").json()["driver"] == {"speed": 2.0}  # unchanged
    # a session created without a driver cannot be given parameters, and steps as before
    plain = runner_client.post("/sessions", json={"model": "runner", "seed": 1}).json()["id"]
    r = runner_client.post(f"/sessions/{plain}/step", json={"driver": {"speed": 2.0}})
    assert r.status_code == 422 and r.json()["error"] == "no_driver"
    r = runner_client.post("/sessions", json={"model": "pendulum-active", "driver": {}})
    assert r.status_code == 422 and "has no driver" in r.json()["message"]


def test_a_driven_websocket_session_with_a_shadow_running_its_own_controller(
    runner_client: TestClient,
) -> None:
    sid = runner_client.post("/sessions", json={"model": "runner", "driver": {}}).json()["id"]
    with runner_client.websocket_connect(f"/ws/sessions/{sid}") as ws:
        ws.send_json({"type": "start", "mode": "lockstep", "shadow": True})
        assert ws.receive_json()["shadow"] is True
        states, shadows = [], []
        for k in range(25):
            ws.send_json({"type": "step", "forces": [0.0, 0.0], "seq": k})
            msg = ws.receive_json()
            assert msg["type"] == "state", msg
            states.append(_root(msg["state"]))
            shadows.append(_root(msg["shadow"]["state"]))
        # both run forward, the MuJoCo twin with its own controller, and stay close over 0.4 s
        assert states[-1][0] - states[0][0] > 0.3 and shadows[-1][0] - shadows[0][0] > 0.3
        assert np.linalg.norm(states[-1] - shadows[-1]) < 0.3
        ws.send_json({"type": "step", "forces": [0.0, 0.0], "driver": {"speed": 3.0}, "seq": 99})
        err = ws.receive_json()
        assert err["type"] == "error" and "[1.6, 2.4]" in err["message"] and err["seq"] == 99
    # the binary batch steps a driven session with its driver's controls, whatever the row says
    before = runner_client.get(f"/sessions/{sid}").json()
    r = runner_client.post(
        "/step", json={"items": [{"session": sid, "controls": [0.0] * 29, "forces": [0.0, 0.0]}]}
    )
    assert r.status_code == 200, r.text
    after = runner_client.get(f"/sessions/{sid}").json()
    assert after["steps"] == before["steps"] + 1 and after["state"][2] > 0.7
