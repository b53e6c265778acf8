"""Websocket load: N concurrent clients stepping their sessions in lock-step, mixed models.

    python bench/ws_load.py --clients 1000 [--duration 10] [--batching on|off] [--binary] [--json]
    python bench/ws_load.py --url http://127.0.0.1:8000 --clients 200

Without ``--url`` it starts the service itself (uvicorn subprocess on 127.0.0.1, a free port,
``ARTIFACTS_DIR=--artifacts``; ``--batching off`` sets ``MAX_BATCH=1`` there). Sessions are spread
round-robin over the models with controls that ``GET /models`` lists (``--models`` to choose). Each
client sends a step, waits for its state, and sends the next (controls drawn uniformly in range);
latency is measured per step on the client. Counting starts once every client is connected and
lasts ``--duration`` seconds (both bounded). With ``--json`` the last line is one JSON object:
clients, steps_per_s, p50_ms, p99_ms, errors (and more).
"""

from __future__ import annotations

import argparse
import asyncio
import json
import time
from typing import Any

import httpx
import numpy as np
from _server import serve
from websockets.asyncio.client import connect

from services.emulator import binary

MAX_CLIENTS = 5000
MAX_DURATION_S = 300.0


class Stats:
    def __init__(self) -> None:
        self.latencies: list[float] = []
        self.errors = 0
        self.counting = False


async def _client(
    url: str,
    sid: str,
    lo: np.ndarray,
    hi: np.ndarray,
    seed: int,
    use_binary: bool,
    stats: Stats,
    ready: asyncio.Event,
    stop: asyncio.Event,
    connected: list[int],
) -> None:
    rng = np.random.default_rng(seed)
    ws_url = (
        url.replace("http://", "ws://") + f"/ws/sessions/{sid}" + ("?format=binary" if use_binary else "")
    )
    try:
        async with connect(ws_url, max_queue=4, open_timeout=60) as ws:
            if use_binary:
                json.loads(await ws.recv())  # "started"
            connected[0] += 1
            await ready.wait()
            k = 0
            while not stop.is_set():
                u = rng.uniform(lo, hi).astype(np.float32)
                t0 = time.perf_counter()
                if use_binary:
                    await ws.send(binary.encode_ws_frame(k, u))
                    reply = await ws.recv()
                    ok = isinstance(reply, bytes) and binary.decode_ws_state(reply)[0] == k
                else:
                    await ws.send(json.dumps({"type": "step", "controls": u.tolist(), "seq": k}))
                    msg = json.loads(await ws.recv())
                    ok = msg.get("type") == "state" and msg.get("seq") == k
                dt = time.perf_counter() - t0
                if stats.counting:
                    if ok:
                        stats.latencies.append(dt)
                    else:
                        stats.errors += 1
                k += 1
    except Exception:  # a failed connection or send is an error of the run, not of the tool
        stats.errors += 1
        connected[0] += 1


async def run(
    url: str, clients: int, duration: float, models: list[str] | None, use_binary: bool
) -> dict[str, Any]:
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
                r = await http.post("/sessions", json={"model": names[i % len(names)], "seed": i})
                r.raise_for_status()
                sid: str = r.json()["id"]
                return sid

        sids = await asyncio.gather(*(create(i) for i in range(clients)))
    stats = Stats()
    ready, stop = asyncio.Event(), asyncio.Event()
    connected = [0]
    tasks = []
    for i, sid in enumerate(sids):
        lo, hi = ranges[names[i % len(names)]]
        tasks.append(
            asyncio.create_task(_client(url, sid, lo, hi, i, use_binary, stats, ready, stop, connected))
        )
        if i % 50 == 49:
            await asyncio.sleep(0.01)  # connect gradually
    deadline = time.monotonic() + 120
    while connected[0] < clients and time.monotonic() < deadline:
        await asyncio.sleep(0.05)
    ready.set()
    await asyncio.sleep(min(1.0, duration / 5))  # warm-up, not counted
    stats.counting = True
    t0 = time.perf_counter()
    await asyncio.sleep(duration)
    stats.counting = False
    elapsed = time.perf_counter() - t0
    stop.set()
    await asyncio.wait(tasks, timeout=30)
    lat = np.asarray(stats.latencies) * 1000.0
    return {
        "clients": clients,
        "connected": connected[0],
        "models": names,
        "duration_s": round(elapsed, 3),
        "steps": len(lat),
        "steps_per_s": round(len(lat) / elapsed, 1),
        "p50_ms": round(float(np.percentile(lat, 50)), 3) if lat.size else None,
        "p99_ms": round(float(np.percentile(lat, 99)), 3) if lat.size else None,
        "errors": stats.errors,
        "frames": "binary" if use_binary else "json",
    }


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--clients", type=int, default=1000)
    p.add_argument("--duration", type=float, default=10.0, help="seconds counted (after all connected)")
    p.add_argument("--url", help="a running service; otherwise one is started")
    p.add_argument("--artifacts", default="artifacts")
    p.add_argument("--models", help="comma-separated; default: every model with controls and no forces")
    p.add_argument("--batching", choices=["on", "off"], default="on", help="off: MAX_BATCH=1 (own server)")
    p.add_argument("--binary", action="store_true", help="binary frames instead of JSON")
    p.add_argument("--json", action="store_true")
    args = p.parse_args()
    if not 1 <= args.clients <= MAX_CLIENTS or not 0 < args.duration <= MAX_DURATION_S:
        p.error(f"--clients must be 1..{MAX_CLIENTS} and --duration in (0, {MAX_DURATION_S}]")
    models = args.models.split(",") if args.models else None
    if args.url:
        result = asyncio.run(run(args.url, args.clients, args.duration, models, args.binary))
    else:
        env = {"MAX_BATCH": "1"} if args.batching == "off" else {}
        with serve(args.artifacts, **env) as (url, _pid):
            result = asyncio.run(run(url, args.clients, args.duration, models, args.binary))
    result["batching"] = args.batching if not args.url else "server's"
    print("| clients | models | frames | batching | steps/s | p50 ms | p99 ms | errors |")
    print("|---|---|---|---|---|---|---|---|")
    print(
        f"| {result['clients']} | {', '.join(result['models'])} | {result['frames']} | {result['batching']} "
        f"| {result['steps_per_s']:,.0f} | {result['p50_ms']} | {result['p99_ms']} | {result['errors']} |"
    )
    if args.json:
        print(json.dumps(result))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
