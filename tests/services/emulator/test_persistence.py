"""Session checkpoints in a real Redis: a restarted replica gets its sessions back (ids, versions,
states bit for bit, step counts, owners), deleted sessions stay deleted, other replicas restore nothing,
and a Redis that is down at startup leaves the service serving (persistence ``degraded``)."""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any, cast

import numpy as np
import redis
from fastapi.testclient import TestClient

from services.emulator.app import create_app
from services.emulator.persistence import decode, encode
from services.emulator.settings import Settings
from tests.helpers import app_state, service_of


def _settings(make_settings: Callable[..., Settings], url: str, prefix: str, **kw: Any) -> Settings:
    base: dict[str, Any] = {
        "redis_url": url,
        "redis_prefix": prefix,
        "replica_id": "p1",
        "checkpoint_interval_s": 60.0,  # checkpoints are forced by the tests unless they set it
    }
    return make_settings(**{**base, **kw})


def _checkpoint(c: TestClient) -> int:
    assert c.portal is not None  # the client's lifespan is running
    n: int = c.portal.call(app_state(c).persistence.checkpoint)
    return n


def _hash(url: str, prefix: str, replica: str = "p1") -> dict[bytes, bytes]:
    client = redis.Redis.from_url(url)
    try:
        return cast(dict[bytes, bytes], client.hgetall(f"{prefix}:sessions:{replica}"))
    finally:
        client.close()


def test_record_round_trip(client: TestClient) -> None:
    s = client.post("/sessions", json={"model": "lander", "seed": 4}).json()
    sess = service_of(client).store.sessions[s["id"]]
    sess.steps, sess.diverged = 17, True
    raw = encode(sess, 1234.5)
    rec = decode(raw)
    assert (rec.model, rec.version, rec.steps, rec.diverged, rec.seed, rec.owner, rec.last_used) == (
        "lander",
        s["version"],
        17,
        True,
        4,
        None,
        1234.5,
    )
    assert rec.state.dtype == np.float32 and rec.state.shape == (13,)
    np.testing.assert_array_equal(rec.state, np.asarray(s["state"], np.float32))
    assert len(raw) < 13 * 4 + 160  # compact: the state's bytes and a short header


def test_restart_restores_checkpointed_sessions(
    make_settings: Callable[..., Settings], redis_url: str, redis_prefix: str
) -> None:
    settings = _settings(make_settings, redis_url, redis_prefix)
    u = [0.5, -1.0, 1.5]
    with TestClient(create_app(settings)) as a:
        assert a.get("/readyz").json() == {"status": "ready", "persistence": "ok"}
        p = a.post("/sessions", json={"model": "pendulum-active", "seed": 1}).json()
        q = a.post("/sessions", json={"model": "lander", "seed": 2}).json()
        gone = a.post("/sessions", json={"model": "pendulum-active", "seed": 3}).json()
        removed = a.post("/sessions", json={"model": "pendulum-active", "seed": 4}).json()
        a.post(f"/sessions/{p['id']}/step", json={"controls": u, "steps": 3})
        a.post(f"/sessions/{q['id']}/step", json={"controls": [0, 0.5, 0, 0], "steps": 2})
        assert a.delete(f"/sessions/{gone['id']}").status_code == 204  # deleted before any checkpoint
        assert _checkpoint(a) == 3
        assert _checkpoint(a) == 0  # nothing changed since
        assert a.delete(f"/sessions/{removed['id']}").status_code == 204
        assert _checkpoint(a) == 1  # the deletion reaches Redis
        assert set(_hash(redis_url, redis_prefix)) == {p["id"].encode(), q["id"].encode()}
        saved = {sid: a.get(f"/sessions/{sid}").json() for sid in (p["id"], q["id"])}
        later = a.post(f"/sessions/{p['id']}/step", json={"controls": u}).json()  # never checkpointed

        # a new process of replica p1 (the old one "crashed": it is still open, no final checkpoint)
        with TestClient(create_app(settings)) as b:
            for sid, want in saved.items():
                got = b.get(f"/sessions/{sid}").json()
                assert got == want  # model, version, state bit for bit, steps, t, seed
            assert b.get(f"/sessions/{gone['id']}").status_code == 404
            assert b.get(f"/sessions/{removed['id']}").status_code == 404
            # it lost the one unsaved step, and goes on exactly as the old process did
            again = b.post(f"/sessions/{p['id']}/step", json={"controls": u}).json()
            assert again["state"] == later["state"] and again["steps"] == later["steps"] == 4
            assert b.get("/metrics").text.count("emulator_persistence_up 1.0") == 1


