"""Controller service throughput: jobs per minute through the real API, Redis and worker processes.

    python bench/control_throughput.py [--jobs 12] [--workers 1,2] [--tasks pendulum-swing,truck-parking]
                                       [--max-iterations N] [--threads 1] [--json]

For each worker count W: start W workers (``python -m services.controller.worker``), submit ``--jobs``
jobs (the tasks in turn, each with its own defaults unless ``--max-iterations``) to the API
(``python -m services.controller``, started here on a free port), and wait until all have ended.
``jobs_per_min`` = jobs / (time from the first submission to the last end) × 60. ``run_s`` is the
mean run time of a job in its worker (fork, PyTorch import, emulator load, optimisation, MuJoCo
replay); ``turnaround_s`` the mean time from submission to end.

Redis: ``REDIS_URL``, else 127.0.0.1:6379, else a ``redis-server`` started for the run
(``scripts/redis.sh``). Every run uses its own key prefix and queue. With ``--json`` the last line
is one JSON object: one row per worker count, and the speed-up of the last over the first.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import signal
import subprocess
import sys
import tempfile
import time
import uuid
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
from _server import REPO, serve

from services.stack import RedisUnavailable, find_redis

MAX_JOBS = 200
MAX_WORKERS = 16


@contextlib.contextmanager
def redis_url() -> Iterator[str]:
    """A Redis URL for the run (one started here is stopped afterwards)."""
    pidfile = Path(f"/tmp/control-bench-redis-{os.getpid()}.pid")
    try:
        url, started = find_redis(pidfile, timeout=30)
    except RedisUnavailable as e:
        raise SystemExit(f"no Redis: {e}") from e
    try:
        yield url
    finally:
        if started is not None:
            with contextlib.suppress(ProcessLookupError):
                os.kill(started, signal.SIGTERM)
        pidfile.unlink(missing_ok=True)


def _stop(procs: list[subprocess.Popen[bytes]]) -> None:
    for p in procs:
        if p.poll() is None:
            p.send_signal(signal.SIGTERM)
    for p in procs:
        try:
            p.wait(30)
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait()


def run(url: str, env: dict[str, str], workers: int, bodies: list[dict[str, Any]]) -> dict[str, Any]:
    """Start the workers, submit the jobs, wait for all to end; the row of the table."""
    procs = [
        subprocess.Popen(
            [
                sys.executable,
                "-m",
                "services.controller.worker",
                "--name",
                f"{env['QUEUE_NAME']}-w{workers}-{i}",
            ],
            env=env,
            cwd=tempfile.gettempdir(),  # MuJoCo writes MUJOCO_LOG.TXT into the working directory on warnings
        )
        for i in range(workers)
    ]
    try:
        with httpx.Client(base_url=url, timeout=30) as c:
            # wait until every worker listens, so that start-up is not part of the measurement
            deadline = time.monotonic() + 60
            while c.get("/readyz").json().get("workers", 0) < workers:
                if time.monotonic() > deadline:
                    raise RuntimeError(f"{workers} workers did not come up in 60 s")
                time.sleep(0.1)
            t0 = time.monotonic()
            ids = [c.post("/jobs", json=b).raise_for_status().json()["id"] for b in bodies]
            pending, done = set(ids), {}
            while pending:
                time.sleep(0.2)
                for job_id in list(pending):
                    j = c.get(f"/jobs/{job_id}").json()
                    if j["status"] in ("succeeded", "failed", "cancelled"):
                        done[job_id] = j
                        pending.discard(job_id)
            wall = time.monotonic() - t0
    finally:
        _stop(procs)
    jobs = list(done.values())
    return {
        "workers": workers,
        "jobs": len(jobs),
        "succeeded": sum(j["status"] == "succeeded" for j in jobs),
        "wall_s": round(wall, 2),
        "jobs_per_min": round(len(jobs) / wall * 60.0, 2),
        "run_s": round(sum(j["ended_at"] - j["started_at"] for j in jobs) / len(jobs), 3),
        "turnaround_s": round(sum(j["ended_at"] - j["created_at"] for j in jobs) / len(jobs), 3),
        "iterations": round(sum(j["iteration"] for j in jobs) / len(jobs), 1),
    }


def cleanup(url: str, prefix: str, queue: str) -> None:
    """Remove this run's keys: its prefix, its queue's RQ registries and its jobs' RQ records."""
    import redis

    r = redis.Redis.from_url(url)
    keys = list(r.scan_iter(match=f"{prefix}:*"))
    for job_id in {k.decode().rsplit(":", 1)[1] for k in keys if b":job:" in k}:
        keys += list(r.scan_iter(match=f"rq:*{job_id}-*"))
    keys += list(r.scan_iter(match=f"rq:*{queue}"))
    if keys:
        r.delete(*keys)
    r.close()


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--jobs", type=int, default=12)
    p.add_argument("--workers", default="1,2", help="comma-separated worker counts")
    p.add_argument("--tasks", default="pendulum-swing,truck-parking")
    p.add_argument("--max-iterations", type=int, help="cap every job's iterations (default: the task's)")
    p.add_argument("--threads", type=int, default=1, help="torch threads per job")
    p.add_argument("--artifacts", default=str(REPO / "artifacts"))
    p.add_argument("--json", action="store_true")
    args = p.parse_args()
    counts = [int(w) for w in args.workers.split(",")]
    if not 1 <= args.jobs <= MAX_JOBS or not all(1 <= w <= MAX_WORKERS for w in counts):
        p.error(f"--jobs must be in [1, {MAX_JOBS}] and each worker count in [1, {MAX_WORKERS}]")
    tasks = args.tasks.split(",")
    bodies: list[dict[str, Any]] = []
    for i in range(args.jobs):
        body: dict[str, Any] = {"task": tasks[i % len(tasks)]}
        if args.max_iterations:
            body["optimizer"] = {"max_iterations": args.max_iterations}
        bodies.append(body)

    rows = []
    with redis_url() as redis:
        tag = uuid.uuid4().hex[:8]
        settings = {  # the API's and the workers' (the rest of their environment is this process's)
            "REDIS_URL": redis,
            "REDIS_PREFIX": f"bench-controller:{tag}",
            "QUEUE_NAME": f"bench-controller-{tag}",
            "ARTIFACTS_DIR": str(Path(args.artifacts).resolve()),
            "API_KEYS": "",
            "MAX_QUEUE": str(MAX_JOBS),
            "RESULT_TTL_S": "600",
            "WORKER_THREADS": str(args.threads),
            "LOG_LEVEL": "warning",
        }
        env = {**os.environ, **settings}
        try:
            with serve(settings["ARTIFACTS_DIR"], "services.controller", ready="/healthz", **settings) as (
                url,
                _pid,
            ):
                for w in counts:
                    rows.append(run(url, env, w, bodies))
        finally:
            cleanup(redis, env["REDIS_PREFIX"], env["QUEUE_NAME"])
    cols = ["workers", "jobs", "succeeded", "wall_s", "jobs_per_min", "run_s", "turnaround_s", "iterations"]
    widths = [max(len(c), *(len(str(r[c])) for r in rows)) for c in cols]
    print(
        f"controller throughput: {args.jobs} jobs ({', '.join(tasks)}), {args.threads} torch thread(s) per job"
    )
    print("  ".join(c.rjust(w) for c, w in zip(cols, widths, strict=True)))
    print("  ".join("-" * w for w in widths))
    for r in rows:
        print("  ".join(str(r[c]).rjust(w) for c, w in zip(cols, widths, strict=True)))
    result = {
        "jobs": args.jobs,
        "tasks": tasks,
        "threads": args.threads,
        "cpus": os.cpu_count(),
        "rows": rows,
        "speedup": round(rows[-1]["jobs_per_min"] / rows[0]["jobs_per_min"], 2),
    }
    if args.json:
        print(json.dumps(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
