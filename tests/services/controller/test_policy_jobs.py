"""Policy jobs through the API, Redis and a real worker process: a lander policy trained for a few
seconds, stored and read back; bad requests refused at submission (422 naming the field); cancelling
a queued and a running policy job; the time limit. Every policy lands in the test's own data
directory (``NEUROANIMATOR_DATA_DIR``, set per test by the suite's conftest)."""

from __future__ import annotations

import copy
import json
import math
import os
import socket
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest
from dm_control import suite
from fastapi.testclient import TestClient
from rq.job import Job
from rq.serializers import JSONSerializer

from neuroanimator.artifacts.policies import list_policies
from services.common import tenancy
from services.controller.policies import PolicyJobSpec
from services.controller.policy_execution import training_settings
from services.controller.settings import Settings
from tests.services.controller.ctl import ARTIFACTS, QUICK, Controller, ctl_fixture, wait_for  # noqa: F401
from tests.services.queues import sse

# a few seconds of training without refinement, a small batch: several iterations in the budget
QUICK_POLICY = {"task": "lander-landing", "seconds": 6, "refine": False, "batch": 16}


def committed_policies() -> dict[tuple[str, str], str]:
    """(model, name) -> version of the committed default policies (read beside a test's own)."""
    return {(m.model, m.name): m.version for m in list_policies(ARTIFACTS)}


def _closed_port() -> int:
    s = socket.socket()
    s.bind(("127.0.0.1", 0))
    port = int(s.getsockname()[1])
    s.close()  # nothing listens there now
    return port


def policy_job(client: TestClient, job_id: str) -> dict[str, Any]:
    r = client.get(f"/policy-jobs/{job_id}")
    assert r.status_code == 200, r.text
    out: dict[str, Any] = r.json()
    return out


def policy_ended(client: TestClient, job_id: str, timeout: float = 90.0) -> dict[str, Any]:
    """The policy job once it reached a final status."""
    out: dict[str, Any] = wait_for(
        f"policy job {job_id} to end",
        lambda: (j := policy_job(client, job_id))["status"] in ("succeeded", "failed", "cancelled") and j,
        timeout,
        every=0.2,
    )
    return out


def test_a_policy_job_trains_stores_and_reads_back(ctl: Controller) -> None:
    api = ctl.client()
    r = api.post("/policies", json=QUICK_POLICY)
    assert r.status_code == 202, r.text
    job_id = r.json()["id"]
    assert r.headers["location"] == f"/policy-jobs/{job_id}"
    queued = policy_job(api, job_id)
    assert (queued["status"], queued["task"], queued["model"], queued["seconds"], queued["refine"]) == (
        "queued",
        "lander-landing",
        "lander",
        6.0,
        False,
    )
    assert queued["emulator_version"].startswith("n25-")  # the task's super-step
    assert api.get(f"/policy-jobs/{job_id}/result").status_code == 409
    # a policy job is not a control job: /jobs neither lists nor shows it, and says where it is
    assert api.get("/jobs").json()["jobs"] == []
    wrong = api.get(f"/jobs/{job_id}")
    assert wrong.status_code == 404 and f"/policy-jobs/{job_id}" in wrong.json()["message"]

    worker = ctl.worker("--burst", "--name", ctl.name("w-policy"))
    done = policy_ended(api, job_id)
    assert worker.wait(timeout=60) == 0, ctl.logs()
    assert done["status"] == "succeeded", (done, ctl.logs())
    assert (done["attempt"], done["worker"]) == (1, ctl.name("w-policy"))
    assert done["iteration"] >= 1 and done["mujoco_steps"] > 0 and done["loss_history"]
    assert done["result"] == f"/policy-jobs/{job_id}/result"

    # the events: queued, running, one progress per iteration (PolicyProgress), end
    events = sse(api.get(f"/policy-jobs/{job_id}/events").text)
    names = [e for e, _ in events]
    assert names[:2] == ["status", "status"] and names[-1] == "end", names
    progress = [d for e, d in events if e == "progress"]
    assert [p["iteration"] for p in progress] == list(range(1, done["iteration"] + 1))
    assert {"loss", "success_physics", "mujoco_steps", "elapsed_s", "attempt"} <= set(progress[0])
    assert progress[-1]["mujoco_steps"] == done["mujoco_steps"]
    assert events[-1][1]["status"] == "succeeded" and events[-1][1]["iterations"] == done["iteration"]

    res = api.get(f"/policy-jobs/{job_id}/result").json()
    assert (res["id"], res["status"], res["task"], res["model"]) == (
        job_id,
        "succeeded",
        "lander-landing",
        "lander",
    )
    policy = res["policy"]
    assert (policy["name"], policy["model"], policy["emulator_version"]) == (
        "lander-landing",
        "lander",
        queued["emulator_version"],
    )
    metrics = policy["metrics"]
    assert metrics["iterations"] == res["iterations"] == done["iteration"] and metrics["stop"] == "budget"
    assert 0.0 <= metrics["success_physics"] <= 1.0 and 0.0 <= metrics["success_emulator"] <= 1.0
    assert metrics["mujoco_steps"] >= done["mujoco_steps"] and metrics["wall_s"] > 0
    assert res["loss_history"][-1]["iteration"] == res["iterations"]
    assert res["success_history"], "the budget's end checks the policy on MuJoCo"

    # stored where the service reads policies, in this test's data directory
    assert api.get("/policies/lander/lander-landing").json() == policy
    assert api.get("/policies/lander/lander-landing", params={"version": policy["version"]}).json() == policy
    listed = {(p["model"], p["name"]): p["version"] for p in api.get("/policies").json()["policies"]}
    assert listed == {**committed_policies(), ("lander", "lander-landing"): policy["version"]}
    truck = api.get("/policies", params={"model": "truck"}).json()["policies"]
    assert [p["version"] for p in truck] == [committed_policies()[("truck", "truck-parking")]]
    folder = Path(os.environ["NEUROANIMATOR_DATA_DIR"]) / "policies" / "lander" / "lander-landing"
    assert (folder / policy["version"] / "policy.onnx").is_file()
    assert [j["id"] for j in api.get("/policy-jobs").json()["jobs"]] == [job_id]


