"""Checkpoints through a Redis that restarts or loses its data (a private ``redis-server``): every live
session, changed or not, is back in the hash within two checkpoint intervals, and ``/readyz`` tells
that Redis went away at once, whether or not any session changed."""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

from fastapi.testclient import TestClient

from services.emulator.app import create_app
from services.emulator.settings import Settings
from tests.helpers import app_state
from tests.services.private_redis import PrivateRedis, private_redis_fixture  # noqa: F401

INTERVAL = 0.5


def _app(make_settings: Callable[..., Settings], redis: PrivateRedis) -> TestClient:
    settings = make_settings(
        redis_url=redis.url, redis_prefix="restart", replica_id="p1", checkpoint_interval_s=INTERVAL
    )
    return TestClient(create_app(settings))


def _records(redis: PrivateRedis) -> int:
    client = redis.client()
    try:
        return int(client.hlen("restart:sessions:p1"))
    finally:
        client.close()


def _wait(what: str, check: Callable[[], Any], timeout: float) -> float:
    t0 = time.monotonic()
    while not check():
        if time.monotonic() - t0 > timeout:
            raise AssertionError(f"{what}: not within {timeout:.1f} s")
        time.sleep(0.02)
    return time.monotonic() - t0


def test_every_session_is_written_again_after_redis_lost_its_data(
    make_settings: Callable[..., Settings], private_redis: PrivateRedis
) -> None:
    with _app(make_settings, private_redis) as c:
        ids = [
            c.post("/sessions", json={"model": "pendulum-active", "seed": i}).json()["id"] for i in range(50)
        ]
        _wait("50 records", lambda: _records(private_redis) == 50, timeout=10)
        time.sleep(2 * INTERVAL)  # nothing changes from here on: no session has a reason to be written
        private_redis.restart()  # no persistence: Redis comes back empty
        took = _wait("50 records again", lambda: _records(private_redis) == 50, timeout=10)
        assert took <= 2 * INTERVAL, f"{took:.2f} s"
        assert app_state(c).persistence.rewrites >= 1
        # a session deleted meanwhile is removed as usual
        assert c.delete(f"/sessions/{ids[0]}").status_code == 204
        _wait("49 records", lambda: _records(private_redis) == 49, timeout=10)


def test_a_deleted_hash_is_written_again(
    make_settings: Callable[..., Settings], private_redis: PrivateRedis
) -> None:
    with _app(make_settings, private_redis) as c:
        for i in range(5):
            c.post("/sessions", json={"model": "pendulum-active", "seed": i})
        _wait("5 records", lambda: _records(private_redis) == 5, timeout=10)
        private_redis.client().delete("restart:sessions:p1")  # the same server: only the count tells
        took = _wait("5 records again", lambda: _records(private_redis) == 5, timeout=10)
        assert took <= 2 * INTERVAL, f"{took:.2f} s"


def test_readyz_asks_redis_itself(
    make_settings: Callable[..., Settings], private_redis: PrivateRedis
) -> None:
    with _app(make_settings, private_redis) as c:
        c.post("/sessions", json={"model": "pendulum-active"})
        assert c.get("/readyz").json() == {"status": "ready", "persistence": "ok"}
        private_redis.stop()
        t0 = time.monotonic()
        assert c.get("/readyz").json() == {"status": "ready", "persistence": "degraded"}
        assert time.monotonic() - t0 < 2.0
        private_redis.start()
        _wait("ok again", lambda: c.get("/readyz").json()["persistence"] == "ok", timeout=10)
