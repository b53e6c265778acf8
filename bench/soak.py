"""Soak: the whole stack under mixed load for minutes, watching errors, latency and memory.

    python bench/soak.py --minutes 10 --json
    python bench/soak.py --minutes 1 --clients 200      # a short check

It starts its own stack: a private ``redis-server`` (free port, nothing saved), the emulator service
(persistence on, checkpoints every second), the controller API and one controller worker, all on the
committed artifacts. Then, all at once and until the time is up:

- ``--clients`` websocket clients (binary frames) each stepping its session at ``--rate`` Hz
  (``ws_load._client``: send, wait for the state, sleep to the next tick);
- batch requests: a binary ``POST /step`` of ``--batch`` sessions twice a second;
- session churn: a session created, stepped once over REST and deleted, ``--churn`` times a second;
- control jobs: a short controller-synthesis job every ``--job-every`` seconds, followed to its end;
- ``/readyz`` and ``/metrics`` of both services every 5 s.

Finished jobs are kept 60 s (``RESULT_TTL_S``), so that Redis's data reaches a steady size.

Reported: per kind of load, its count, throughput, p50/p99 latency, errors and 5xx; the jobs submitted,
succeeded, failed and not ended; and the resident memory of every process (emulator, controller API,
worker, Redis, this load generator) once the load is on (after ``--warmup`` seconds) and at the end,
with its growth. ``memory_flat`` is every server process within 10% of its start; ``ok`` is that plus
no errors and no 5xx.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Awaitable, Callable, Iterator
from pathlib import Path
from typing import Any

import httpx
import numpy as np
from _server import REPO, free_port, rss_bytes, serve
from ws_load import Stats, _client, control_ring

from services.emulator import binary

QUICK_JOB = {"task": "pendulum-swing", "optimizer": {"max_iterations": 3}}


class Series:
    """Latencies, errors and 5xx of one kind of load."""

    def __init__(self) -> None:
        self.latencies: list[float] = []
        self.errors = 0
        self.server_errors = 0
        self.last_error = ""

    def observe(self, seconds: float, status: int, ok: bool) -> None:
        if ok:
            self.latencies.append(seconds)
            return
        self.errors += 1
        if status >= 500:
            self.server_errors += 1

    def summary(self, elapsed: float) -> dict[str, Any]:
        lat = np.asarray(self.latencies) * 1000.0
        return {
            "count": int(lat.size),
            "per_s": round(lat.size / elapsed, 1),
            "p50_ms": round(float(np.percentile(lat, 50)), 2) if lat.size else None,
            "p99_ms": round(float(np.percentile(lat, 99)), 2) if lat.size else None,
            "errors": self.errors,
            "5xx": self.server_errors,
            **({"last_error": self.last_error} if self.last_error else {}),
        }


@contextlib.contextmanager
def private_redis(folder: Path) -> Iterator[tuple[str, int]]:
    """(URL, pid) of a ``redis-server`` of this run on a free port; nothing saved to disk."""
    if shutil.which("redis-server") is None:
        raise SystemExit("redis-server is not installed")
    port = free_port()
    proc = subprocess.Popen(
        ["redis-server", "--port", str(port), "--bind", "127.0.0.1", "--dir", str(folder), "--save", ""],
        stdout=subprocess.DEVNULL,
    )
    try:
        yield f"redis://127.0.0.1:{port}/0", proc.pid
    finally:
        proc.terminate()
        proc.wait(10)


async def _every(period: float, stop: asyncio.Event, action: Callable[[], Awaitable[None]]) -> None:
    """Run ``action`` every ``period`` seconds (not overlapping) until ``stop``."""
    loop = asyncio.get_running_loop()
    nxt = loop.time()
    while not stop.is_set():
        nxt += period
        with contextlib.suppress(asyncio.CancelledError):
            await action()
        delay = nxt - loop.time()
        if delay > 0:
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(stop.wait(), delay)
        else:
            nxt = loop.time()


async def _timed(
    series: Series, request: Awaitable[httpx.Response], ok_status: int = 200
) -> httpx.Response | None:
    t0 = time.perf_counter()
    try:
        r = await request
    except httpx.HTTPError as exc:
        series.observe(0.0, 0, False)
        series.last_error = f"{type(exc).__name__}: {exc}"
        return None
    ok = r.status_code == ok_status
    series.observe(time.perf_counter() - t0, r.status_code, ok)
    if not ok:
        series.last_error = f"{r.status_code}: {r.text[:200]}"
    return r


def _memory(pids: dict[str, int]) -> dict[str, float]:
    out = {}
    for name, pid in pids.items():
        with contextlib.suppress(OSError, RuntimeError):
            out[name] = round(rss_bytes(pid) / 2**20, 1)
    return out


async def soak(
    emulator: str,
    controller: str,
    pids: dict[str, int],
    minutes: float,
    clients: int,
    rate: float,
    batch: int,
    churn: float,
    job_every: float,
    warmup: float,
) -> dict[str, Any]:
    timeout = httpx.Timeout(30.0)
    # idle connections dropped after 4 s, before uvicorn's 5 s keep-alive timeout closes them: a request
    # sent on a connection the server is closing at that moment fails (ReadError) through no fault of it
    limits = httpx.Limits(max_connections=32, keepalive_expiry=4.0)
    async with (
        httpx.AsyncClient(base_url=emulator, timeout=timeout, limits=limits) as emu,
        httpx.AsyncClient(base_url=controller, timeout=timeout, limits=limits) as ctl,
    ):
        detail = (await emu.get("/models/pendulum-active")).json()
        lo = np.array([c["low"] for c in detail["controls"]])
        hi = np.array([c["high"] for c in detail["controls"]])
        sem = asyncio.Semaphore(32)

        async def create(i: int) -> str:
            async with sem:
                r = await emu.post("/sessions", json={"model": "pendulum-active", "seed": i})
                r.raise_for_status()
                sid: str = r.json()["id"]
                return sid

        ws_sids = await asyncio.gather(*(create(i) for i in range(clients)))
        batch_sids = await asyncio.gather(*(create(clients + i) for i in range(batch)))

        ws_stats, ready, stop = Stats(), asyncio.Event(), asyncio.Event()
        connected = [0]
        base = emulator.replace("http://", "ws://", 1) + "/ws/sessions/"
        tasks = []
        for i, sid in enumerate(ws_sids):
            ring = control_ring(lo, hi, i, True)
            coro = _client(
                f"{base}{sid}?format=binary",
                ring,
                rate,
                i / max(1, clients),
                ws_stats,
                ready,
                stop,
                connected,
            )
            tasks.append(asyncio.create_task(coro))
            if i % 50 == 49:
                await asyncio.sleep(0.01)
        deadline = time.monotonic() + 120
        while connected[0] < clients and time.monotonic() < deadline:
            await asyncio.sleep(0.05)
        ready.set()

        series = {name: Series() for name in ("batch", "churn", "ops")}
        jobs = {"submitted": 0, "succeeded": 0, "failed": 0, "cancelled": 0}
        pending: set[str] = set()
        rows = np.random.default_rng(0).uniform(lo, hi, size=(batch, len(lo)))
        body = binary.encode_batch_request(list(batch_sids), rows)
        diverged = [0]

        async def step_batch() -> None:
            r = await _timed(
                series["batch"],
                emu.post("/step", content=body, headers={"content-type": "application/octet-stream"}),
            )
            if r is not None and r.status_code == 200:
                status, _ = binary.decode_batch_response(r.content)
                diverged[0] += int((status == binary.DIVERGED).sum())  # a model's answer, not an error
                if (status == binary.UNKNOWN).any():  # a session lost
                    series["batch"].errors += 1
                    series["batch"].last_error = f"{int((status == binary.UNKNOWN).sum())} sessions unknown"

        async def churn_one() -> None:
            t0 = time.perf_counter()
            try:
                r = await emu.post("/sessions", json={"model": "pendulum-active"})
                ok = r.status_code == 201
                if ok:
                    sid = r.json()["id"]
                    r = await emu.post(f"/sessions/{sid}/step", json={"controls": lo.tolist()})
                    ok = r.status_code == 200
                    d = await emu.delete(f"/sessions/{sid}")
                    ok = ok and d.status_code == 204
                series["churn"].observe(time.perf_counter() - t0, r.status_code, ok)
                if not ok:
                    series["churn"].last_error = f"{r.status_code}: {r.text[:200]}"
            except httpx.HTTPError as exc:
                series["churn"].observe(0.0, 0, False)
                series["churn"].last_error = f"{type(exc).__name__}: {exc}"

        async def submit_job() -> None:
            r = await _timed(series["ops"], ctl.post("/jobs", json=QUICK_JOB), ok_status=202)
            if r is not None and r.status_code == 202:
                jobs["submitted"] += 1
                pending.add(r.json()["id"])

        async def follow_jobs() -> None:
            for job_id in list(pending):
                r = await _timed(series["ops"], ctl.get(f"/jobs/{job_id}"))
                if r is not None and r.status_code == 200 and r.json()["status"] in jobs:
                    jobs[r.json()["status"]] += 1
                    pending.discard(job_id)

        async def ops() -> None:
            for client in (emu, ctl):
                await _timed(series["ops"], client.get("/readyz"))
                await _timed(series["ops"], client.get("/metrics"))

        loops = [
            asyncio.create_task(_every(0.5, stop, step_batch)),
            asyncio.create_task(_every(1.0 / churn, stop, churn_one)),
            asyncio.create_task(_every(job_every, stop, submit_job)),
            asyncio.create_task(_every(2.0, stop, follow_jobs)),
            asyncio.create_task(_every(5.0, stop, ops)),
        ]
        await asyncio.sleep(warmup)
        ws_stats.counting = True
        for s in series.values():  # the warm-up is not counted
            s.__init__()  # type: ignore[misc]
        mem_start = _memory(pids)
        t0 = time.perf_counter()
        await asyncio.sleep(minutes * 60.0)
        elapsed = time.perf_counter() - t0
        ws_stats.counting = False
        mem_end = _memory(pids)
        stop.set()
        await asyncio.wait([*tasks, *loops], timeout=60)
        # the jobs still running get a last chance to end
        end_by = time.monotonic() + 120
        while pending and time.monotonic() < end_by:
            await follow_jobs()
            await asyncio.sleep(1.0)

    lat = np.asarray(ws_stats.latencies) * 1000.0
    memory = {
        name: {
            "start_mb": mem_start[name],
            "end_mb": mem_end.get(name),
            "growth_pct": round(100.0 * (mem_end[name] - mem_start[name]) / mem_start[name], 1)
            if name in mem_end
            else None,
        }
        for name in mem_start
    }
    servers = [m for name, m in memory.items() if name != "load_generator"]
    flat = all(m["growth_pct"] is not None and m["growth_pct"] <= 10.0 for m in servers)
    out: dict[str, Any] = {
        "minutes": minutes,
        "seconds_counted": round(elapsed, 1),
        "websocket": {
            "clients": clients,
            "connected": connected[0],
            "rate_hz": rate,
            "steps": int(lat.size),
            "steps_per_s": round(lat.size / elapsed, 1),
            "p50_ms": round(float(np.percentile(lat, 50)), 2) if lat.size else None,
            "p99_ms": round(float(np.percentile(lat, 99)), 2) if lat.size else None,
            "errors": ws_stats.errors,
        },
        **{name: s.summary(elapsed) for name, s in series.items()},
        "batch_rows_diverged": diverged[0],
        "jobs": {**jobs, "not_ended": len(pending)},
        "memory": memory,
        "memory_flat": flat,
    }
    errors = ws_stats.errors + sum(s.errors for s in series.values()) + jobs["failed"] + len(pending)
    out["errors"] = errors
    out["5xx"] = sum(s.server_errors for s in series.values())
    out["ok"] = flat and errors == 0 and out["5xx"] == 0
    return out


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--minutes", type=float, default=10.0)
    p.add_argument("--clients", type=int, default=1000, help="websocket clients")
    p.add_argument("--rate", type=float, default=10.0, help="steps per second of each websocket client")
    p.add_argument("--batch", type=int, default=256, help="sessions in each batch POST /step")
    p.add_argument(
        "--churn", type=float, default=5.0, help="sessions created, stepped and deleted per second"
    )
    p.add_argument("--job-every", type=float, default=15.0, help="seconds between control jobs")
    p.add_argument("--warmup", type=float, default=20.0, help="seconds of load before counting")
    p.add_argument("--artifacts", default=str(REPO / "artifacts"))
    p.add_argument("--json", action="store_true", help="print one JSON object")
    args = p.parse_args()
    if not 0 < args.minutes <= 120 or not 0 <= args.clients <= 5000 or args.churn <= 0:
        p.error("--minutes in (0, 120], --clients in [0, 5000], --churn > 0")
    with tempfile.TemporaryDirectory() as tmp, private_redis(Path(tmp)) as (redis_url, redis_pid):
        # finished jobs kept a minute, not a day: Redis then holds a steady amount of data (what is kept
        # for a day grows by design, and would hide a leak or pass for one)
        env = {"REDIS_URL": redis_url, "LOG_LEVEL": "warning", "RESULT_TTL_S": "60"}
        with (
            serve(args.artifacts, "services.emulator", **env, CHECKPOINT_INTERVAL_S="1.0") as (
                emu_url,
                emu_pid,
            ),
            serve(args.artifacts, "services.controller", ready="/healthz", **env) as (ctl_url, ctl_pid),
        ):
            worker = subprocess.Popen(
                [sys.executable, "-m", "services.controller.worker"],
                env={**os.environ, **env, "ARTIFACTS_DIR": args.artifacts, "PYTHONPATH": str(REPO)},
                cwd=tmp,  # MuJoCo's warning log, if any, stays out of the repository
            )
            try:
                pids = {
                    "emulator": emu_pid,
                    "controller_api": ctl_pid,
                    "worker": worker.pid,
                    "redis": redis_pid,
                    "load_generator": os.getpid(),
                }
                out = asyncio.run(
                    soak(
                        emu_url,
                        ctl_url,
                        pids,
                        args.minutes,
                        args.clients,
                        args.rate,
                        args.batch,
                        args.churn,
                        args.job_every,
                        args.warmup,
                    )
                )
            finally:
                worker.terminate()
                worker.wait(60)
    out["load_avg_1m_at_end"] = round(os.getloadavg()[0], 2)
    if args.json:
        print(json.dumps(out))
    else:
        print(json.dumps(out, indent=2))
    return 0 if out["ok"] else 1


if __name__ == "__main__":
    sys.exit(main())