BAD: list[tuple[dict[str, Any], str, str]] = [
    ({"task": "lander-hover"}, "task", "lander-landing"),  # the message names the built-in tasks
    ({"task": "lander-landing", "seconds": 100_000}, "seconds", "1800"),
    ({"task": "lander-landing", "seconds": 2}, "seconds", "greater than or equal to 5"),
    ({"task": "lander-landing", "seconds": "60"}, "seconds", "valid number"),
    ({"task": "lander-landing", "batch": 0}, "batch", "greater than or equal to 1"),
    ({"task": "lander-landing", "hidden": [64, 0]}, "hidden[1]", "greater than or equal to 1"),
    ({"task": "lander-landing", "hidden": []}, "hidden", "at least 1"),
    ({"task": "lander-landing", "refine": "yes"}, "refine", "boolean"),
    ({"task": "lander-landing", "seeds": 2}, "seeds", "a goal-reaching task trains from one seed"),
    ({"task": "lander-landing", "seeds": 9}, "seeds", "less than or equal to 8"),
    ({"task": "lander-landing", "wings": 2}, "wings", "xtra"),
    ({}, "task", "required"),
]


@pytest.mark.parametrize(("body", "field", "text"), BAD, ids=[f"{b[1]}-{i}" for i, b in enumerate(BAD)])
def test_bad_policy_requests_are_422_naming_the_field(
    ctl: Controller, body: dict[str, Any], field: str, text: str
) -> None:
    # refused before Redis is asked: this app's Redis is a closed port
    api = ctl.client(redis_url=f"redis://127.0.0.1:{_closed_port()}/0")
    r = api.post("/policies", json=body)
    assert r.status_code == 422, r.text
    err = r.json()
    assert err["field"] == field and text in err["message"], err


def test_a_reward_jobs_seeds_reach_its_training_and_a_goal_jobs_never_do() -> None:
    reward = PolicyJobSpec(task="walker-stand", model="walker", emulator_version="v", substeps=10,
                           seconds=60, refine=True, hidden=[64, 64], seeds=3)  # fmt: skip
    assert training_settings(reward, threads=1)["seeds"] == 3
    assert "seeds" not in training_settings(reward.model_copy(update={"task": "lander-landing"}), threads=1)


