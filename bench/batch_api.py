"""Batch API: one client stepping N sessions per binary ``POST /step`` request, against MuJoCo.

    python bench/batch_api.py --sessions 4096 [--duration 5] [--compare-off] [--idle-sessions 10000] [--json]
    python bench/batch_api.py --url http://127.0.0.1:8000 --sessions 1024

Rows of the table:
* ``binary batch``: N ``--model`` sessions (default pendulum-active) stepped by one client, one binary
  request (proto/frames.md) after another, for ``--duration`` s: session_steps_per_s. The client is
  the lean keep-alive one of ``bench/_httpclient.py`` (why: see there); the same load through
  ``httpx`` follows for up to 3 s (httpx_session_steps_per_s).
* ``mujoco.rollout``: the same N start states stepped by the MuJoCo model of the same artifact
  (``load_physical_model(...).simulate`` with held controls, ``--rollout-threads`` threads, in this
  process, on the same cores) over the same simulated time (capped at ``--rollout-max-s`` of wall
  time; the simulated time covered is reported): rollout_session_steps_per_s (super-steps of Δt) and
  ``ratio`` = session_steps_per_s / rollout_session_steps_per_s.
* ``--compare-off``: server-side batching on vs off: the sessions stepped by one-session binary
  requests, ``--concurrency`` in flight, against a server with default batching and one with
  ``MAX_BATCH=1`` (``bench/ws_load.py --batching on|off`` is the same comparison over websockets).
* ``--idle-sessions K``: the server's resident memory (VmRSS) before and after creating K idle
  sessions, reported per 10,000 (only for a server this script started).

Without ``--url`` the service is started here (uvicorn subprocess on 127.0.0.1, a free port,
``ARTIFACTS_DIR=--artifacts``). With ``--json`` the last line is one JSON object: sessions,
session_steps_per_s, rollout_session_steps_per_s, ratio (and more).
"""

from __future__ import annotations

import argparse
import asyncio
import json
import threading
import time
from pathlib import Path
from typing import Any

import _httpclient
import httpx
import numpy as np
from _server import rss_bytes, serve

from services.emulator import binary

MAX_SESSIONS = 100_000
MAX_DURATION_S = 120.0
OCTET = {"content-type": "application/octet-stream"}


async def create_sessions(
    url: str, model: str, n: int, concurrency: int = 64
) -> tuple[list[str], np.ndarray]:
    """Ids and (n, S) start states of n new sessions (seeds 0..n-1)."""
    async with httpx.AsyncClient(
        base_url=url, timeout=60, limits=httpx.Limits(max_connections=concurrency)
    ) as c:
        sem = asyncio.Semaphore(concurrency)

        async def one(i: int) -> dict[str, Any]:
            async with sem:
                r = await c.post("/sessions", json={"model": model, "seed": i})
                r.raise_for_status()
                out: dict[str, Any] = r.json()
                return out

        infos = await asyncio.gather(*(one(i) for i in range(n)))
    return [s["id"] for s in infos], np.asarray([s["state"] for s in infos], np.float64)


def step_batched(
    url: str, ids: list[str], u: np.ndarray, duration: float, client: str = "lean"
) -> dict[str, Any]:
    """One request after another, each stepping every session once, with the lean HTTP client of
    ``bench/_httpclient.py`` or with ``httpx``."""
    body = binary.encode_batch_request(ids, u)
    with _httpclient.Client(url) if client == "lean" else httpx.Client(base_url=url, timeout=60) as c:
        for _ in range(3):  # warm-up
            c.post("/step", content=body, headers=OCTET).raise_for_status()
        requests, bad, lat = 0, 0, []
        t0 = time.perf_counter()
        while time.perf_counter() - t0 < duration:
            t = time.perf_counter()
            r = c.post("/step", content=body, headers=OCTET)
            lat.append(time.perf_counter() - t)
            r.raise_for_status()
            status, _ = binary.decode_batch_response(r.content)
            bad += int((status > binary.CLIPPED).sum())
            requests += 1
        elapsed = time.perf_counter() - t0
    return {
        "requests": requests,
        "super_steps": requests,
        "session_steps_per_s": round(len(ids) * requests / elapsed, 1),
        "request_p50_ms": round(float(np.percentile(lat, 50)) * 1000, 3),
        "errors": bad,
    }


