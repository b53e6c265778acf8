"""Every bad input gets a clear error naming the field, the expected and the got, and harms nothing."""

from __future__ import annotations

from collections.abc import Callable

import pytest
from fastapi.testclient import TestClient


@pytest.fixture
def sid(client: TestClient) -> str:
    sid: str = client.post("/sessions", json={"model": "pendulum-active", "seed": 1}).json()["id"]
    return sid


def test_unknown_model_or_version_is_404(client: TestClient) -> None:
    r = client.post("/sessions", json={"model": "nosuch"})
    assert r.status_code == 404
    b = r.json()
    assert b["error"] == "unknown_model" and b["field"] == "model" and b["got"] == "nosuch"
    assert "unknown model 'nosuch'" in b["message"]
    r = client.post("/sessions", json={"model": "lander", "version": "../../etc"})
    assert r.status_code == 404 and r.json()["error"] == "unknown_version"
    assert "has no version '../../etc'" in r.json()["message"]


def test_unknown_session_is_404(client: TestClient) -> None:
    r = client.post("/sessions/r0-nope/step", json={"controls": [0, 0, 0]})
    assert r.status_code == 404 and "no session 'r0-nope'" in r.json()["message"]


@pytest.mark.parametrize(
    ("body", "field", "expected", "got"),
    [
        ({"controls": [0, 0]}, "controls", 3, 2),
        ({"controls": [0, 0, 0], "forces": [1.0]}, "forces", 0, 1),
        ({"controls": [0, 0, 0, 0]}, "controls", 3, 4),
    ],
)
def test_wrong_length_is_422(
    client: TestClient, sid: str, body: dict[str, object], field: str, expected: int, got: int
) -> None:
    r = client.post(f"/sessions/{sid}/step", json=body)
    assert r.status_code == 422
    b = r.json()
    assert (b["error"], b["field"], b["expected"], b["got"]) == ("wrong_length", field, expected, got)
    assert b["message"] == f"{field} must have {expected} values for model 'pendulum-active', got {got}"
    assert client.get(f"/sessions/{sid}").json()["steps"] == 0


def test_wrong_state_length_is_422(client: TestClient) -> None:
    r = client.post("/sessions", json={"model": "lander", "state": [0.0] * 6})
    b = r.json()
    assert r.status_code == 422 and (b["field"], b["expected"], b["got"]) == ("state", 13, 6)
    assert b["message"] == "state must have 13 values for model 'lander', got 6"


def test_zero_quaternion_is_422(client: TestClient) -> None:
    r = client.post("/sessions", json={"model": "lander", "state": [0.0] * 13})
    assert r.status_code == 422 and r.json()["field"] == "state[3:7]"
    assert "must not be zero" in r.json()["message"]


@pytest.mark.parametrize(
    ("raw", "field", "msg"),
    [
        ('{"controls": [0, NaN, 0]}', "controls[1]", "finite number"),
        ('{"controls": [0, 0, Infinity]}', "controls[2]", "finite number"),
        ('{"controls": [0, -Infinity, 0]}', "controls[1]", "finite number"),
        ('{"controls": [0, 0, 1e400]}', "controls[2]", "finite number"),
        ('{"controls": ["1", 0, 0]}', "controls[0]", "valid number"),
        ('{"controls": [true, 0, 0]}', "controls[0]", "valid number"),
        ('{"controls": "0,0,0"}', "controls", "valid list"),
        ('{"controls": [0, 0, 0], "steps": "2"}', "steps", "valid integer"),
        ('{"controls": [0, 0, 0], "steps": 0}', "steps", "greater than or equal to 1"),
        ('{"controls": [0, 0, 0], "frames_per_step": 0}', "frames_per_step", "greater than or equal to 1"),
        ('{"controls": [0, 0, 0], "speed": 2}', "speed", "Extra inputs are not permitted"),
    ],
)
def test_non_numbers_and_non_finite_are_422(
    client: TestClient, sid: str, raw: str, field: str, msg: str
) -> None:
    r = client.post(f"/sessions/{sid}/step", content=raw, headers={"content-type": "application/json"})
    assert r.status_code == 422, r.text
    b = r.json()
    assert b["error"] == "invalid_request" and b["field"] == field
    assert msg in b["message"] and b["message"].startswith(f"{field}: ")
    assert msg in b["expected"]
    assert client.get(f"/sessions/{sid}").json()["steps"] == 0