def test_a_jobs_threads_are_the_operators_when_set_else_its_tasks_own() -> None:
    """WORKER_THREADS unset: the acrobot's policy trains on its task's two threads (at most the cores),
    as the CLI and the bench train it; a goal job on one. Set: every job that many."""
    from neuroanimator.control.policy import PolicySettings
    from neuroanimator.control.reward_policy import RewardSettings
    from neuroanimator.control.seed_race import thread_count
    from neuroanimator.control.suite_tasks import SUITE_TASKS

    acrobot = SUITE_TASKS["acrobot-swingup"]
    reward = PolicyJobSpec(task=acrobot.name, model="acrobot", emulator_version="v", substeps=5,
                           seconds=60, refine=False, hidden=[64])  # fmt: skip
    cores = min(acrobot.threads, os.cpu_count() or 1)
    assert acrobot.threads == 2 and Settings.model_fields["worker_threads"].default is None
    assert thread_count(acrobot, RewardSettings(**training_settings(reward, threads=None))) == cores
    assert thread_count(acrobot, RewardSettings(**training_settings(reward, threads=1))) == 1
    goal = reward.model_copy(update={"task": "lander-landing", "model": "lander"})
    assert PolicySettings(**training_settings(goal, threads=None)).threads == 1
    assert PolicySettings(**training_settings(goal, threads=3)).threads == 3


def test_unknown_task_lists_the_built_in_ones(ctl: Controller) -> None:
    api = ctl.client(redis_url=f"redis://127.0.0.1:{_closed_port()}/0")
    err = api.post("/policies", json={"task": "lander-hover"}).json()
    assert err["error"] == "invalid_job" and err["got"] == "lander-hover"
    assert {"lander-landing", "pendulum-swing", "truck-parking", "quadrotor-follow"} <= set(err["expected"])
    tasks = {t["name"]: t for t in api.get("/policy-tasks").json()["tasks"]}
    assert set(err["expected"]) == set(tasks)
    assert (tasks["lander-landing"]["model"], tasks["lander-landing"]["substeps"]) == ("lander", 25)
    assert tasks["lander-landing"]["success_criterion"]


def test_a_task_without_an_emulator_at_its_super_step_is_422(ctl: Controller, tmp_path: Path) -> None:
    """A registry whose lander has only its n = 50 emulator: the task (n = 25) cannot be trained."""
    arts = tmp_path / "arts" / "lander"
    arts.mkdir(parents=True)
    version = (ARTIFACTS / "lander" / "latest-n50").read_text().strip()
    (arts / version).symlink_to(ARTIFACTS / "lander" / version)
    for pointer in ("latest", "latest-n50"):
        (arts / pointer).write_text(version + "\n")
    api = ctl.client(artifacts_dir=str(tmp_path / "arts"), redis_url=f"redis://127.0.0.1:{_closed_port()}/0")
    r = api.post("/policies", json={"task": "lander-landing", "seconds": 10})
    assert r.status_code == 422, r.text
    err = r.json()
    assert err["field"] == "task" and "n = 25" in err["message"], err
    assert err["got"] == {"model": "lander", "substeps": [50]}
    # a model the registry lacks altogether
    r = api.post("/policies", json={"task": "truck-parking", "seconds": 10})
    assert r.status_code == 422 and "unknown model" in r.json()["message"], r.text


def test_cancel_a_queued_policy_job_stores_nothing(ctl: Controller) -> None:
    api = ctl.client()
    job_id = api.post("/policies", json=QUICK_POLICY).json()["id"]
    # RQ would kill a delivery past its timeout: it covers the longest policy job, not JOB_TIMEOUT_S's
    delivery = Job.fetch(f"{job_id}-1", connection=ctl.r, serializer=JSONSerializer)
    assert delivery.timeout is not None and delivery.timeout >= 1800 + 300
    r = api.delete(f"/policy-jobs/{job_id}")
    assert r.status_code == 202 and r.json()["status"] == "cancelled", r.text
    assert r.json()["error"] == "cancelled before it started"
    assert api.delete(f"/policy-jobs/{job_id}").status_code == 409  # already ended
    res = api.get(f"/policy-jobs/{job_id}/result").json()
    assert (res["status"], res["policy"], res["iterations"]) == ("cancelled", None, 0)
    listed = {(p["model"], p["name"]): p["version"] for p in api.get("/policies").json()["policies"]}
    assert listed == committed_policies()  # the committed defaults, nothing new
    # a control job is not a policy job
    control = api.post("/jobs", json=QUICK).json()["id"]
    wrong = api.get(f"/policy-jobs/{control}")
    assert wrong.status_code == 404 and f"/jobs/{control}" in wrong.json()["message"]
    assert [j["id"] for j in api.get("/policy-jobs").json()["jobs"]] == [job_id]


