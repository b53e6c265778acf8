"""Who is working, as Redis knows it: the live-worker count of ``/readyz`` and ``controller_workers``
follows SIGKILLs and a Redis restart (heartbeats with expiry, not RQ's registration); the queue carries
JSON, and a worker runs nothing but controller deliveries."""

from __future__ import annotations

import json
import zlib
from pathlib import Path

from rq import Queue
from rq.registry import FailedJobRegistry
from rq.serializers import JSONSerializer

from tests.services.controller.ctl import QUICK, Controller, ctl_fixture, ended, kill, wait_for  # noqa: F401
from tests.services.private_redis import PrivateRedis, private_redis_fixture  # noqa: F401


def _workers(api: object) -> int:
    r = api.get("/readyz")  # type: ignore[attr-defined]
    assert r.status_code == 200, r.text
    return int(r.json()["workers"])


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
    ctl.worker("--burst").wait(120)
    assert not target.exists(), "the worker ran a function it was not made for"
    assert foreign.id in FailedJobRegistry(queue=queue).get_job_ids()
    assert "refused" in ctl.logs()
    assert ended(api, job_id)["status"] == "succeeded"  # the controller's own job ran