def test_clean_shutdown_loses_nothing_and_replicas_are_separate(
    make_settings: Callable[..., Settings], redis_url: str, redis_prefix: str
) -> None:
    settings = _settings(make_settings, redis_url, redis_prefix)
    with TestClient(create_app(settings)) as a:
        s = a.post("/sessions", json={"model": "lander", "seed": 8}).json()
        a.post(f"/sessions/{s['id']}/step", json={"controls": [0, 0, 0, 0], "steps": 5})
        service_of(a).store.sessions[s["id"]].diverged = True
        want = a.get(f"/sessions/{s['id']}").json()
    # closing wrote a final checkpoint
    with TestClient(create_app(settings)) as b:
        got = b.get(f"/sessions/{s['id']}").json()
        assert got == want and got["steps"] == 5 and got["diverged"]
        r = b.post(f"/sessions/{s['id']}/step", json={"controls": [0, 0, 0, 0]})
        assert r.status_code == 409 and r.json()["error"] == "diverged"
    with TestClient(create_app(_settings(make_settings, redis_url, redis_prefix, replica_id="p2"))) as other:
        assert other.get(f"/sessions/{s['id']}").status_code == 404
        assert service_of(other).store.sessions == {}


def test_background_checkpoints(
    make_settings: Callable[..., Settings], redis_url: str, redis_prefix: str
) -> None:
    settings = _settings(make_settings, redis_url, redis_prefix, checkpoint_interval_s=0.05)

    def wait_for(pred: Callable[[dict[bytes, bytes]], bool]) -> dict[bytes, bytes]:
        deadline = time.monotonic() + 5.0
        while True:
            h = _hash(redis_url, redis_prefix)
            if pred(h) or time.monotonic() > deadline:
                return h
            time.sleep(0.02)

    with TestClient(create_app(settings)) as c:
        sid = c.post("/sessions", json={"model": "pendulum-active", "seed": 5}).json()["id"]
        out = c.post(f"/sessions/{sid}/step", json={"controls": [1, 1, 1], "steps": 2}).json()
        h = wait_for(lambda h: sid.encode() in h and decode(h[sid.encode()]).steps == 2)
        rec = decode(h[sid.encode()])
        assert rec.steps == 2
        np.testing.assert_array_equal(rec.state, np.asarray(out["state"], np.float32))
        c.delete(f"/sessions/{sid}")
        assert sid.encode() not in wait_for(lambda h: sid.encode() not in h)


def test_owner_survives_restart(
    make_settings: Callable[..., Settings], redis_url: str, redis_prefix: str
) -> None:
    settings = _settings(make_settings, redis_url, redis_prefix, api_keys="alpha,beta")
    alpha, beta = {"X-API-Key": "alpha"}, {"X-API-Key": "beta"}
    with TestClient(create_app(settings)) as a:
        sid = a.post("/sessions", json={"model": "pendulum-active", "seed": 1}, headers=alpha).json()["id"]
    raw = next(iter(_hash(redis_url, redis_prefix).values()))
    assert b"alpha" not in raw  # the key's id is stored, never the key
    with TestClient(create_app(settings)) as b:
        assert b.get(f"/sessions/{sid}", headers=alpha).status_code == 200
        assert b.get(f"/sessions/{sid}", headers=beta).status_code == 404
        assert service_of(b).store.per_owner == {decode(raw).owner: 1}


def test_redis_down_at_startup(make_settings: Callable[..., Settings], redis_prefix: str) -> None:
    settings = make_settings(redis_url="redis://127.0.0.1:1/0", redis_prefix=redis_prefix)
    t0 = time.monotonic()
    with TestClient(create_app(settings)) as c:
        assert time.monotonic() - t0 < 10.0
        r = c.get("/readyz")
        assert r.status_code == 200 and r.json() == {"status": "ready", "persistence": "degraded"}
        sid = c.post("/sessions", json={"model": "pendulum-active", "seed": 1}).json()["id"]
        assert c.post(f"/sessions/{sid}/step", json={"controls": [0, 0, 0]}).status_code == 200
        assert "emulator_persistence_up 0.0" in c.get("/metrics").text


def test_persistence_off_without_redis_url(client: TestClient) -> None:
    assert client.get("/readyz").json() == {"status": "ready", "persistence": "off"}


def test_a_driven_session_comes_back_driven(
    make_settings: Callable[..., Settings], redis_url: str, redis_prefix: str
) -> None:
    """The driver's parameters are checkpointed; a restored session is driven again (its controller
    starts its phase afresh), so it steps without controls as before."""
    from pathlib import Path

    artifacts = Path(__file__).resolve().parents[3] / "artifacts"  # the committed runner
    settings = _settings(make_settings, redis_url, redis_prefix, artifacts_dir=artifacts)
    with TestClient(create_app(settings)) as a:
        s = a.post("/sessions", json={"model": "runner", "driver": {"speed": 2.2}}).json()
        a.post(f"/sessions/{s['id']}/step", json={"forces": [0.0, 0.0], "steps": 3})
        assert _checkpoint(a) == 1
        assert decode(_hash(redis_url, redis_prefix)[s["id"].encode()]).driver == {"speed": 2.2}
        with TestClient(create_app(settings)) as b:
            got = b.get(f"/sessions/{s['id']}").json()
            assert got["driver"] == {"speed": 2.2} and got["steps"] == 3
            r = b.post(f"/sessions/{s['id']}/step", json={"forces": [0.0, 0.0]})
            assert r.status_code == 200 and r.json()["steps"] == 4