def test_cancel_a_running_policy_job_before_its_first_check_stores_nothing(ctl: Controller) -> None:
    """Cancelled at its first iterations, long before its first check on MuJoCo: an untrained network
    is not worth a version (nor moving ``latest`` to it)."""
    api = ctl.client()
    job_id = api.post("/policies", json={**QUICK_POLICY, "seconds": 600}).json()["id"]
    ctl.worker("--name", ctl.name("w-policy-cancel"))
    wait_for("an iteration", lambda: policy_job(api, job_id)["iteration"] >= 1, timeout=60)
    r = api.delete(f"/policy-jobs/{job_id}")
    assert r.status_code == 202 and r.json()["status"] in ("running", "cancelled"), r.text
    done = policy_ended(api, job_id, timeout=60)
    assert done["status"] == "cancelled", (done, ctl.logs())
    assert "before its first check on MuJoCo; nothing stored" in done["error"]
    res = api.get(f"/policy-jobs/{job_id}/result").json()
    assert res["policy"] is None and res["iterations"] >= 1
    # the lander's latest policy is still the committed default
    latest = api.get("/policies/lander/lander-landing").json()["version"]
    assert latest == committed_policies()[("lander", "lander-landing")]


def test_past_its_time_limit_a_policy_job_fails_with_the_best_so_far(ctl: Controller) -> None:
    """A budget plus ``POLICY_OVERHEAD_S`` shorter than drawing the goals and training takes."""
    api = ctl.client()
    job_id = api.post("/policies", json={**QUICK_POLICY, "seconds": 6}).json()["id"]
    ctl.worker("--burst", env={"POLICY_OVERHEAD_S": "0.1"})
    done = policy_ended(api, job_id, timeout=60)
    assert done["status"] == "failed" and "time limit of 6.1 s" in done["error"], (done, ctl.logs())
    res = api.get(f"/policy-jobs/{job_id}/result").json()
    # stored when it was checked on MuJoCo before the limit (the usual case), else nothing
    assert res["policy"] is None or res["policy"]["metrics"]["stop"] == "cancelled"


# ---------------------------------------------------------------- a user's own policy task
# the truck parks within 5 m of the origin, facing any heading (its heading weighs nothing and is no
# goal), from near the origin at rest; trained at the truck's latest emulator (n = 50, 0.5 s)
TRUCK_NEAR: dict[str, Any] = {
    "model": "truck",
    "name": "truck-near",
    "summary": "Truck: park within 5 m of the origin, facing any heading, and stop there in 10 s.",
    "episode_s": 10,
    "starts": {"low": [-1, -1, -math.pi, 0, 0, 0], "high": [1, 1, math.pi, 0, 0, 0]},
    "goal": {"variables": ["position.x", "position.y"], "low": [-5, -5], "high": [5, 5]},
    "target_state": [0, 0, 0, 0, 0, 0],
    "state_weights": [1, 1, 0, 3, 3, 0.5],
    "success": [
        {"check": "distance", "variables": ["position.x", "position.y"], "max": 1.5},
        {"check": "norm", "variables": ["velocity.x", "velocity.y"], "max": 0.5},
    ],
    "settle_s": 5,
}


def with_task(**changes: Any) -> dict[str, Any]:
    """TRUCK_NEAR with some of its fields (``starts__low``: a field of a part) replaced."""
    task = copy.deepcopy(TRUCK_NEAR)
    for key, value in changes.items():
        part, _, field = key.rpartition("__")
        (task[part] if part else task)[field] = value
    return task


