"""Upload to drive, with API keys on: a model folder uploaded as a .zip trains with a tiny budget in a
real training worker; the emulator service (started before, never restarted) then serves it to the
uploading key only, a session steps it, the controller service runs a job on it through a real worker;
an operator publishes it (every key then sees it) and deletes it. Trainings that cannot succeed fail
in the worker with the reason (a model that diverges: the time and the joint; one that samples too
slowly: the estimate), and a running training is cancelled within seconds, leaving nothing behind."""

from __future__ import annotations

import os
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from fastapi.testclient import TestClient

from services.controller.app import create_app as controller_app
from services.controller.settings import Settings as ControllerSettings
from services.emulator.app import create_app as emulator_app
from services.emulator.settings import Settings as EmulatorSettings
from tests.services.queues import sse
from tests.services.trainer.trn import KEYS, TINY, TINYBOT, Trainer, auth, ended, upload, wait_for, zipped

A, B, OP = auth("key-a"), auth("key-b"), auth("key-op")
WOBBLY = b"""<mujoco model="wobbly">
  <option timestep="0.05"/>
  <worldbody>
    <body name="link">
      <joint name="spring" type="hinge" stiffness="1e7"/>
      <geom type="capsule" fromto="0 0 0 0.3 0 0" size="0.02" mass="0.01"/>
    </body>
  </worldbody>
  <actuator><motor name="m" joint="spring" ctrlrange="-1 1"/></actuator>
</mujoco>"""


@pytest.fixture(name="trn", scope="module")
def trn_fixture(redis_url: str, tmp_path_factory: pytest.TempPathFactory) -> Iterator[Trainer]:
    t = Trainer(redis_url, tmp_path_factory.mktemp("trainer"), JOB_TIMEOUT_S="120", **KEYS)
    t.worker()  # one training worker for the module: the trainings below run one after another
    try:
        yield t
    finally:
        t.close()


def test_upload_train_drive_control_publish_delete(trn: Trainer, tmp_path: Path) -> None:
    api = trn.client()
    common: dict[str, Any] = {
        "data_dir": trn.data,
        "artifacts_dir": trn.defaults,
        "api_keys": KEYS["API_KEYS"],
    }
    common |= {"operator_keys": "key-op", "api_key_secret": KEYS["API_KEY_SECRET"]}
    emulator = TestClient(emulator_app(EmulatorSettings(**common, redis_url="", registry_poll_s=0.1)))
    emulator.__enter__()
    trn.clients.append(emulator)
    assert emulator.get("/models", headers=A).json()["models"] == []  # running before the model exists

    r = upload(api, "tinybot.zip", zipped(TINYBOT), key="key-a", **TINY)
    assert r.status_code == 202, r.text
    tid = r.json()["id"]
    assert api.get(f"/trainings/{tid}", headers=B).status_code == 404  # another key's training
    done = ended(api, tid, key="key-a")
    assert done["status"] == "succeeded", (done, trn.logs())
    assert (done["phase"], done["percent"]) == ("done", 100.0)
    assert [p["epoch"] for p in done["loss_curve"]] == [1, 2, 3]
    res = done["result"]
    assert res["model"] == "tinybot" and res["artifact"] == f"tinybot/{res['version']}"
    assert res["substeps"] == 10 and res["examples"] == 200
    assert 0 < res["one_step_rel_error"] < 1 and res["linear_baseline_rel_error"] > 0
    assert res["physical_errors"]["joint_angle_rad"][0]["t_s"] == 1.0
    assert set(res["phase_seconds"]) == {"validating", "sampling", "training", "evaluating", "exporting"}
    events = sse(api.get(f"/trainings/{tid}/events", headers=A).text)
    phases = [d["phase"] for e, d in events if e == "progress"]
    assert [p for i, p in enumerate(phases) if i == 0 or phases[i - 1] != p] == [
        "validating",
        "sampling",
        "training",
        "evaluating",
        "exporting",
    ]
    assert events[-1][0] == "end" and events[-1][1]["result"]["version"] == res["version"]
    streamed = [p for e, d in events if e == "progress" for p in d["losses"]]
    assert streamed == [[p["epoch"], p["loss"]] for p in done["loss_curve"]]  # the curve, live
    wait_for("the upload removed", lambda: not any(trn.settings().uploads().iterdir()), 10)

    # the emulator service serves it without a restart, to the key that uploaded it
    wait_for("the emulator to list it", lambda: emulator.get("/models", headers=A).json()["models"], 10)
    assert emulator.get("/models", headers=B).json()["models"] == []
    assert emulator.post("/sessions", json={"model": "tinybot"}, headers=B).status_code == 404
    s = emulator.post("/sessions", json={"model": "tinybot", "seed": 1}, headers=A)
    assert s.status_code == 201, s.text
    sid = s.json()["id"]
    step = emulator.post(f"/sessions/{sid}/step", json={"controls": [0.5], "steps": 3}, headers=A)
    assert step.status_code == 200 and len(step.json()["state"]) == 2, step.text

    # the controller service runs a job on it (for that key only)
    ctl_env = {"REDIS_PREFIX": f"test-controller:{trn.tag}", "QUEUE_NAME": f"test-controller-{trn.tag}"}
    cs: dict[str, Any] = {**common, "redis_url": trn.env["REDIS_URL"]}
    cs |= {k.lower(): v for k, v in ctl_env.items()}
    controller = TestClient(controller_app(ControllerSettings(**cs)))
    controller.__enter__()
    trn.clients.append(controller)
    spec = {"model": "tinybot", "horizon": 5, "optimizer": {"max_iterations": 2}}
    refused = controller.post("/jobs", json=spec, headers=B)
    assert refused.status_code == 422 and refused.json()["field"] == "model", refused.text
    assert refused.json()["message"].endswith("trained models are []")  # another key's model is not named
    job = controller.post("/jobs", json=spec, headers=A)
    assert job.status_code == 202, job.text
    env = {**os.environ, **{k.upper(): str(v) for k, v in common.items()}, **ctl_env}
    env["REDIS_URL"] = trn.env["REDIS_URL"]
    ran = subprocess.run(
        [sys.executable, "-m", "services.controller.worker", "--burst", "--name", f"c-{trn.tag}"],
        env=env,
        cwd=tmp_path,
        capture_output=True,
        timeout=180,
        check=False,
    )
    assert ran.returncode == 0, ran.stderr[-2000:]
    got = controller.get(f"/jobs/{job.json()['id']}", headers=A).json()
    assert got["status"] == "succeeded", got

    # an operator publishes it: every key sees it
    assert api.post("/models/tinybot/publish", headers=A).status_code == 403
    assert api.get("/models", headers=B).json()["models"] == []
    listed = api.get("/models", headers=OP).json()["models"]
    assert [(m["model"], m["versions"]) for m in listed] == [("tinybot", [res["version"]])]
    assert listed[0]["owner"].startswith("k-") and listed[0]["size_bytes"] > 0
    published = api.post("/models/tinybot/publish", headers=OP)
    assert published.status_code == 200 and published.json()["published"], published.text
    assert emulator.post("/sessions", json={"model": "tinybot"}, headers=B).status_code == 201
    # the name stays the uploader's: another key cannot train under it
    taken = upload(api, "tinybot.zip", zipped(TINYBOT), key="key-b", **TINY)
    assert taken.status_code == 409 and taken.json()["error"] == "name_taken", taken.text

    # an operator deletes it: gone from the registry, its policies with it, and from the emulator's list
    learned = trn.data / "policies" / "tinybot" / "hover"
    learned.mkdir(parents=True)
    (learned / "latest").write_text("p-1\n")
    assert api.delete("/models/tinybot", headers=B).status_code == 404
    assert api.delete("/models/tinybot", headers=A).status_code == 403  # published: operators only
    assert api.delete("/models/tinybot", headers=OP).status_code == 200
    assert not (trn.data / "tinybot").exists() and not learned.parent.exists()
    assert (trn.data / "policies").is_dir()  # the other models' policies stay
    wait_for(
        "the emulator to drop it", lambda: emulator.get("/models", headers=OP).json()["models"] == [], 10
    )


