"""Binary ``POST /step`` (proto/frames.md): the same states as JSON, per-session status bytes, and
malformed bodies answered with a JSON 4xx naming the problem (nothing stepped)."""

from __future__ import annotations

import struct
from collections.abc import Callable
from typing import Any

import numpy as np
import pytest
from fastapi.testclient import TestClient

from services.emulator import binary
from tests.helpers import service_of

OCTET = {"content-type": "application/octet-stream"}


def _sessions(client: TestClient, n: int, model: str = "pendulum-active", seed0: int = 0) -> list[str]:
    return [client.post("/sessions", json={"model": model, "seed": seed0 + i}).json()["id"] for i in range(n)]


def _post(client: TestClient, body: bytes) -> Any:
    return client.post("/step", content=body, headers=OCTET)


def test_binary_and_json_give_identical_states(client: TestClient) -> None:
    n = 7
    a, b = _sessions(client, n), _sessions(client, n)
    rng = np.random.default_rng(0)
    for _ in range(3):
        u = rng.uniform(-1.5, 1.5, (n, 3)).astype(np.float32)
        js = client.post(
            "/step", json={"items": [{"session": s, "controls": u[i].tolist()} for i, s in enumerate(a)]}
        ).json()["results"]
        r = _post(client, binary.encode_batch_request(b, u))
        assert r.status_code == 200 and r.headers["content-type"] == "application/octet-stream"
        status, states = binary.decode_batch_response(r.content)
        assert status.tolist() == [binary.OK] * n and states.shape == (n, 6)
        np.testing.assert_allclose(
            states, np.asarray([x["state"] for x in js], np.float32), rtol=0, atol=1e-6
        )
    assert {client.get(f"/sessions/{s}").json()["steps"] for s in b} == {3}


def test_status_bytes_clipped_unknown_and_one_ort_call(client: TestClient) -> None:
    service = service_of(client)
    ids = _sessions(client, 3)
    before = np.asarray([client.get(f"/sessions/{s}").json()["state"] for s in ids], np.float32)
    u = np.array([[0, 0, 0], [5, 0, 0], [0, 0, 0]], np.float32)  # row 1 is out of range: clipped
    calls0 = service.stepper.ort_calls
    r = _post(client, binary.encode_batch_request([*ids[:2], "r0-gone", ids[2]], np.insert(u, 2, 0, axis=0)))
    status, states = binary.decode_batch_response(r.content)
    assert service.stepper.ort_calls - calls0 == 1
    assert status.tolist() == [binary.OK, binary.CLIPPED, binary.UNKNOWN, binary.OK]
    assert np.isnan(states[2]).all()
    emu = service.registry.get("pendulum-active").emulator
    want = emu.step(before, np.array([[0, 0, 0], [2, 0, 0], [0, 0, 0]], np.float32))
    np.testing.assert_allclose(states[[0, 1, 3]], want, rtol=0, atol=1e-6)


def test_diverged_session_status(client: TestClient, diverging_state: list[float]) -> None:
    bad = client.post("/sessions", json={"model": "pendulum-active", "state": diverging_state}).json()["id"]
    good = _sessions(client, 1)[0]
    body = binary.encode_batch_request([bad, good], np.zeros((2, 3), np.float32))
    status, states = binary.decode_batch_response(_post(client, body).content)
    assert status.tolist() == [binary.DIVERGED, binary.OK]
    np.testing.assert_array_equal(states[0], [3, 0, 0, 0, 0, 0])  # its last finite state
    status, _ = binary.decode_batch_response(_post(client, body).content)
    assert status.tolist() == [binary.DIVERGED, binary.OK]
    assert client.get(f"/sessions/{good}").json()["steps"] == 2


def _header(count: int, width: int = 24, magic: bytes = b"NAST", version: int = 1) -> bytes:
    return struct.pack("<4sHHIHH", magic, version, 0, count, width, 0)