def test_a_custom_policy_task_trains_and_stores_under_its_name(ctl: Controller) -> None:
    api = ctl.client()
    r = api.post("/policies", json={"task": TRUCK_NEAR, "seconds": 6, "refine": False, "batch": 16})
    assert r.status_code == 202, r.text
    job_id = r.json()["id"]
    queued = policy_job(api, job_id)
    assert (queued["task"], queued["model"], queued["seconds"]) == ("truck-near", "truck", 6.0)
    latest = (ARTIFACTS / "truck" / "latest").read_text().strip()
    assert queued["emulator_version"] == latest  # no substeps: the model's latest emulator

    worker = ctl.worker("--burst", "--name", ctl.name("w-custom"))
    done = policy_ended(api, job_id)
    assert worker.wait(timeout=60) == 0, ctl.logs()
    assert done["status"] == "succeeded", (done, ctl.logs())
    policy = api.get(f"/policy-jobs/{job_id}/result").json()["policy"]
    assert api.get("/policies/truck/truck-near").json() == policy
    assert (policy["name"], policy["model"], policy["emulator_version"]) == ("truck-near", "truck", latest)
    assert policy["description"] == TRUCK_NEAR["summary"]
    # the goals it was trained for are the task's: position only, inside its 5 m box
    assert policy["goal_variables"] == ["position.x", "position.y"]
    assert all(-5 <= lo <= hi <= 5 for lo, hi in zip(policy["goal_low"], policy["goal_high"], strict=True))
    assert policy["task"]["success"] == TRUCK_NEAR["success"]
    assert policy["task"]["episode_s"] == 10 and policy["metrics"]["iterations"] >= 1

    # no name: custom-<model>; a super-step of its own: the emulator at that n
    r = api.post("/policies", json={"task": with_task(name=None, substeps=25), "seconds": 6})
    assert r.status_code == 202, r.text
    other = policy_job(api, r.json()["id"])
    assert other["task"] == "custom-truck" and other["emulator_version"].startswith("n25-")
    assert api.delete(f"/policy-jobs/{other['id']}").json()["status"] == "cancelled"


INF = 1e400  # JSON can carry it (a number too large for a double): it reads as infinity
BAD_TASKS: list[tuple[dict[str, Any], str, str]] = [
    (with_task(model="nope"), "task.model", "unknown model 'nope'"),
    (with_task(substeps=7), "task.substeps", "substeps=7"),
    (with_task(name="truck-parking"), "task.name", "built-in"),
    (with_task(name="cartpole-swingup"), "task.name", "built-in"),  # a suite task's name is one too
    (with_task(name="../x"), "task.name", "pattern"),
    (with_task(target_state=[0, 0, 0]), "task.target_state", "6 values"),
    (with_task(state_weights=[1] * 7), "task.state_weights", "6 values"),
    (with_task(state_weights=[0, 0, 1, 1, 1, 1]), "task.state_weights", "weigh 0"),
    (with_task(state_weights=[1, 1, -1, 1, 1, 1]), "task.state_weights[2]", "greater than or equal to 0"),
    (with_task(starts__low=[0, 0, 0]), "task.starts.low", "6 values"),
    (with_task(starts__low=[2, -1, -1, 0, 0, 0]), "task.starts.low[0]", "above high"),
    (with_task(starts__random_yaw=True), "task.starts.random_yaw", "no orientation quaternion"),
    (with_task(goal__variables=["position.x", "position.z"]), "task.goal.variables[1]", "position.z"),
    (with_task(goal__variables=["position.x", "position.x"]), "task.goal.variables[1]", "twice"),
    (with_task(goal__low=[-5]), "task.goal.low", "2 values"),
    (with_task(goal__low=[-5, 6]), "task.goal.low[1]", "above high"),
    (with_task(goal__high=[5, INF]), "task.goal.high[1]", "finite number"),
    (with_task(target_state=[0, 0, INF, 0, 0, 0]), "task.target_state[2]", "finite number"),
    (with_task(state_weights=[1, 1, 0, -INF, 1, 1]), "task.state_weights[3]", "finite number"),
    (with_task(episode_s=INF), "task.episode_s", "finite number"),
    (
        with_task(success=[{"check": "norm", "variables": ["speed"], "max": 1}]),
        "task.success[0].variables",
        "speed",
    ),
    (with_task(success=[{"check": "distance", "variables": ["heading"]}]), "task.success[0].max", "required"),
    (with_task(success=[]), "task.success", "at least 1"),
    (with_task(episode_s=0.2), "task.episode_s", "super-step"),
    (with_task(goal_period_s=12), "task.goal_period_s", "run's 10 s"),
    (with_task(goal_period_s=5, check_after_s=6), "task.check_after_s", "period (5 s)"),
    (with_task(settle_s=11), "task.settle_s", "period (10 s)"),
    (with_task(wings=2), "task.wings", "xtra"),
    (with_task(starts=None), "task.starts", "valid dictionary"),
]


