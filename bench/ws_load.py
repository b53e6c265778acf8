"""Websocket load: N concurrent clients stepping their sessions in lock-step, mixed models.

    python bench/ws_load.py --clients 1000 [--duration 10] [--batching on|off] [--binary] [--json]
    python bench/ws_load.py --clients 1000 --rate 10 --binary     # each client ticks at 10 Hz
    python bench/ws_load.py --clients 1000 --replicas 2 --binary  # two emulator processes, one per core
    python bench/ws_load.py --url http://127.0.0.1:8000 --clients 200

Without ``--url`` it starts the service itself (uvicorn subprocess on 127.0.0.1, a free port,
``ARTIFACTS_DIR=--artifacts``; ``--batching off`` sets ``MAX_BATCH=1`` there; ``--replicas N`` starts
N of them, REPLICA_ID r1..rN, and each client talks to the replica that owns its session, as behind
the compose file's proxy). Sessions are spread
round-robin over the models with controls that ``GET /models`` lists (``--models`` to choose). Each
client sends a step, waits for its state, and sends the next; with ``--rate R`` it steps at most R
times a second instead (a game client ticking at R Hz: send, wait for the state, sleep until its next
tick; a tick missed while waiting is skipped, never made up; the clients' ticks are spread evenly over
the period). Latency is measured per step on the client. Counting starts once every client is
connected and lasts ``--duration`` seconds (both bounded). With ``--json`` the last line is one JSON
object: clients, steps_per_s, p50_ms, p99_ms, errors (and more: mode, rate_hz, target_steps_per_s,
client_cpu_pct, server_cpu_pct, loop).

The clients are lean so that the benchmark measures the server, not itself: ``_wsclient.WsClient``
(a minimal websocket client on a raw asyncio protocol) on uvloop where it is installed (``--loop``),
and each client's controls are drawn once, as a ring of 64 pre-encoded vectors (float32 bytes for
binary frames, JSON text for JSON frames) that it cycles through with its ``seq`` put in front. The
load generator's CPU share over the counted window is reported (``client_cpu_pct``; with its own
server, ``server_cpu_pct`` too) so that a run whose clients starve the server shows it.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import os
import struct
import time
from collections.abc import Callable, Coroutine
from typing import Any

import httpx
import numpy as np
from _server import serve
from _wsclient import WsClient

from services.emulator import binary

MAX_CLIENTS = 5000
MAX_REPLICAS = 8
MAX_DURATION_S = 300.0
MAX_RATE_HZ = 1000.0
RING = 64  # pre-encoded control vectors per client
_PREFIX = struct.Struct("<4sI")  # magic and seq: the start of both the client and the state frame
_CLOCK_TICKS = os.sysconf("SC_CLK_TCK")


class Stats:
    def __init__(self) -> None:
        self.latencies: list[float] = []
        self.errors = 0
        self.counting = False


def control_ring(lo: np.ndarray, hi: np.ndarray, seed: int, use_binary: bool) -> list[bytes] | list[str]:
    """``RING`` control vectors drawn uniformly in ``lo``..``hi``: float32 bytes, or JSON arrays."""
    u = np.random.default_rng(seed).uniform(lo, hi, size=(RING, len(lo))).astype("<f4")
    if use_binary:
        return [row.tobytes() for row in u]
    return [json.dumps(row.tolist()) for row in u]


async def _client(
    ws_url: str,
    ring: list[bytes] | list[str],
    rate: float,
    phase: float,
    stats: Stats,
    ready: asyncio.Event,
    stop: asyncio.Event,
    connected: list[int],
) -> None:
    ws: WsClient | None = None
    counted = False
    try:
        ws = await WsClient.connect(ws_url, timeout=60)
        if isinstance(ring[0], bytes):
            json.loads(await ws.recv())  # "started"
        connected[0] += 1
        counted = True
        await ready.wait()
        loop = asyncio.get_running_loop()
        period = 1.0 / rate if rate > 0 else 0.0
        nxt = loop.time() + phase * period
        perf = time.perf_counter
        latencies = stats.latencies
        k = 0
        while not stop.is_set():
            if period:
                delay = nxt - loop.time()
                if delay > 0:
                    await asyncio.sleep(delay)
                nxt += period
                late = loop.time() - nxt
                if late > 0:  # ticks missed while waiting for a state are skipped, not made up
                    nxt += (late // period + 1) * period
            tail = ring[k & (RING - 1)]
            t0 = perf()
            if isinstance(tail, bytes):
                ws.send_binary(_PREFIX.pack(binary.WS_CLIENT_MAGIC, k) + tail)
                reply = await ws.recv()
                ok = (
                    isinstance(reply, bytes)
                    and len(reply) >= binary.WS_STATE_HEADER.size
                    and _PREFIX.unpack_from(reply) == (binary.WS_STATE_MAGIC, k)
                )
            else:
                ws.send_text(f'{{"type":"step","controls":{tail},"seq":{k}}}')
                msg = json.loads(await ws.recv())
                ok = msg.get("type") == "state" and msg.get("seq") == k
            dt = perf() - t0
            if stats.counting:
                if ok:
                    latencies.append(dt)
                else:
                    stats.errors += 1
            k += 1
    except Exception:  # a failed connection or send is an error of the run, not of the tool
        stats.errors += 1
        if not counted:
            connected[0] += 1
    finally:
        if ws is not None:
            await ws.close(timeout=10)


def _cpu_s(pid: int) -> float:
    """User + system CPU seconds of a process so far, from /proc/<pid>/stat."""
    with open(f"/proc/{pid}/stat") as f:
        fields = f.read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / _CLOCK_TICKS


async def run(
    urls: list[str],
    clients: int,
    duration: float,
    models: list[str] | None,
    use_binary: bool,
    rate: float = 0.0,
    server_pids: list[int] | None = None,
) -> dict[str, Any]:
    """Client i's session lives on replica ``urls[i % len(urls)]``, which it then talks to directly
    (what the proxy's session affinity does in a deployment)."""
    url = urls[0]
    async with httpx.AsyncClient(base_url=url, timeout=60, limits=httpx.Limits(max_connections=64)) as http:
        listed = (await http.get("/models")).json()["models"]
        names = [m["model"] for m in listed if m["num_controls"] > 0 and m["num_forces"] == 0]
        if models:
            names = [m for m in models if m in names] or names
        ranges = {}
        for name in names:
            d = (await http.get(f"/models/{name}")).json()
            ranges[name] = (
                np.array([c["low"] for c in d["controls"]]),
                np.array([c["high"] for c in d["controls"]]),
            )
        sem = asyncio.Semaphore(64)

        async def create(i: int) -> str:
            async with sem:
                owner = urls[i % len(urls)]
                r = await http.post(f"{owner}/sessions", json={"model": names[i % len(names)], "seed": i})
                r.raise_for_status()
                sid: str = r.json()["id"]
                return sid

        sids = await asyncio.gather(*(create(i) for i in range(clients)))
    stats = Stats()
    ready, stop = asyncio.Event(), asyncio.Event()
    connected = [0]
    tasks = []
    bases = [u.replace("http://", "ws://", 1) + "/ws/sessions/" for u in urls]
    query = "?format=binary" if use_binary else ""
    for i, sid in enumerate(sids):
        lo, hi = ranges[names[i % len(names)]]
        ring = control_ring(lo, hi, i, use_binary)
        coro = _client(
            bases[i % len(urls)] + sid + query, ring, rate, i / clients, stats, ready, stop, connected
        )
        tasks.append(asyncio.create_task(coro))
        if i % 50 == 49:
            await asyncio.sleep(0.01)  # connect gradually
    deadline = time.monotonic() + 120
    while connected[0] < clients and time.monotonic() < deadline:
        await asyncio.sleep(0.05)
    ready.set()
    await asyncio.sleep(min(1.0, duration / 5) + (1.0 / rate if rate > 0 else 0.0))  # warm-up
    stats.counting = True
    t0, cpu0 = time.perf_counter(), time.process_time()
    pids = server_pids or []
    srv0 = sum(_cpu_s(p) for p in pids)
    await asyncio.sleep(duration)
    stats.counting = False
    elapsed = time.perf_counter() - t0
    client_cpu = time.process_time() - cpu0
    server_cpu = sum(_cpu_s(p) for p in pids) - srv0 if pids else None
    stop.set()
    await asyncio.wait(tasks, timeout=30)
    lat = np.asarray(stats.latencies) * 1000.0
    steps_per_s = len(lat) / elapsed
    return {
        "clients": clients,
        "connected": connected[0],
        "models": names,
        "duration_s": round(elapsed, 3),
        "steps": len(lat),
        "steps_per_s": round(steps_per_s, 1),
        "p50_ms": round(float(np.percentile(lat, 50)), 3) if lat.size else None,
        "p99_ms": round(float(np.percentile(lat, 99)), 3) if lat.size else None,
        "errors": stats.errors,
        "frames": "binary" if use_binary else "json",
        "mode": f"lock-step at {rate:g} Hz per client" if rate > 0 else "lock-step, as fast as possible",
        "rate_hz": rate,
        "target_steps_per_s": round(clients * rate, 1) if rate > 0 else None,
        "replicas": len(urls),
        "client_cpu_pct": round(100.0 * client_cpu / elapsed, 1),
        "server_cpu_pct": round(100.0 * server_cpu / elapsed, 1) if server_cpu is not None else None,
    }


def _runner(loop: str) -> tuple[str, Callable[[Coroutine[Any, Any, dict[str, Any]]], dict[str, Any]]]:
    """(the event loop's name, a function running a coroutine on it): uvloop when asked or installed."""
    if loop != "asyncio":
        try:
            import uvloop
        except ImportError:
            if loop == "uvloop":
                raise
        else:

            def on_uvloop(coro: Coroutine[Any, Any, dict[str, Any]]) -> dict[str, Any]:
                with asyncio.Runner(loop_factory=uvloop.new_event_loop) as runner:
                    return runner.run(coro)

            return "uvloop", on_uvloop
    return "asyncio", asyncio.run


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--clients", type=int, default=1000)
    p.add_argument("--duration", type=float, default=10.0, help="seconds counted (after all connected)")
    p.add_argument(
        "--rate", type=float, default=0.0, help="steps per second per client; 0: as fast as possible"
    )
    p.add_argument("--url", help="a running service (comma-separated: replicas); otherwise started here")
    p.add_argument(
        "--replicas",
        type=int,
        default=1,
        help="emulator processes started here (REPLICA_ID r1..rN); each client talks to its session's owner",
    )
    p.add_argument("--artifacts", default="artifacts")
    p.add_argument("--models", help="comma-separated; default: every model with controls and no forces")
    p.add_argument("--batching", choices=["on", "off"], default="on", help="off: MAX_BATCH=1 (own server)")
    p.add_argument("--binary", action="store_true", help="binary frames instead of JSON")
    p.add_argument("--loop", choices=["auto", "uvloop", "asyncio"], default="auto", help="the clients' loop")
    p.add_argument("--json", action="store_true")
    args = p.parse_args()
    if not 1 <= args.clients <= MAX_CLIENTS or not 0 < args.duration <= MAX_DURATION_S:
        p.error(f"--clients must be 1..{MAX_CLIENTS} and --duration in (0, {MAX_DURATION_S}]")
    if not 0 <= args.rate <= MAX_RATE_HZ:
        p.error(f"--rate must be in 0..{MAX_RATE_HZ}")
    models = args.models.split(",") if args.models else None
    loop_name, run_on_loop = _runner(args.loop)
    if not 1 <= args.replicas <= MAX_REPLICAS:
        p.error(f"--replicas must be 1..{MAX_REPLICAS}")
    if args.url:
        urls = args.url.split(",")
        result = run_on_loop(run(urls, args.clients, args.duration, models, args.binary, args.rate))
    else:
        env = {"MAX_BATCH": "1"} if args.batching == "off" else {}
        with contextlib.ExitStack() as stack:
            servers = [
                stack.enter_context(serve(args.artifacts, **env, REPLICA_ID=f"r{k + 1}"))
                for k in range(args.replicas)
            ]
            urls, pids = [u for u, _ in servers], [pid for _, pid in servers]
            result = run_on_loop(run(urls, args.clients, args.duration, models, args.binary, args.rate, pids))
    result["batching"] = args.batching if not args.url else "server's"
    result["loop"] = loop_name
    server_cpu = "" if result["server_cpu_pct"] is None else f" / {result['server_cpu_pct']:.0f}"
    target = result["target_steps_per_s"]
    print(f"mode: {result['mode']}" + (f" (target {target:,.0f} steps/s)" if target else ""))
    print(
        "| clients | replicas | models | frames | batching | mode | steps/s | p50 ms | p99 ms | errors "
        "| CPU % client / server |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    print(
        f"| {result['clients']} | {result['replicas']} | {', '.join(result['models'])} | {result['frames']} "
        f"| {result['batching']} "
        f"| {result['mode']} | {result['steps_per_s']:,.0f} | {result['p50_ms']} | {result['p99_ms']} "
        f"| {result['errors']} | {result['client_cpu_pct']:.0f}{server_cpu} |"
    )
    if args.json:
        print(json.dumps(result))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