def step_unbatched(
    url: str, ids: list[str], u: np.ndarray, duration: float, concurrency: int
) -> dict[str, Any]:
    """One-session binary requests, ``concurrency`` in flight (one lean keep-alive client per
    thread: the socket waits release the GIL), round-robin over the sessions."""
    bodies = [binary.encode_batch_request([sid], u[i : i + 1]) for i, sid in enumerate(ids)]
    done = [0] * concurrency
    stop = threading.Event()

    def worker(w: int) -> None:
        with _httpclient.Client(url) as c:
            i = w
            while not stop.is_set():
                c.post("/step", content=bodies[i % len(bodies)], headers=OCTET).raise_for_status()
                done[w] += 1
                i += concurrency

    threads = [threading.Thread(target=worker, args=(w,), daemon=True) for w in range(concurrency)]
    t0 = time.perf_counter()
    for t in threads:
        t.start()
    time.sleep(duration)
    stop.set()
    for t in threads:
        t.join(60)
    elapsed = time.perf_counter() - t0
    return {"session_steps_per_s": round(sum(done) / elapsed, 1), "requests": sum(done)}


def rollout(
    artifacts: Path,
    model: str,
    version: str,
    states: np.ndarray,
    u: np.ndarray,
    super_steps: int,
    threads: int,
    max_s: float,
) -> dict[str, Any]:
    """MuJoCo stepping the same sessions under the same held controls, super-step by super-step."""
    from neuroanimator.artifacts import registry

    path = registry.resolve(artifacts, model, version)
    manifest = registry.read_manifest(path)
    physical = registry.load_physical_model(path, manifest)
    n = manifest.substeps
    x = states.copy()
    controls = u[:, None, :].astype(np.float64)
    physical.simulate(x[:8], controls[:8], nstep=n, threads=threads)  # warm-up
    done = 0
    t0 = time.perf_counter()
    while done < super_steps and (time.perf_counter() - t0 < max_s or done == 0):
        x = physical.simulate(x, controls, nstep=n, threads=threads)[:, -1]
        done += 1
    elapsed = time.perf_counter() - t0
    return {
        "rollout_super_steps": done,
        "rollout_session_steps_per_s": round(len(x) * done / elapsed, 1),
        "physical_steps_per_super_step": n,
    }


