"""The session table as arrays: a repeated binary id list answered from the store's cache still sees
deletions, slot reuse, expiry and key ownership; bulk locks exclude single-session steps and wake them."""

from __future__ import annotations

import asyncio
import time
from collections.abc import Callable
from typing import Any

import numpy as np
import pytest
from fastapi.testclient import TestClient

from neuroanimator.contracts.emulator import SessionCreate
from services.emulator import binary
from services.emulator.fastpath import binary_step
from services.emulator.service import EmulatorService
from services.emulator.sessions import Session
from services.emulator.settings import Settings

OCTET = {"content-type": "application/octet-stream"}
ZERO = [0.0, 0.0, 0.0]


def _step(
    c: TestClient, ids: list[str], headers: dict[str, str] | None = None
) -> tuple[list[int], np.ndarray]:
    body = binary.encode_batch_request(ids, np.zeros((len(ids), 3), np.float32))
    r = c.post("/step", content=body, headers={**OCTET, **(headers or {})})
    assert r.status_code == 200, r.text
    status, states = binary.decode_batch_response(r.content)
    return status.tolist(), states


def _new(c: TestClient, n: int, headers: dict[str, str] | None = None) -> list[str]:
    return [
        c.post("/sessions", json={"model": "pendulum-active", "seed": i}, headers=headers).json()["id"]
        for i in range(n)
    ]


def test_repeated_id_list_sees_deletion_and_slot_reuse(client: TestClient) -> None:
    ids = _new(client, 4)
    for _ in range(2):  # the second request is answered from the id-list cache
        assert _step(client, ids)[0] == [binary.OK] * 4
    assert client.delete(f"/sessions/{ids[1]}").status_code == 204
    reused = _new(client, 1)[0]  # takes the freed slot
    status, states = _step(client, ids)
    assert status == [binary.OK, binary.UNKNOWN, binary.OK, binary.OK]
    assert np.isnan(states[1]).all()
    assert client.get(f"/sessions/{reused}").json()["steps"] == 0  # the slot's new owner was not stepped
    assert [client.get(f"/sessions/{s}").json()["steps"] for s in ids[::2]] == [3, 3]


def test_repeated_id_list_sees_expiry(make_client: Callable[..., TestClient]) -> None:
    c = make_client(session_ttl_s=0.3)
    ids = _new(c, 3)
    assert _step(c, ids)[0] == [binary.OK] * 3
    time.sleep(0.45)
    assert _step(c, ids)[0] == [binary.UNKNOWN] * 3
    assert c.get(f"/sessions/{ids[0]}").status_code == 404


def test_repeated_id_list_of_another_key_is_unknown(make_client: Callable[..., TestClient]) -> None:
    c = make_client(api_keys="alpha,beta")
    alpha, beta = {"x-api-key": "alpha"}, {"x-api-key": "beta"}
    ids = _new(c, 3, alpha)
    for _ in range(2):
        assert _step(c, ids, alpha)[0] == [binary.OK] * 3
    assert _step(c, ids, beta)[0] == [binary.UNKNOWN] * 3  # the same bytes, cached for alpha
    assert {c.get(f"/sessions/{s}", headers=alpha).json()["steps"] for s in ids} == {2}


def test_bulk_and_single_steps_of_one_session_exclude_each_other(
    make_settings: Callable[..., Settings],
) -> None:
    service = EmulatorService(make_settings(max_wait_ms=5.0))

    async def run() -> None:
        ids = [service.create_session(SessionCreate(model="pendulum-active", seed=i)).id for i in range(8)]
        body = binary.encode_batch_request(ids, np.zeros((8, 3), np.float32))
        one = service.store.get(ids[3])
        # a 20-step REST request on session 3 and two bulk requests over all 8, at once
        single = asyncio.create_task(
            service.stepper.step(one, service.stepper.check(one.emu, ZERO, []), steps=20)
        )
        bulks = [asyncio.create_task(binary_step(service, body)) for _ in range(2)]
        await asyncio.gather(single, *bulks)
        for b in bulks:
            assert binary.decode_batch_response(b.result())[0].tolist() == [binary.OK] * 8
        pool = one.pool
        assert not pool.busy.any() and not pool.waiters
        steps = [service.store.get(s).steps for s in ids]
        assert steps == [2, 2, 2, 22, 2, 2, 2, 2]

    asyncio.run(run())


