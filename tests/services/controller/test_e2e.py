"""A real built-in task through the API, Redis and a real worker process: submit → progress → result,
the SSE and websocket streams, the job list, and no PyTorch in the worker's parent process."""

from __future__ import annotations

from typing import Any

from services.controller.settings import Settings
from tests.services.controller.ctl import (  # noqa: F401
    ARTIFACTS,
    QUICK,
    Controller,
    ctl_fixture,
    ended,
    job,
    maps_torch,
    wait_for,
)
from tests.services.queues import sse


def test_submit_progress_result_through_a_worker(ctl: Controller) -> None:
    api = ctl.client()
    assert api.get("/readyz").json()["status"] == "no workers"  # ready once a worker runs
    tasks = {t["name"]: t for t in api.get("/tasks").json()["tasks"]}
    assert {"pendulum-swing", "truck-parking", "lander-landing"} <= set(tasks)
    assert tasks["pendulum-swing"]["model"] == "pendulum-active"

    # four descent updates and no Levenberg-Marquardt ones after them (they have a cap of their own)
    optimizer = {"max_iterations": 4, "stop_on_success": False, "gauss_newton_iterations": 0}
    r = api.post("/jobs", json={**QUICK, "optimizer": optimizer})
    assert r.status_code == 202, r.text
    job_id = r.json()["id"]
    assert r.json()["status"] == "queued" and r.headers["location"] == f"/jobs/{job_id}"
    queued = job(api, job_id)
    assert (queued["status"], queued["attempt"], queued["task"], queued["model"]) == (
        "queued",
        0,
        "pendulum-swing",
        "pendulum-active",
    )
    assert api.get(f"/jobs/{job_id}/result").status_code == 409

    worker = ctl.worker("--burst", "--name", ctl.name("w-e2e"))
    # while the job runs: the job's process has torch, the worker's parent process does not
    running = wait_for("the job to run", lambda: (j := job(api, job_id))["status"] != "queued" and j)
    if running["status"] == "running":
        pid = int(ctl.r.hget(f"{ctl.env['REDIS_PREFIX']}:job:{job_id}", "pid") or 0)
        try:
            assert not maps_torch(worker.pid), "the worker's parent process imported torch"
            wait_for("torch in the job process", lambda: maps_torch(pid), timeout=30)
        except FileNotFoundError:
            pass  # it ended meanwhile
    done = ended(api, job_id)
    assert worker.wait(timeout=60) == 0, ctl.logs()
    assert done["status"] == "succeeded", done
    assert (done["attempt"], done["failures"], done["worker"]) == (1, 0, ctl.name("w-e2e"))
    # one objective per progress event: the initial controller, 4 updates (and any later phase's)
    assert done["iteration"] >= 4 and len(done["objective_history"]) == done["iteration"] + 1
    assert done["best_objective"] is not None and done["best_objective"] <= done["objective_history"][0]
    assert done["best"]["objective"] == done["best_objective"]
    assert done["result"] == f"/jobs/{job_id}/result"

    res = api.get(f"/jobs/{job_id}/result").json()
    assert res["id"] == job_id and res["status"] == "succeeded" and res["task"] == "pendulum-swing"
    assert res["iterations"] == 4 and res["objective_history"] == done["objective_history"][:5]
    assert len(res["times"]) == len(res["controls"]) and len(res["controls"][0]) == 3
    states = res["emulated"]["states"]
    assert len(states[0]) == 6 and len(res["physical"]["states"][0]) == 6
    assert res["final_error_emulator"] is not None and res["final_error_physics"] is not None

    # the event stream replays everything: queued, running, five progress events, end
    body = api.get(f"/jobs/{job_id}/events")
    assert body.headers["content-type"].startswith("text/event-stream")
    events = sse(body.text)
    names = [e for e, _ in events]
    assert names[:2] == ["status", "status"] and names[-1] == "end", names
    progress = [d for e, d in events if e == "progress"]
    assert [p["iteration"] for p in progress] == list(range(done["iteration"] + 1))
    assert [p["objective"] for p in progress] == done["objective_history"]
    assert {"objective", "best_objective", "success_emulator", "elapsed_s"} <= set(progress[0])
    assert events[-1][1]["status"] == "succeeded" and events[-1][1]["iterations"] == 4
    # ... and resumes after Last-Event-ID
    ids = [line[4:] for line in body.text.splitlines() if line.startswith("id: ")]
    tail = sse(api.get(f"/jobs/{job_id}/events", headers={"Last-Event-ID": ids[-2]}).text)
    assert [e for e, _ in tail] == ["end"]

    with api.websocket_connect(f"/ws/jobs/{job_id}") as ws:
        msgs: list[dict[str, Any]] = []
        while not msgs or msgs[-1]["event"] != "end":
            msgs.append(ws.receive_json())
    assert [m["event"] for m in msgs] == names

    listed = api.get("/jobs").json()["jobs"]
    assert [j["id"] for j in listed] == [job_id] and listed[0]["status"] == "succeeded"


