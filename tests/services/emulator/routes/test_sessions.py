"""Session lifecycle, REST stepping equal to ``OnnxEmulator.step``, frames, expiry."""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
from fastapi.testclient import TestClient

from neuroanimator.export.runtime import OnnxEmulator
from tests.helpers import service_of


def _emulator(client: TestClient, model: str) -> OnnxEmulator:
    version = client.get(f"/models/{model}").json()["version"]
    root: Path = service_of(client).settings.artifacts_dir
    return OnnxEmulator(root / model / version / "emulator.onnx")


def test_lifecycle(client: TestClient) -> None:
    r = client.post("/sessions", json={"model": "pendulum-active", "seed": 7})
    assert r.status_code == 201
    s = r.json()
    assert s["id"].startswith("r0-")
    assert (s["model"], s["steps"], s["t"], s["diverged"], s["seed"]) == ("pendulum-active", 0, 0.0, False, 7)
    assert len(s["state"]) == 6
    assert client.get(f"/sessions/{s['id']}").json()["state"] == s["state"]
    assert client.delete(f"/sessions/{s['id']}").status_code == 204
    r = client.get(f"/sessions/{s['id']}")
    assert r.status_code == 404 and r.json()["error"] == "unknown_session"
    assert client.delete(f"/sessions/{s['id']}").status_code == 404


def test_seeded_start_is_typical_and_deterministic(client: TestClient) -> None:
    a = client.post("/sessions", json={"model": "lander", "seed": 3}).json()
    b = client.post("/sessions", json={"model": "lander", "seed": 3}).json()
    c = client.post("/sessions", json={"model": "lander", "seed": 4}).json()
    assert a["state"] == b["state"] != c["state"]
    d = client.post("/sessions", json={"model": "lander"}).json()
    assert isinstance(d["seed"], int)
    q = np.asarray(a["state"][3:7])
    assert abs(np.linalg.norm(q) - 1) < 1e-5


def test_given_state_quaternion_is_normalised(client: TestClient) -> None:
    state = [0.0, 0.0, 5.0, 2.0, 0.0, 0.0, 0.0, 0.1, 0.0, 0.0, 0.0, 0.0, 0.0]
    s = client.post("/sessions", json={"model": "lander", "state": state}).json()
    assert s["state"][3:7] == [1.0, 0.0, 0.0, 0.0]
    assert s["seed"] is None


def test_rest_step_equals_onnx_step(client: TestClient) -> None:
    emu = _emulator(client, "pendulum-active")
    s = client.post("/sessions", json={"model": "pendulum-active", "seed": 11}).json()
    u = [0.5, -1.0, 1.5]
    r = client.post(f"/sessions/{s['id']}/step", json={"controls": u})
    assert r.status_code == 200
    out = r.json()
    want = emu.step(np.asarray([s["state"]], np.float32), np.asarray([u], np.float32))[0]
    np.testing.assert_array_equal(np.asarray(out["state"], np.float32), want)
    assert out["steps"] == 1 and not out["clipped"] and out["clipped_controls"] == []
    assert client.get(f"/sessions/{s['id']}").json()["state"] == out["state"]


def test_multi_step_equals_rollout(client: TestClient) -> None:
    emu = _emulator(client, "lander")
    s = client.post("/sessions", json={"model": "lander", "seed": 5}).json()
    u = [100.0, 0.0, 1.0, -1.0]
    mid = client.get("/models/lander").json()["controls"]
    u = [min(max(v, c["low"]), c["high"]) for v, c in zip(u, mid, strict=True)]
    out = client.post(f"/sessions/{s['id']}/step", json={"controls": u, "steps": 4}).json()
    want = emu.rollout(np.asarray([s["state"]], np.float32), np.asarray([[u] * 4], np.float32))[0, 1:]
    np.testing.assert_allclose(np.asarray(out["states"]), want, rtol=0, atol=1e-6)
    assert out["state"] == out["states"][-1]
    assert out["steps"] == 4
    assert abs(out["t"] - 4 * client.get("/models/lander").json()["super_timestep"]) < 1e-9


def test_frames_endpoints_exact_and_unit_quaternions(client: TestClient) -> None:
    s = client.post("/sessions", json={"model": "lander", "seed": 9}).json()
    r = client.post(
        f"/sessions/{s['id']}/step", json={"controls": [0, 0, 0, 0], "steps": 3, "frames_per_step": 5}
    )
    out = r.json()
    fr = np.asarray(out["frames"])
    assert fr.shape == (3 * 5 + 1, 13)
    np.testing.assert_array_equal(fr[0], np.asarray(s["state"], np.float32))
    for k in range(3):
        np.testing.assert_array_equal(fr[5 * (k + 1)], np.asarray(out["states"][k], np.float32))
    np.testing.assert_allclose(np.linalg.norm(fr[:, 3:7], axis=1), 1.0, atol=1e-6)
    assert out["frames"] is not None
    assert client.post(f"/sessions/{s['id']}/step", json={"controls": [0, 0, 0, 0]}).json()["frames"] is None


def test_idle_sessions_expire(make_client: Callable[..., TestClient]) -> None:
    c = make_client(session_ttl_s=0.2)
    sid = c.post("/sessions", json={"model": "pendulum-active", "seed": 1}).json()["id"]
    time.sleep(0.1)
    assert c.get(f"/sessions/{sid}").status_code == 200  # use restarts the idle clock
    time.sleep(0.25)
    assert c.get(f"/sessions/{sid}").status_code == 404
    store = service_of(c).store
    sid2 = c.post("/sessions", json={"model": "pendulum-active", "seed": 1}).json()["id"]
    time.sleep(0.25)
    assert store.expire() == 1 and sid2 not in store.sessions


def test_slots_are_reused(client: TestClient) -> None:
    store = service_of(client).store
    ids = [
        client.post("/sessions", json={"model": "pendulum-active", "seed": i}).json()["id"] for i in range(70)
    ]
    pool = store.sessions[ids[0]].pool
    assert pool.states.shape[0] == 128 and pool.used == 70  # grew once, contiguous
    for sid in ids[:10]:
        client.delete(f"/sessions/{sid}")
    client.post("/sessions", json={"model": "pendulum-active", "seed": 99})
    assert pool.used == 61 and pool.states.shape[0] == 128
    # the survivors' states survived the growth
    s = client.get(f"/sessions/{ids[-1]}").json()
    assert (
        s["state"] == client.post("/sessions", json={"model": "pendulum-active", "seed": 69}).json()["state"]
    )
