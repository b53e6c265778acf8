"""API keys: off by default; when API_KEYS is set every call but the ops endpoints needs a key, a key
owns its sessions (another key gets 404, in batch stepping and websockets too), and a per-key quota."""

from __future__ import annotations

from collections.abc import Callable

import pytest
from fastapi.testclient import TestClient
from starlette.testclient import WebSocketDenialResponse
from starlette.websockets import WebSocketDisconnect

from services.common.auth import ApiKeys

ALPHA = {"Authorization": "Bearer alpha"}
BETA = {"X-API-Key": "beta"}
PENDULUM = {"model": "pendulum-active", "seed": 1}


@pytest.fixture
def authed(make_client: Callable[..., TestClient]) -> TestClient:
    return make_client(api_keys=" alpha, beta ,", max_sessions_per_key=3)


def test_off_by_default(client: TestClient) -> None:
    assert client.get("/models").status_code == 200
    assert client.post("/sessions", json=PENDULUM).status_code == 201


def test_keys_parsed() -> None:
    keys = ApiKeys(" alpha, beta ,,")
    assert len(keys) == 2 and keys.enabled and not ApiKeys(" , ").enabled
    assert keys.owner("alpha") == keys.id_of("alpha") != keys.owner("beta")
    assert keys.owner("gamma") is None and keys.owner("") is None and keys.owner(None) is None


def test_key_ids_are_keyed_by_the_server_secret() -> None:
    """An id read from a checkpoint or a log cannot be checked against guessed keys without the secret:
    it is no plain hash of the key, differs under another secret, and is stable under the same one."""
    import hashlib

    one, same, other = ApiKeys("alpha", "s1"), ApiKeys("alpha", "s1"), ApiKeys("alpha", "s2")
    ident = one.owner("alpha")
    assert ident is not None and ident == same.owner("alpha") != other.owner("alpha")
    assert ident.removeprefix("k-") not in hashlib.sha256(b"alpha").hexdigest()
    assert ApiKeys("alpha").owner("alpha") != ApiKeys("alpha").owner("alpha")  # no secret: drawn at start


@pytest.mark.parametrize(
    ("method", "path"),
    [
        ("GET", "/models"),
        ("GET", "/models/lander"),
        ("POST", "/sessions"),
        ("GET", "/sessions/r0-x"),
        ("DELETE", "/sessions/r0-x"),
        ("POST", "/sessions/r0-x/step"),
        ("POST", "/step"),
        ("GET", "/openapi.json"),
    ],
)
def test_every_endpoint_needs_a_key(authed: TestClient, method: str, path: str) -> None:
    r = authed.request(method, path, json={})
    assert r.status_code == 401
    assert r.json()["error"] == "unauthorized" and "Authorization: Bearer <key>" in r.json()["message"]
    assert r.headers["www-authenticate"] == "Bearer"
    bad = authed.request(method, path, json={}, headers={"Authorization": "Bearer gamma"})
    assert bad.status_code == 401 and bad.json()["error"] == "invalid_api_key"
    assert authed.request(method, path, json={}, headers={"X-API-Key": "alpha "}).status_code != 401


def test_ops_endpoints_are_open(authed: TestClient) -> None:
    for path in ("/healthz", "/readyz", "/metrics"):
        assert authed.get(path).status_code == 200, path


def test_a_key_owns_its_sessions(authed: TestClient) -> None:
    a = authed.post("/sessions", json=PENDULUM, headers=ALPHA).json()
    b = authed.post("/sessions", json=PENDULUM, headers=BETA).json()
    sid = a["id"]
    assert authed.get(f"/sessions/{sid}", headers=ALPHA).json()["state"] == a["state"]
    for r in (
        authed.get(f"/sessions/{sid}", headers=BETA),
        authed.post(f"/sessions/{sid}/step", json={"controls": [0, 0, 0]}, headers=BETA),
        authed.delete(f"/sessions/{sid}", headers=BETA),
    ):
        assert r.status_code == 404 and r.json()["error"] == "unknown_session"
    # batch stepping: the other key's session is unknown to beta, its own steps
    items = [{"session": sid, "controls": [0, 0, 0]}, {"session": b["id"], "controls": [0, 0, 0]}]
    res = authed.post("/step", json={"items": items}, headers=BETA).json()["results"]
    assert res[0]["error"]["error"] == "unknown_session" and res[0]["state"] is None
    assert res[1]["error"] is None and res[1]["state"] is not None
    assert authed.get(f"/sessions/{sid}", headers=ALPHA).json()["steps"] == 0  # untouched
    assert authed.delete(f"/sessions/{sid}", headers=ALPHA).status_code == 204


def test_per_key_quota(authed: TestClient) -> None:
    ids = [authed.post("/sessions", json=PENDULUM, headers=ALPHA).json()["id"] for _ in range(3)]
    r = authed.post("/sessions", json=PENDULUM, headers=ALPHA)
    assert r.status_code == 429 and r.json()["error"] == "key_quota_exceeded"
    assert (r.json()["field"], r.json()["expected"], r.json()["got"]) == ("MAX_SESSIONS_PER_KEY", 3, 4)
    assert "MAX_SESSIONS_PER_KEY" in r.json()["message"]
    assert authed.post("/sessions", json=PENDULUM, headers=BETA).status_code == 201  # beta has its own
    authed.delete(f"/sessions/{ids[0]}", headers=ALPHA)
    assert authed.post("/sessions", json=PENDULUM, headers=ALPHA).status_code == 201


def test_websocket_keys(authed: TestClient) -> None:
    sid = authed.post("/sessions", json=PENDULUM, headers=ALPHA).json()["id"]
    with pytest.raises(WebSocketDenialResponse) as denied, authed.websocket_connect(f"/ws/sessions/{sid}"):
        pass
    assert denied.value.status_code == 401 and "?api_key=<key>" in denied.value.json()["message"]
    with (
        pytest.raises(WebSocketDenialResponse),
        authed.websocket_connect(f"/ws/sessions/{sid}?api_key=gamma"),
    ):
        pass
    for url, headers in ((f"/ws/sessions/{sid}?api_key=alpha", {}), (f"/ws/sessions/{sid}", ALPHA)):
        with authed.websocket_connect(url, headers=dict(headers)) as ws:
            ws.send_json({"type": "step", "controls": [0, 0, 0], "seq": 1})
            assert ws.receive_json()["type"] == "state"
    # another key's session: as if it did not exist
    with authed.websocket_connect(f"/ws/sessions/{sid}?api_key=beta") as ws:
        assert ws.receive_json()["error"] == "unknown_session"
        with pytest.raises(WebSocketDisconnect) as closed:
            ws.receive_json()
        assert closed.value.code == 4404