def test_a_start_that_would_diverge_is_refused_at_submission(ctl: Controller) -> None:
    """A start rate of 1e200 once overflowed the emulator in the worker (the objective not finite);
    states are bounded now (``terms.MAX_VALUE``), so such a job is refused before it is queued. How a
    run that diverges ends (failed, the best finite controller kept) is tested in test_synthesis.py."""
    api = ctl.client()
    body = {
        "task": "pendulum-swing",
        "initial_state": [0, 0, 0, 1e200, 0, 0],
        "optimizer": {"max_iterations": 3},
    }
    r = api.post("/jobs", json=body)
    assert r.status_code == 422, r.text
    assert r.json()["field"] == "initial_state[3]" and "10000" in r.json()["message"]
    assert api.get("/jobs").json()["jobs"] == []


def test_sse_follows_a_running_job_live(ctl: Controller) -> None:
    api = ctl.client()
    job_id = api.post(
        "/jobs", json={**QUICK, "optimizer": {"max_iterations": 3, "stop_on_success": False}}
    ).json()["id"]
    ctl.worker("--burst")
    seen = []
    with api.stream("GET", f"/jobs/{job_id}/events") as s:
        for line in s.iter_lines():
            if line.startswith("event: "):
                seen.append(line[7:])
    assert seen[-1] == "end" and seen.count("progress") >= 4 and "status" in seen


def test_worker_and_api_processes_do_not_import_torch() -> None:
    import subprocess
    import sys

    code = (
        "import sys\n"
        "from services.controller.app import create_app\n"
        "from services.controller.settings import Settings\n"
        "import services.controller.worker, services.controller.__main__\n"
        f"create_app(Settings(artifacts_dir={str(ARTIFACTS)!r}))\n"
        "assert 'torch' not in sys.modules, 'torch was imported'\n"
    )
    subprocess.run([sys.executable, "-c", code], check=True, timeout=120)


def test_settings_from_environment(monkeypatch: Any) -> None:
    monkeypatch.setenv("MAX_QUEUE", "7")
    monkeypatch.setenv("JOB_TIMEOUT_S", "12.5")
    monkeypatch.setenv("CORS_ORIGINS", "http://localhost:5173, http://x")
    s = Settings()
    assert (s.max_queue, s.job_timeout_s, s.port) == (7, 12.5, 8001)
    assert s.cors_list() == ["http://localhost:5173", "http://x"]


def test_neuro_worker_command_runs_jobs(ctl: Controller) -> None:
    import os
    import subprocess
    import sys

    api = ctl.client()
    job_id = api.post("/jobs", json=QUICK).json()["id"]
    # `neuro worker` execs `python -m services.controller.worker` (the CLI process has imported torch)
    subprocess.run(
        [sys.executable, "-m", "neuroanimator.cli", "worker", "--burst", "--name", ctl.name("w-cli")],
        env={**os.environ, **ctl.env},
        cwd=ctl.tmp,
        check=True,
        timeout=120,
        capture_output=True,
    )
    done = job(api, job_id)
    assert (done["status"], done["worker"]) == ("succeeded", ctl.name("w-cli")), done
