"""Dynamic batching: concurrent requests share ORT calls and equal stepping one by one; divergence
of one session leaves the others untouched."""

from __future__ import annotations

import asyncio
from collections.abc import Callable
from typing import Any

import httpx
import numpy as np
from fastapi.testclient import TestClient

from neuroanimator.export.runtime import OnnxEmulator
from services.emulator.app import create_app
from services.emulator.settings import Settings
from tests.helpers import service_of


def _controls(n: int, seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).uniform(-2, 2, (n, 3)).astype(np.float32)


def test_concurrent_requests_share_ort_calls(make_settings: Callable[..., Settings]) -> None:
    app = create_app(make_settings(max_wait_ms=20.0))
    service = app.state.service
    n = 48
    u = _controls(n)

    async def run() -> tuple[list[dict[str, Any]], list[dict[str, Any]]]:
        transport = httpx.ASGITransport(app=app)
        async with httpx.AsyncClient(transport=transport, base_url="http://test") as c:
            created = [
                (await c.post("/sessions", json={"model": "pendulum-active", "seed": i})).json()
                for i in range(n)
            ]
            calls0 = service.stepper.ort_calls
            rs = await asyncio.gather(
                *(
                    c.post(f"/sessions/{s['id']}/step", json={"controls": u[i].tolist()})
                    for i, s in enumerate(created)
                )
            )
            assert all(r.status_code == 200 for r in rs)
            assert service.stepper.ort_calls - calls0 < n / 4, (
                f"{service.stepper.ort_calls - calls0} ORT calls for {n} requests"
            )
            return created, [r.json() for r in rs]

    created, outs = asyncio.run(run())
    emu: OnnxEmulator = service.registry.get("pendulum-active").emulator
    x = np.asarray([s["state"] for s in created], np.float32)
    one_by_one = np.stack([emu.step(x[i : i + 1], u[i : i + 1])[0] for i in range(n)])
    got = np.asarray([o["state"] for o in outs], np.float32)
    np.testing.assert_allclose(got, one_by_one, rtol=0, atol=1e-6)
    text = TestClient(app).get("/metrics").text
    assert 'emulator_batch_size_count{model="pendulum-active"}' in text


def test_batch_endpoint_mixed_models_one_call_per_model(client: TestClient) -> None:
    service = service_of(client)
    pend = [client.post("/sessions", json={"model": "pendulum-active", "seed": i}).json() for i in range(5)]
    land = [client.post("/sessions", json={"model": "lander", "seed": i}).json() for i in range(3)]
    u = _controls(5, 1)
    items = [{"session": s["id"], "controls": u[i].tolist()} for i, s in enumerate(pend)]
    items += [{"session": s["id"], "controls": [0, 0, 0, 0]} for s in land]
    items.append({"session": "r0-gone", "controls": [0, 0, 0]})
    calls0 = service.stepper.ort_calls
    r = client.post("/step", json={"items": items})
    assert r.status_code == 200
    res = r.json()["results"]
    assert service.stepper.ort_calls - calls0 == 2  # one per model
    assert [x["session"] for x in res] == [it["session"] for it in items]
    assert res[-1]["state"] is None and res[-1]["error"]["error"] == "unknown_session"
    emu = service.registry.get("pendulum-active").emulator
    want = emu.step(np.asarray([s["state"] for s in pend], np.float32), u)
    np.testing.assert_allclose(np.asarray([x["state"] for x in res[:5]], np.float32), want, atol=1e-6)
    assert all(x["error"] is None and len(x["state"]) == 13 for x in res[5:8])


def test_divergence_marks_only_that_session(client: TestClient, diverging_state: list[float]) -> None:
    bad = client.post("/sessions", json={"model": "pendulum-active", "state": diverging_state}).json()
    good = client.post("/sessions", json={"model": "pendulum-active", "state": [0.5, 0, 0, 0, 0, 0]}).json()
    r = client.post(
        "/step",
        json={
            "items": [
                {"session": bad["id"], "controls": [0, 0, 0]},
                {"session": good["id"], "controls": [0, 0, 0]},
            ]
        },
    )
    res = r.json()["results"]
    assert res[0]["error"]["error"] == "diverged" and "non-finite" in res[0]["error"]["message"]
    assert res[1]["error"] is None and res[1]["state"] != good["state"]
    info = client.get(f"/sessions/{bad['id']}").json()
    assert info["diverged"] is True and info["state"] == bad["state"] and info["steps"] == 0
    r = client.post(f"/sessions/{bad['id']}/step", json={"controls": [0, 0, 0]})
    assert r.status_code == 409 and r.json()["error"] == "diverged"
    r = client.post(f"/sessions/{good['id']}/step", json={"controls": [0, 0, 0]})
    assert r.status_code == 200 and r.json()["steps"] == 2