def idle_memory(url: str, pid: int, model: str, k: int) -> dict[str, Any]:
    before = rss_bytes(pid)
    asyncio.run(create_sessions(url, model, k))
    time.sleep(0.5)
    after = rss_bytes(pid)
    return {
        "idle_sessions": k,
        "rss_before_mb": round(before / 2**20, 1),
        "rss_after_mb": round(after / 2**20, 1),
        "rss_per_10k_idle_mb": round((after - before) / 2**20 * 10_000 / k, 2),
    }


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--sessions", type=int, default=4096)
    p.add_argument("--duration", type=float, default=5.0, help="seconds of stepping per row")
    p.add_argument("--url", help="a running service; otherwise one is started")
    p.add_argument("--artifacts", default="artifacts")
    p.add_argument("--model", default="pendulum-active")
    p.add_argument("--rollout-threads", type=int, default=2)
    p.add_argument("--rollout-max-s", type=float, default=30.0, help="wall-time cap of the MuJoCo row")
    p.add_argument(
        "--compare-off", action="store_true", help="add a row with MAX_BATCH=1, unbatched requests"
    )
    p.add_argument("--concurrency", type=int, default=32, help="requests in flight for --compare-off")
    p.add_argument("--idle-sessions", type=int, default=0, help="measure RSS per 10,000 idle sessions")
    p.add_argument("--json", action="store_true")
    args = p.parse_args()
    if not 1 <= args.sessions <= MAX_SESSIONS or not 0 < args.duration <= MAX_DURATION_S:
        p.error(f"--sessions must be 1..{MAX_SESSIONS} and --duration in (0, {MAX_DURATION_S}]")
    if not 0 <= args.idle_sessions <= MAX_SESSIONS:
        p.error(f"--idle-sessions must be 0..{MAX_SESSIONS}")
    artifacts = Path(args.artifacts)
    result: dict[str, Any] = {"sessions": args.sessions, "model": args.model}
    env = {"MAX_BATCH": str(max(4096, args.sessions)), "MAX_SESSIONS": str(MAX_SESSIONS + args.sessions)}

    def measure(url: str) -> tuple[list[str], np.ndarray, np.ndarray]:
        detail = httpx.get(f"{url}/models/{args.model}").raise_for_status().json()
        result["version"] = detail["version"]
        result["super_timestep"] = detail["super_timestep"]
        lo = np.array([c["low"] for c in detail["controls"]])
        hi = np.array([c["high"] for c in detail["controls"]])
        ids, states = asyncio.run(create_sessions(url, args.model, args.sessions))
        u = np.random.default_rng(0).uniform(lo, hi, (args.sessions, len(lo))).astype(np.float32)
        result.update(step_batched(url, ids, u, args.duration))
        # the same load with a general-purpose client, whose own CPU time per request shows here
        with_httpx = step_batched(url, ids, u, min(args.duration, 3.0), client="httpx")
        result["httpx_session_steps_per_s"] = with_httpx["session_steps_per_s"]
        result["super_steps"] += with_httpx["super_steps"]
        return ids, states, u

    if args.url:
        _, states, u = measure(args.url)
    else:
        with serve(args.artifacts, **env) as (url, pid):
            _, states, u = measure(url)
            if args.idle_sessions:
                result.update(idle_memory(url, pid, args.model, args.idle_sessions))
    if args.compare_off:  # the same one-session-request load against batching on, then off
        for label, extra in (("on", {}), ("off", {"MAX_BATCH": "1"})):
            with serve(args.artifacts, MAX_SESSIONS=str(args.sessions + 10), **extra) as (url, _pid):
                ids, _ = asyncio.run(create_sessions(url, args.model, args.sessions))
                one = step_unbatched(url, ids, u, args.duration, args.concurrency)
            result[f"single_requests_batching_{label}_session_steps_per_s"] = one["session_steps_per_s"]
    result.update(
        rollout(
            artifacts,
            args.model,
            result["version"],
            states,
            u,
            result["super_steps"],
            args.rollout_threads,
            args.rollout_max_s,
        )
    )
    result["ratio"] = round(result["session_steps_per_s"] / result["rollout_session_steps_per_s"], 2)
    result["simulated_s_emulator"] = round(result["super_steps"] * result["super_timestep"], 3)
    result["simulated_s_rollout"] = round(result["rollout_super_steps"] * result["super_timestep"], 3)

    print("| row | sessions | session-steps/s | simulated s per session |")
    print("|---|---|---|---|")
    print(
        f"| binary batch, batching on | {args.sessions} | {result['session_steps_per_s']:,.0f} | {result['simulated_s_emulator']} |"
    )
    print(
        f"| the same with an httpx client | {args.sessions} | {result['httpx_session_steps_per_s']:,.0f} | – |"
    )
    for label in ("on", "off"):
        key = f"single_requests_batching_{label}_session_steps_per_s"
        if key in result:
            print(
                f"| one-session requests × {args.concurrency} in flight, batching {label} | {args.sessions} "
                f"| {result[key]:,.0f} | – |"
            )
    print(
        f"| mujoco.rollout, {args.rollout_threads} threads | {args.sessions} "
        f"| {result['rollout_session_steps_per_s']:,.0f} | {result['simulated_s_rollout']} |"
    )
    print(f"\nratio (emulator / MuJoCo): {result['ratio']}×")
    if "rss_per_10k_idle_mb" in result:
        print(f"resident memory per 10,000 idle sessions: {result['rss_per_10k_idle_mb']} MiB")
    if args.json:
        print(json.dumps(result))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
