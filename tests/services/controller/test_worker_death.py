"""A worker killed with SIGKILL mid-job (with its job process: the machine is gone) loses nothing:
the job's lease expires, another worker re-queues it and runs it to the end."""

from __future__ import annotations

from tests.services.controller.ctl import Controller, ctl_fixture, ended, job, kill, long_job, wait_for  # noqa: F401


def test_sigkilled_worker_job_completes_on_another_worker(ctl: Controller) -> None:
    api = ctl.client()
    a = ctl.worker("--name", ctl.name("w-a"))
    b = ctl.worker("--name", ctl.name("w-b"))
    workers = {ctl.name("w-a"): a, ctl.name("w-b"): b}
    job_id = api.post("/jobs", json=long_job(150)).json()["id"]
    running = wait_for(
        "the job to iterate", lambda: (j := job(api, job_id))["iteration"] >= 1 and j, timeout=90
    )
    victim = running["worker"]
    assert victim in workers and running["attempt"] == 1
    horse = int(ctl.r.hget(f"{ctl.env['REDIS_PREFIX']}:job:{job_id}", "pid") or 0)
    kill(workers[victim].pid)
    kill(horse)
    assert workers[victim].wait(timeout=10) == -9

    done = ended(api, job_id, timeout=150)
    survivor = ctl.name("w-b") if victim == ctl.name("w-a") else ctl.name("w-a")
    assert done["status"] == "succeeded", (done, ctl.logs())
    assert (done["attempt"], done["failures"], done["worker"]) == (2, 1, survivor)
    assert api.get(f"/jobs/{job_id}/result").json()["iterations"] == 150
    assert len(done["objective_history"]) == done["iteration"] + 1  # this attempt's, from iteration 0
    events = api.get(f"/jobs/{job_id}/events").text
    assert f"abandoned: worker {victim} stopped renewing the job's lease" in events
    assert "controller_jobs_requeued_total 1.0" in api.get("/metrics").text
