"""Who is working, as Redis knows it: the live-worker count of ``/readyz`` and ``controller_workers``
follows SIGKILLs and a Redis restart (heartbeats with expiry, not RQ's registration); the queue carries
JSON, and a worker runs nothing but controller deliveries."""

from __future__ import annotations

import json
import time
import zlib
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from rq import Queue
from rq.registry import FailedJobRegistry
from rq.serializers import JSONSerializer

from tests.services.controller.ctl import (  # noqa: F401
    QUICK,
    Controller,
    ctl_fixture,
    ended,
    kill,
    long_job,
    wait_for,
)
from tests.services.private_redis import PrivateRedis, private_redis_fixture  # noqa: F401


def _workers(api: object) -> int:
    r = api.get("/readyz")  # type: ignore[attr-defined]
    assert r.status_code == 200 or r.json()["status"] == "no workers", r.text  # 503 while none is heard
    return int(r.json()["workers"])


def _answered(api: Any, path: str) -> Any:
    """The JSON of a GET that succeeded, else None (the API's first call after a Redis restart may
    find its connection gone)."""
    r = api.get(path)
    return r.json() if r.status_code == 200 or "workers" in r.text else None


@pytest.fixture
def aof_redis(tmp_path: Path) -> Iterator[PrivateRedis]:
    """A private Redis that keeps its data across a restart (AOF); requested before ``ctl``, it stops
    after the deployment's workers."""
    folder = tmp_path / "aof-redis"
    folder.mkdir()
    server = PrivateRedis(folder, aof=True)
    server.start()
    try:
        yield server
    finally:
        server.stop(kill=True)


def test_sigkilled_workers_drop_out_of_the_count(ctl: Controller) -> None:
    api = ctl.client()
    procs = [ctl.worker("--name", ctl.name(f"w{i}")) for i in range(3)]
    wait_for("3 workers", lambda: _workers(api) == 3, timeout=60)
    for p in procs[:2]:
        kill(p.pid)
        p.wait(10)
    window = ctl.settings().worker_alive_s()
    wait_for("1 worker", lambda: _workers(api) == 1, timeout=window + 5)
    assert "controller_workers 1.0" in api.get("/metrics").text
    procs[2].terminate()
    procs[2].wait(20)
    assert _workers(api) == 0  # a clean stop leaves at once


def test_the_count_comes_back_after_redis_lost_its_data(ctl: Controller, private_redis: PrivateRedis) -> None:
    ctl.env["REDIS_URL"] = private_redis.url
    api = ctl.client()
    ctl.worker("--name", ctl.name("w"))
    wait_for("the worker", lambda: _workers(api) == 1, timeout=60)
    private_redis.restart(down_s=0.5)  # no persistence: everything is gone
    assert private_redis.client().dbsize() == 0
    wait_for("the worker again", lambda: _workers(api) == 1, timeout=ctl.settings().worker_alive_s() + 10)
    # and it still takes jobs
    job_id = api.post("/jobs", json=QUICK).json()["id"]
    assert ended(api, job_id)["status"] == "succeeded"


def test_the_queue_is_json_and_a_foreign_function_is_not_run(ctl: Controller, tmp_path: Path) -> None:
    api = ctl.client()
    job_id = api.post("/jobs", json=QUICK).json()["id"]
    raw = ctl.r.hget(f"rq:job:{job_id}-1", "data")
    assert isinstance(raw, bytes)
    func, _instance, args, _kwargs = json.loads(zlib.decompress(raw))  # JSON, not a pickle
    assert func == "services.controller.execution.perform" and args == [job_id, 1]

    target = tmp_path / "made-by-a-queued-job"
    queue = Queue(ctl.env["QUEUE_NAME"], connection=ctl.r, serializer=JSONSerializer)
    foreign = queue.enqueue("os.mkdir", str(target))
    # a pickle, as RQ writes by default: the worker's JSON cannot read it, and nothing is unpickled
    pickled = Queue(ctl.env["QUEUE_NAME"], connection=ctl.r).enqueue("os.mkdir", str(target))
    ctl.worker("--burst").wait(120)
    assert not target.exists(), "the worker ran a function it was not made for"
    assert {foreign.id, pickled.id} <= set(FailedJobRegistry(queue=queue).get_job_ids())
    assert "<unreadable: DeserializationError>" in ctl.logs()
    assert "refused" in ctl.logs()
    assert ended(api, job_id)["status"] == "succeeded"  # the controller's own job ran


def test_a_busy_worker_outlives_a_redis_outage(aof_redis: PrivateRedis, ctl: Controller) -> None:
    """Redis away for several heartbeats while the only worker runs a job: the worker stays (RQ's own
    loop quit on the failed heartbeat), is counted again and takes jobs as soon as Redis is back, and
    the job, kept by the AOF, goes on."""
    ctl.env["REDIS_URL"] = aof_redis.url
    api = ctl.client()
    proc = ctl.worker("--name", ctl.name("w"))
    wait_for("the worker", lambda: _workers(api) == 1, timeout=60)
    job_id = api.post("/jobs", json=long_job()).json()["id"]
    wait_for("the job to run", lambda: api.get(f"/jobs/{job_id}").json()["iteration"] > 0, timeout=60)
    aof_redis.stop()
    time.sleep(3 * ctl.settings().heartbeat_s())
    assert proc.poll() is None, ctl.logs()[-3000:]
    aof_redis.start()
    back = time.monotonic()
    wait_for("the worker again", lambda: (_answered(api, "/readyz") or {}).get("workers") == 1, timeout=30)
    assert proc.poll() is None, ctl.logs()[-3000:]
    running = _answered(api, f"/jobs/{job_id}")
    assert running is not None and running["status"] == "running" and running["attempt"] == 1, running
    assert api.delete(f"/jobs/{job_id}").status_code == 202
    assert ended(api, job_id)["status"] == "cancelled"
    quick = api.post("/jobs", json=QUICK).json()["id"]
    assert ended(api, quick)["status"] == "succeeded"
    assert time.monotonic() - back < 60