def test_beyond_float32_is_422(client: TestClient, sid: str) -> None:
    r = client.post(f"/sessions/{sid}/step", json={"controls": [0, 1e39, 0]})
    b = r.json()
    assert r.status_code == 422 and b["field"] == "controls[1]" and "float32" in b["message"]


def test_malformed_json_is_422(client: TestClient, sid: str) -> None:
    r = client.post(
        f"/sessions/{sid}/step", content="{not json", headers={"content-type": "application/json"}
    )
    assert r.status_code == 422 and r.json()["error"] == "invalid_request"
    assert r.json()["field"] == "body" and "not valid JSON at character 1" in r.json()["message"]


def test_out_of_range_controls_are_clipped_and_reported(client: TestClient, sid: str) -> None:
    rng = client.get("/models/pendulum-active").json()["controls"]
    hi, lo = rng[0]["high"], rng[2]["low"]
    a = client.post("/sessions", json={"model": "pendulum-active", "seed": 1}).json()["id"]
    clipped = client.post(f"/sessions/{sid}/step", json={"controls": [hi + 100, 0.1, lo - 5]}).json()
    assert clipped["clipped"] is True and clipped["clipped_controls"] == [0, 2]
    at_limit = client.post(f"/sessions/{a}/step", json={"controls": [hi, 0.1, lo]}).json()
    assert at_limit["clipped"] is False and at_limit["state"] == clipped["state"]


def test_too_many_steps_is_422(client: TestClient, sid: str) -> None:
    r = client.post(f"/sessions/{sid}/step", json={"controls": [0, 0, 0], "steps": 10**6})
    b = r.json()
    assert r.status_code == 422 and b["field"] == "steps" and "at most 1000" in b["message"]


def test_too_many_sessions_is_429(make_client: Callable[..., TestClient]) -> None:
    c = make_client(max_sessions=2)
    for i in range(2):
        assert c.post("/sessions", json={"model": "lander", "seed": i}).status_code == 201
    r = c.post("/sessions", json={"model": "lander", "seed": 3})
    assert r.status_code == 429
    assert r.json()["error"] == "too_many_sessions" and "maximum of 2 sessions" in r.json()["message"]
    assert (r.json()["field"], r.json()["expected"], r.json()["got"]) == ("MAX_SESSIONS", 2, 3)


def test_batch_over_max_is_413_and_steps_nothing(make_client: Callable[..., TestClient]) -> None:
    c = make_client(max_batch=3)
    ids = [c.post("/sessions", json={"model": "pendulum-active", "seed": i}).json()["id"] for i in range(4)]
    r = c.post("/step", json={"items": [{"session": s, "controls": [0, 0, 0]} for s in ids]})
    assert r.status_code == 413
    b = r.json()
    assert b["error"] == "batch_too_large" and "at most 3 items" in b["message"] and b["got"] == 4
    assert all(c.get(f"/sessions/{s}").json()["steps"] == 0 for s in ids)


def test_batch_bad_item_is_422_and_steps_nothing(client: TestClient) -> None:
    ids = [
        client.post("/sessions", json={"model": "pendulum-active", "seed": i}).json()["id"] for i in range(2)
    ]
    r = client.post(
        "/step",
        json={"items": [{"session": ids[0], "controls": [0, 0, 0]}, {"session": ids[1], "controls": [0]}]},
    )
    b = r.json()
    assert r.status_code == 422 and b["field"] == "items[1].controls" and (b["expected"], b["got"]) == (3, 1)
    r = client.post("/step", json={"items": [{"session": ids[0]}, {"session": ids[0]}]})
    assert r.status_code == 422 and r.json()["error"] == "duplicate_session"
    r = client.post(
        "/step",
        content='{"items": [{"session": "x", "controls": [NaN]}]}',
        headers={"content-type": "application/json"},
    )
    assert r.status_code == 422 and r.json()["field"] == "items[0].controls[0]"
    assert all(client.get(f"/sessions/{s}").json()["steps"] == 0 for s in ids)