def test_trainings_that_cannot_succeed_fail_naming_why(trn: Trainer) -> None:
    api = trn.client()
    diverges = upload(api, "wobbly.xml", WOBBLY, key="key-a", **TINY)
    slow = upload(
        api,
        "tinybot.zip",
        zipped(TINYBOT),
        key="key-b",
        name="slowbot",
        super_step="1000",
        examples="1000000",
    )
    assert diverges.status_code == 202 and slow.status_code == 202, (diverges.text, slow.text)
    failed = ended(api, diverges.json()["id"], key="key-a")
    assert failed["status"] == "failed" and failed["phase"] == "failed", failed
    assert "diverged 0.05 s into" in failed["error"] and "joint 'spring'" in failed["error"]
    assert "smaller timestep" in failed["error"]
    failed = ended(api, slow.json()["id"], key="key-b")
    assert failed["status"] == "failed", failed
    assert "samples too slowly" in failed["error"] and "JOB_TIMEOUT_S" in failed["error"]
    assert "smaller sample budget" in failed["error"]
    wait_for("both names given back", lambda: trn.models() == [], 10)  # nothing exported
    assert failed["attempt"] == 1 and failed["failures"] == 0  # not retried: it would fail the same way


def test_a_running_training_is_cancelled_at_once(trn: Trainer) -> None:
    api = trn.client()
    r = upload(api, "tinybot.zip", zipped(TINYBOT), key="key-a", super_step="10", examples="100000")
    assert r.status_code == 202, r.text
    tid = r.json()["id"]

    def sampling() -> bool:
        got = api.get(f"/trainings/{tid}", headers=A).json()
        assert got["status"] in ("queued", "running"), got
        return bool(got["phase"] in ("sampling", "training"))

    wait_for("it to sample", sampling, 60)
    assert api.delete(f"/trainings/{tid}", headers=A).status_code == 202
    done = ended(api, tid, timeout=20, key="key-a")
    assert done["status"] == "cancelled" and done["phase"] == "cancelled", done
    # the worker cleans up once it has ended the training: nothing exported, nothing left
    left = [trn.settings().uploads(), trn.settings().staging()]
    wait_for(
        "the name and files given back",
        lambda: trn.models() == [] and not any(any(d.iterdir()) for d in left),
        10,
    )
