"""A training worker SIGKILLed under ``services.stack`` while it trains: the stack restarts it and kills
what it had started (the job process and the training: no orphan renews the lease), the new worker is
counted by ``/readyz``, and the training goes back to the queue and runs again."""

from __future__ import annotations

import os
import signal
import time
from pathlib import Path

import httpx

from tests.e2e.harness import running_stack
from tests.services.queues import wait_for
from tests.services.trainer.trn import TINYBOT, zipped

LONG = {"super_step": "10", "examples": "200", "epochs": "5000", "hidden": "8", "rollout_steps": "0"}


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    state = (
        Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
        if Path(f"/proc/{pid}").exists()
        else "X"
    )
    return state not in ("Z", "X")


def test_a_killed_training_worker_is_restarted_without_orphans(tmp_path: Path) -> None:
    with running_stack(tmp_path, controller=False, env={"LEASE_TTL_S": "2", "REAP_INTERVAL_S": "0.5"}) as s:
        api = httpx.Client(base_url=s.urls["trainer"], timeout=60)
        wait_for("the training worker", lambda: api.get("/readyz").status_code == 200, timeout=60)
        r = api.post(
            "/trainings", files={"file": ("tinybot.zip", zipped(TINYBOT))}, data={**LONG, "force": "true"}
        )
        assert r.status_code == 202, r.text
        job = r.json()["id"]
        wait_for(
            "the training", lambda: api.get(f"/trainings/{job}").json()["phase"] == "training", timeout=120
        )
        worker = s.services["training-worker"]
        assert worker.proc is not None
        old_pid = worker.proc.pid
        started = [
            int(p.parent.name)
            for p in Path("/proc").glob("[0-9]*/stat")
            if p.exists() and _session(p) == old_pid and int(p.parent.name) != old_pid
        ]
        assert started, "the worker had started no job process"
        os.kill(old_pid, signal.SIGKILL)
        worker.proc.wait(10)
        s.check()  # what the stack's loop does every second
        assert worker.proc.pid != old_pid and worker.proc.poll() is None
        time.sleep(0.5)
        assert not [p for p in started if _alive(p)], "orphans of the killed worker live on"
        again = wait_for(
            "the training to run again",
            lambda: (
                (b := api.get(f"/trainings/{job}").json())["attempt"] >= 2 and b["status"] == "running" and b
            ),
            timeout=120,
        )
        assert again["status"] == "running"
        assert api.get("/readyz").json()["workers"] >= 1  # the dead one counts until WORKER_ALIVE_S
        api.delete(f"/trainings/{job}")


def _session(stat: Path) -> int:
    try:
        return int(stat.read_text().rsplit(")", 1)[1].split()[3])
    except (OSError, IndexError, ValueError):
        return -1