def _cases(ids: list[str], lander: str) -> list[tuple[bytes, int, str, str]]:
    ok = binary.encode_batch_request(ids, np.zeros((2, 3), np.float32))
    nan = binary.encode_batch_request(ids, np.array([[0, 0, 0], [0, np.nan, 0]], np.float32))
    inf = binary.encode_batch_request(ids, np.array([[0, 0, np.inf], [0, 0, 0]], np.float32))
    wrong_count = bytearray(ok)
    struct.pack_into("<I", wrong_count, 8, 3)  # the header says 3 sessions, the body holds 2
    mixed = binary.encode_batch_request([ids[0], lander], np.zeros((2, 3), np.float32))
    dup = binary.encode_batch_request([ids[0], ids[0]], np.zeros((2, 3), np.float32))
    return [
        (b"NAST\x01\x00", 422, "malformed_binary", "shorter than the 16-byte header"),
        (b"XXXX" + ok[4:], 422, "bad_magic", "expected the magic b'NAST'"),
        (_header(2, version=9) + ok[16:], 422, "unsupported_version", "version 9"),
        (ok[:-4], 422, "wrong_length", "must be"),
        (bytes(wrong_count), 422, "wrong_length", "the header says 3 sessions"),
        (_header(2, width=0), 422, "bad_id_width", "1..256"),
        (nan, 422, "not_finite", "items[1].controls[1]"),
        (inf, 422, "not_finite", "items[0].controls[2]"),
        (mixed, 422, "mixed_models", "one binary request steps sessions of one model version"),
        (dup, 422, "duplicate_session", "more than once"),
    ]


@pytest.mark.parametrize("case", range(10))
def test_malformed_binary_is_4xx_naming_the_problem_and_steps_nothing(client: TestClient, case: int) -> None:
    ids = _sessions(client, 2)
    lander = _sessions(client, 1, "lander")[0]
    body, code, error, needle = _cases(ids, lander)[case]
    r = _post(client, body)
    assert r.status_code == code and r.headers["content-type"] == "application/json"
    b = r.json()
    assert b["error"] == error and needle in b["message"], b
    assert all(client.get(f"/sessions/{s}").json()["steps"] == 0 for s in [*ids, lander])


def test_binary_batch_over_max_is_413(make_client: Callable[..., TestClient]) -> None:
    c = make_client(max_batch=3)
    ids = _sessions(c, 4)
    r = _post(c, binary.encode_batch_request(ids, np.zeros((4, 3), np.float32)))
    assert r.status_code == 413
    b = r.json()
    assert b["error"] == "batch_too_large" and "at most 3 items" in b["message"] and b["got"] == 4
    assert all(c.get(f"/sessions/{s}").json()["steps"] == 0 for s in ids)


def test_unknown_sessions_only_and_other_content_types(client: TestClient) -> None:
    r = _post(client, binary.encode_batch_request(["r0-a", "r0-b"], np.zeros((2, 3), np.float32)))
    status, states = binary.decode_batch_response(r.content)
    assert status.tolist() == [binary.UNKNOWN] * 2 and states.shape == (2, 0)
    r = client.post("/step", content=b"items", headers={"content-type": "text/plain"})
    assert r.status_code == 415 and r.json()["error"] == "unsupported_media_type"
    r = client.post("/step", content=b"{not json", headers={"content-type": "application/json"})
    assert r.status_code == 422 and r.json()["error"] == "malformed_json"


def test_binary_body_over_the_cap_is_413_and_parameters_are_ignored(
    make_client: Callable[..., TestClient],
) -> None:
    c = make_client(max_batch=2)
    r = _post(c, b"NAST" + b"\0" * 5000)
    assert r.status_code == 413 and r.json()["error"] == "body_too_large"
    assert "MAX_BATCH=2" in r.json()["message"]
    ids = _sessions(c, 2)
    body = binary.encode_batch_request(ids, np.zeros((2, 3), np.float32))
    r = c.post("/step", content=body, headers={"content-type": "Application/Octet-Stream; x=1"})
    assert r.status_code == 200 and binary.decode_batch_response(r.content)[0].tolist() == [binary.OK] * 2