def test_session_deleted_while_its_bulk_step_is_in_flight(
    make_settings: Callable[..., Settings], monkeypatch: pytest.MonkeyPatch
) -> None:
    service = EmulatorService(make_settings())
    loaded = service.registry.get("pendulum-active")
    real = loaded.emulator.step
    newcomers: list[Session] = []

    def deleting(*args: Any, **kw: Any) -> np.ndarray:  # the ORT call; the session goes meanwhile
        assert service.store.delete(ids[0])
        newcomers.append(service.create_session(SessionCreate(model="pendulum-active", seed=9)))
        return real(*args, **kw)

    async def run() -> None:
        monkeypatch.setattr(loaded.emulator, "step", deleting)
        body = binary.encode_batch_request(ids, np.zeros((3, 3), np.float32))
        status, states = binary.decode_batch_response(await binary_step(service, body))
        assert status.tolist() == [binary.UNKNOWN, binary.OK, binary.OK]
        assert np.isnan(states[0]).all()
        newcomer = newcomers[0]
        assert newcomer.slot == 0  # the deleted session's slot, handed out again
        assert newcomer.steps == 0 and not newcomer.lock.locked()
        assert [service.store.get(s).steps for s in ids[1:]] == [1, 1]

    ids = [service.create_session(SessionCreate(model="pendulum-active", seed=i)).id for i in range(3)]
    asyncio.run(run())


def test_sessions_of_another_key_or_expired_are_unknown_before_the_model_check(
    make_client: Callable[..., TestClient],
) -> None:
    c = make_client(api_keys="alpha,beta", session_ttl_s=1.0)
    alpha, beta = {"x-api-key": "alpha"}, {"x-api-key": "beta"}
    old = c.post("/sessions", json={"model": "lander", "seed": 1}, headers=beta).json()["id"]
    time.sleep(1.2)
    theirs = c.post("/sessions", json={"model": "lander", "seed": 0}, headers=alpha).json()["id"]
    mine = _new(c, 1, beta)[0]
    # alpha's lander and beta's expired lander neither fail the request (mixed_models) nor shape it
    assert _step(c, [theirs, old, mine], beta)[0] == [binary.UNKNOWN, binary.UNKNOWN, binary.OK]
    body = binary.encode_batch_request([theirs], np.zeros((1, 3), np.float32))  # 3 inputs: beta's guess
    r = c.post("/step", content=body, headers={**OCTET, **beta})  # alone: not a wrong_length for lander
    assert r.status_code == 200 and binary.decode_batch_response(r.content)[0].tolist() == [binary.UNKNOWN]
    assert c.get(f"/sessions/{theirs}", headers=alpha).json()["steps"] == 0
    assert c.get(f"/sessions/{old}", headers=beta).status_code == 404


def test_a_cached_id_block_cut_at_another_width_is_other_ids(client: TestClient) -> None:
    ids = _new(client, 2)
    body = binary.encode_batch_request(ids, np.zeros((2, 3), np.float32))
    assert _step(client, ids)[0] == [binary.OK] * 2  # the block is cached now
    width = binary.REQUEST_HEADER.unpack_from(body)[4]
    block = body[16 : 16 + 2 * width]
    one = binary.REQUEST_HEADER.pack(binary.REQUEST_MAGIC, 1, 0, 1, 2 * width, 0) + block + bytes(12)
    r = client.post("/step", content=one, headers=OCTET)
    assert r.status_code == 200 and binary.decode_batch_response(r.content)[0].tolist() == [binary.UNKNOWN]