@pytest.mark.parametrize(
    ("task", "field", "text"), BAD_TASKS, ids=[f"{b[1]}-{i}" for i, b in enumerate(BAD_TASKS)]
)
def test_bad_custom_tasks_are_422_naming_the_field(
    ctl: Controller, task: dict[str, Any], field: str, text: str
) -> None:
    api = ctl.client(redis_url=f"redis://127.0.0.1:{_closed_port()}/0")
    # json.dumps writes infinity as Infinity, which JSON lacks: send 1e400, as a client's JSON would
    body = json.dumps({"task": task, "seconds": 6}).replace("Infinity", "1e400")
    r = api.post("/policies", content=body, headers={"content-type": "application/json"})
    assert r.status_code == 422, r.text
    err = r.json()
    assert err["field"] == field and text in err["message"], err


def test_a_custom_task_names_the_expected_and_the_got(ctl: Controller) -> None:
    api = ctl.client(redis_url=f"redis://127.0.0.1:{_closed_port()}/0")
    err = api.post("/policies", json={"task": with_task(goal__variables=["position.x", "speed"])}).json()
    assert (err["error"], err["got"]) == ("invalid_job", "speed")
    assert err["expected"] == ["position.x", "position.y", "heading", "velocity.x", "velocity.y", "yaw_rate"]
    err = api.post("/policies", json={"task": with_task(substeps=7)}).json()
    assert (err["got"], err["expected"]) == (7, [25, 50, 100])
    err = api.post("/policies", json={"task": 3}).json()
    assert err["field"] == "task" and "built-in policy task's name or a policy task" in err["message"]


def test_a_custom_task_on_a_model_the_caller_does_not_see_is_422(ctl: Controller, tmp_path: Path) -> None:
    """Another key's upload of a truck: to this key there is no such model, as for a built-in task."""
    arts = tmp_path / "arts" / "truck"
    arts.mkdir(parents=True)
    for entry in (ARTIFACTS / "truck").iterdir():
        (arts / entry.name).symlink_to(entry)
    tenancy.write(tmp_path / "arts", "truck", tenancy.Ownership.new("another-key-id"))
    api = ctl.client(
        artifacts_dir=str(tmp_path / "arts"),
        api_keys="key-a",
        redis_url=f"redis://127.0.0.1:{_closed_port()}/0",
    )
    r = api.post("/policies", json={"task": TRUCK_NEAR}, headers={"Authorization": "Bearer key-a"})
    assert r.status_code == 422, r.text
    err = r.json()
    assert err["field"] == "task.model" and "unknown model 'truck'" in err["message"], err
    assert "truck" not in err["expected"]


def test_a_suite_task_without_its_domains_model_is_422_saying_how_to_make_it(ctl: Controller) -> None:
    api = ctl.client(redis_url=f"redis://127.0.0.1:{_closed_port()}/0")
    tasks = {t["name"]: t for t in api.get("/policy-tasks").json()["tasks"]}
    reacher = tasks["reacher-hard"]
    assert (reacher["kind"], reacher["model"], reacher["substeps"]) == ("reward", "reacher", 2)
    assert reacher["goal_variables"] == ["target.x", "target.y"] and reacher["target_return"] == 900
    assert reacher["success_criterion"].endswith("(mean of 10 episodes) at least 900")
    humanoid = tasks["humanoid-stand"]  # no target: its return is reported
    assert (humanoid["model"], humanoid["substeps"], humanoid["target_return"]) == ("humanoid", 5, 0)
    assert humanoid["success_criterion"].startswith("none set")
    r = api.post("/policies", json={"task": "reacher-hard", "seconds": 10})
    assert r.status_code == 422, r.text
    err = r.json()
    assert err["field"] == "task" and "neuro train --mjcf dm_control/suite/reacher.xml" in err["message"], err
    assert "--time-budget" not in err["message"], err  # the default budget: not written out
    # a body on the ground: its emulator needs three times the default's data and training
    r = api.post("/policies", json={"task": "walker-stand", "seconds": 10})
    assert r.status_code == 422, r.text
    assert "--substeps 10 --time-budget 900" in r.json()["message"], r.text


