"""Controller jobs through workers killed with SIGKILL: are any lost or run to the end twice?

    python bench/jobs_sigkill.py [--jobs 100] [--workers 3] [--kill-every 8] [--json]

It starts a private ``redis-server``, the controller API and ``--workers`` workers on the committed
artifacts, submits ``--jobs`` short jobs (pendulum-swing, 3 iterations), and every ``--kill-every``
seconds kills a random worker *and its job process* with SIGKILL (a machine gone) while it runs a job,
starting a fresh worker in its place. The run ends when every job has ended (or ``--timeout``).

Reported: jobs succeeded, failed, lost (not ended by the timeout), finished twice (the finished-jobs
count beyond the number of jobs), kills, re-queues (``controller_jobs_requeued``) and the worker count
of ``/readyz`` at the end against the workers alive.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import random
import re
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import httpx
import redis
from _server import REPO, serve
from soak import private_redis

QUICK_JOB = {"task": "pendulum-swing", "optimizer": {"max_iterations": 3}}
FINAL = ("succeeded", "failed", "cancelled")


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--jobs", type=int, default=100)
    p.add_argument("--workers", type=int, default=3)
    p.add_argument("--kill-every", type=float, default=8.0, help="seconds between SIGKILLs")
    p.add_argument("--timeout", type=float, default=900.0, help="seconds for every job to end")
    p.add_argument("--artifacts", default=str(REPO / "artifacts"))
    p.add_argument("--json", action="store_true")
    args = p.parse_args()
    with tempfile.TemporaryDirectory() as tmp, private_redis(Path(tmp)) as (redis_url, _):
        env = {
            "REDIS_URL": redis_url,
            "LOG_LEVEL": "warning",
            "JOB_RETRIES": "20",  # kills are the test: a job is retried, not failed, after a few
            "LEASE_TTL_S": "3",
            "REAP_INTERVAL_S": "1",
            "MAX_QUEUE": str(args.jobs + 10),
        }
        worker_env = {**os.environ, **env, "ARTIFACTS_DIR": args.artifacts, "PYTHONPATH": str(REPO)}
        workers: list[subprocess.Popen[bytes]] = []

        def start_worker() -> None:
            workers.append(
                subprocess.Popen(
                    [sys.executable, "-m", "services.controller.worker"],
                    env=worker_env,
                    cwd=tmp,
                    stdout=subprocess.DEVNULL,
                    stderr=subprocess.DEVNULL,
                )
            )

        r = redis.Redis.from_url(redis_url)
        kills = 0
        with (
            serve(args.artifacts, "services.controller", ready="/healthz", **env) as (url, _pid),
            httpx.Client(base_url=url, timeout=30) as api,
        ):
            for _ in range(args.workers):
                start_worker()
            ids = []
            for _ in range(args.jobs):
                resp = api.post("/jobs", json=QUICK_JOB)
                resp.raise_for_status()
                ids.append(resp.json()["id"])
            t0 = time.monotonic()
            next_kill = t0 + args.kill_every
            status: dict[str, str] = {}
            while time.monotonic() - t0 < args.timeout:
                for job_id in ids:
                    if status.get(job_id) not in FINAL:
                        status[job_id] = api.get(f"/jobs/{job_id}").json()["status"]
                if all(s in FINAL for s in status.values()):
                    break
                if time.monotonic() >= next_kill:
                    next_kill += args.kill_every
                    running = [
                        (job_id, int(horse_pid))
                        for job_id in ids
                        if status[job_id] == "running"
                        and (horse_pid := r.hget(f"neuroanimator:controller:job:{job_id}", "pid"))
                    ]
                    ours = {w.pid: w for w in workers if w.poll() is None}
                    running = [(job_id, horse) for job_id, horse in running if _parent(horse) in ours]
                    if running:
                        job_id, horse = random.choice(running)
                        victim = ours[_parent(horse) or 0]
                        for pid in (victim.pid, horse):
                            with contextlib.suppress(ProcessLookupError):
                                os.kill(pid, signal.SIGKILL)
                        victim.wait(10)
                        kills += 1
                        workers.remove(victim)
                        start_worker()
                time.sleep(0.5)
            took = time.monotonic() - t0
            time.sleep(3 * 3 + 1)  # WORKER_ALIVE_S (3 heartbeats of 3 s): the last killed one drops out
            metrics = api.get("/metrics").text
            ready = api.get("/readyz").json()
            alive = sum(1 for w in workers if w.poll() is None)
            for w in workers:
                w.terminate()
            for w in workers:
                w.wait(60)
        counts = {s: sum(1 for v in status.values() if v == s) for s in FINAL}
        finished = sum(_metric(metrics, f'controller_jobs_finished_total{{status="{s}"}}') for s in FINAL)
        out: dict[str, Any] = {
            "jobs": args.jobs,
            "workers": args.workers,
            **counts,
            "lost": sum(1 for v in status.values() if v not in FINAL),
            "finished_twice": max(0, int(finished) - args.jobs),
            "kills": kills,
            "requeued": int(_metric(metrics, "controller_jobs_requeued_total")),
            "readyz_workers": ready.get("workers"),
            "workers_alive": alive,
            "seconds": round(took, 1),
        }
    if args.json:
        print(json.dumps(out))
    else:
        print(json.dumps(out, indent=2))
    return 0 if out["lost"] == 0 and out["finished_twice"] == 0 and out["failed"] == 0 else 1


def _parent(pid: int) -> int | None:
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None
    return int(stat.rsplit(")", 1)[1].split()[1])


def _metric(text: str, name: str) -> float:
    m = re.search(rf"^{re.escape(name)} (\S+)$", text, re.M)
    return float(m.group(1)) if m else 0.0


if __name__ == "__main__":
    sys.exit(main())
