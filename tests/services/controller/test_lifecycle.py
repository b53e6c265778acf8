"""Cancelling (queued and running), idempotency keys, the time limit, a job whose runs keep crashing,
and a worker's clean shutdown (its running job goes back on the queue)."""

from __future__ import annotations

import shutil
import signal
from pathlib import Path

from tests.services.controller.ctl import (  # noqa: F401
    ARTIFACTS,
    QUICK,
    Controller,
    ctl_fixture,
    ended,
    job,
    long_job,
    wait_for,
)


def test_cancel_a_queued_job(ctl: Controller) -> None:
    api = ctl.client()
    job_id = api.post("/jobs", json=QUICK).json()["id"]
    r = api.delete(f"/jobs/{job_id}")
    assert r.status_code == 202 and r.json()["status"] == "cancelled"
    assert r.json()["error"] == "cancelled before it started"
    assert api.delete(f"/jobs/{job_id}").status_code == 409  # already ended
    res = api.get(f"/jobs/{job_id}/result").json()
    assert (res["status"], res["iterations"]) == ("cancelled", 0)
    # it left the queue: a worker finds nothing to do
    w = ctl.worker("--burst")
    assert w.wait(timeout=60) == 0
    after = job(api, job_id)
    assert (after["status"], after["attempt"]) == ("cancelled", 0)
    assert 'controller_jobs_finished_total{status="cancelled"} 1.0' in api.get("/metrics").text


def test_cancel_a_running_job_keeps_the_best_controller(ctl: Controller) -> None:
    api = ctl.client()
    job_id = api.post("/jobs", json=long_job()).json()["id"]
    ctl.worker("--name", ctl.name("w-cancel"))
    wait_for("a few iterations", lambda: job(api, job_id)["iteration"] >= 3, timeout=90)
    r = api.delete(f"/jobs/{job_id}")
    assert r.status_code == 202 and r.json()["status"] in ("running", "cancelled")
    done = ended(api, job_id, timeout=30)
    assert done["status"] == "cancelled" and done["iteration"] >= 3
    res = api.get(f"/jobs/{job_id}/result").json()
    assert res["status"] == "cancelled" and 3 <= res["iterations"] < 10_000
    assert res["controls"]  # the best controller so far
    events = api.get(f"/jobs/{job_id}/events").text
    assert events.rstrip().splitlines()[-2] == "event: end"


def test_idempotency_key_returns_the_same_job(ctl: Controller) -> None:
    api = ctl.client()
    body = {**QUICK, "idempotency_key": "order-17"}
    first = api.post("/jobs", json=body)
    again = api.post("/jobs", json=body)
    assert first.status_code == again.status_code == 202
    assert first.json()["id"] == again.json()["id"]
    assert (first.json()["created"], again.json()["created"]) == (True, False)
    other = api.post("/jobs", json={**QUICK, "idempotency_key": "order-18"})
    assert other.json()["id"] != first.json()["id"]
    clash = api.post("/jobs", json={**body, "optimizer": {"max_iterations": 5}})
    assert clash.status_code == 409 and clash.json()["field"] == "idempotency_key"
    assert len(api.get("/jobs").json()["jobs"]) == 2


def test_time_limit_ends_the_job_failed_with_its_best_controller(ctl: Controller) -> None:
    ctl.env["JOB_TIMEOUT_S"] = "4"
    api = ctl.client()
    job_id = api.post("/jobs", json=long_job()).json()["id"]
    ctl.worker("--burst")
    done = ended(api, job_id, timeout=90)
    assert done["status"] == "failed" and "time limit of 4 s" in done["error"], done
    res = api.get(f"/jobs/{job_id}/result").json()
    assert res["status"] == "failed" and res["controls"]  # the best controller found in the time


def test_a_job_whose_runs_crash_is_retried_then_failed(ctl: Controller, tmp_path: Path) -> None:
    # a registry whose pendulum emulator has a manifest (so the job validates) but broken weights
    src = ARTIFACTS / "pendulum-active"
    version = (src / "latest-n50").read_text().strip()
    dst = tmp_path / "registry" / "pendulum-active"
    shutil.copytree(src / version, dst / version)
    for ptr in ("latest", "latest-n50"):
        (dst / ptr).write_text(version + "\n")
    (dst / version / "weights.pt").write_bytes(b"not a checkpoint")
    ctl.env.update({"ARTIFACTS_DIR": str(tmp_path / "registry"), "JOB_RETRIES": "1"})
    api = ctl.client()
    job_id = api.post("/jobs", json=QUICK).json()["id"]
    ctl.worker("--burst")
    done = ended(api, job_id, timeout=120)
    assert done["status"] == "failed", done
    assert (done["attempt"], done["failures"]) == (2, 2)
    assert "gave up after 2 failed runs (JOB_RETRIES=1)" in done["error"]
    res = api.get(f"/jobs/{job_id}/result").json()
    assert res["status"] == "failed" and res["reason"] == done["error"]
    statuses = [ln for ln in api.get(f"/jobs/{job_id}/events").text.splitlines() if ln.startswith("data: ")]
    assert sum('"status":"queued"' in s for s in statuses) == 2  # submitted, then re-queued once


def test_sigterm_puts_the_running_job_back_on_the_queue(ctl: Controller) -> None:
    api = ctl.client()
    job_id = api.post("/jobs", json=long_job(150)).json()["id"]
    w = ctl.worker("--name", ctl.name("w-leaving"))
    wait_for("the job to iterate", lambda: job(api, job_id)["iteration"] >= 1, timeout=90)
    w.send_signal(signal.SIGTERM)
    assert w.wait(timeout=30) == 0, ctl.logs()  # it stopped promptly, without finishing the job
    back = job(api, job_id)
    assert back["status"] == "queued" and back["failures"] == 0, back
    assert f"worker {ctl.name('w-leaving')} shut down" in back["error"]
    ctl.worker("--burst", "--name", ctl.name("w-next"))
    done = ended(api, job_id, timeout=120)
    assert (done["status"], done["attempt"], done["worker"]) == ("succeeded", 2, ctl.name("w-next"))
    assert api.get(f"/jobs/{job_id}/result").json()["iterations"] == 150