def test_a_suite_task_trains_through_a_worker_and_reports_its_returns(ctl: Controller) -> None:
    """dm_control's point_mass, brought in as a user's MJCF under its domain's name, then its suite
    task as a policy job: trained by a worker for its reward (two seeds side by side), stored, its
    returns in the result."""
    data = Path(os.environ["NEUROANIMATOR_DATA_DIR"])
    subprocess.run(
        [sys.executable, "-m", "neuroanimator.cli", "train", "--mjcf", str(Path(suite.__file__).parent / "point_mass.xml"),
         "--name", "point_mass", "--substeps", "2", "--examples", "2000", "--epochs", "20", "--hidden", "32",
         "--rollout-steps", "0", "--force", "--quiet", "--out", str(data)],
        check=True, capture_output=True, timeout=300,
    )  # fmt: skip
    api = ctl.client()
    r = api.post(
        "/policies", json={"task": "point_mass-easy", "seconds": 8, "batch": 16, "refine": False, "seeds": 2}
    )
    assert r.status_code == 202, r.text
    job_id = r.json()["id"]
    queued = policy_job(api, job_id)
    assert (queued["model"], queued["emulator_version"][:3]) == ("point_mass", "n2-")
    worker = ctl.worker("--burst", "--name", ctl.name("w-suite"))
    done = policy_ended(api, job_id, timeout=180)
    assert worker.wait(timeout=60) == 0, ctl.logs()
    assert done["status"] == "succeeded", (done, ctl.logs())
    progress = [d for e, d in sse(api.get(f"/policy-jobs/{job_id}/events").text) if e == "progress"]
    assert [p["iteration"] for p in progress] == list(range(1, done["iteration"] + 1))
    assert any(p["return_physics"] is not None for p in progress)
    # the status says the last check's return, as the progress did
    assert done["return_physics"] == progress[-1]["return_physics"] and done["success_physics"] is None
    res = api.get(f"/policy-jobs/{job_id}/result").json()
    metrics = res["policy"]["metrics"]
    assert 0 <= metrics["return_physics"] <= 1000 and metrics["success_physics"] is None
    # two seeds trained side by side in the job, the better kept
    assert len(metrics["seed_returns"]) == 2 and metrics["return_physics"] == max(metrics["seed_returns"])
    assert res["return_history"] and res["success_history"] == []
    assert all(0 <= p["value"] <= 1000 for p in res["return_history"])
    assert api.get("/policies/point_mass/point_mass-easy").json() == res["policy"]

    # a reward of the user's own on the same model: the point mass kept still with small controls,
    # beside one whose term names a body the model lacks (the API cannot read the MJCF: the job fails)
    still = {"kind": "reward", "model": "point_mass", "name": "hold-still", "episode_s": 2, "starts": "rest",
             "terms": [{"kind": "still", "body": "pointmass", "margin": 0.1}, {"kind": "small_control"}]}  # fmt: skip
    r = api.post("/policies", json={"task": still, "seconds": 6, "batch": 16, "refine": False})
    assert r.status_code == 202, r.text
    own = r.json()["id"]
    lacking = {**still, "name": "no-such-body", "terms": [{"kind": "height", "body": "head", "at_least": 1}]}
    bad = api.post("/policies", json={"task": lacking, "seconds": 6, "batch": 16, "refine": False}).json()[
        "id"
    ]
    for wrong, field in (
        ({**still, "episode_s": 0.001}, "task.episode_s"),
        ({**still, "name": "walker-stand"}, "task.name"),
        ({**still, "model": "nobody"}, "task.model"),
    ):
        r = api.post("/policies", json={"task": wrong, "seconds": 6})
        assert r.status_code == 422 and r.json()["field"] == field, r.text
    r = api.post("/policies", json={"task": {**still, "terms": [{"kind": "speed"}]}, "seconds": 6})
    assert r.status_code == 422 and "a speed term needs at_least" in r.text, r.text
    worker = ctl.worker("--burst", "--name", ctl.name("w-own"))
    done = policy_ended(api, own, timeout=180)
    failed = policy_ended(api, bad, timeout=60)
    assert worker.wait(timeout=60) == 0, ctl.logs()
    assert done["status"] == "succeeded" and done["task"] == "hold-still", (done, ctl.logs())
    stored = api.get(f"/policy-jobs/{own}/result").json()["policy"]
    assert stored["name"] == "hold-still" and 0 <= stored["metrics"]["return_physics"] <= 100  # 2 s at 20 ms
    assert failed["status"] == "failed", failed
    reason = api.get(f"/policy-jobs/{bad}/result").json()["reason"]
    assert "no body 'head'" in reason and "'pointmass'" in reason, reason
