"""Websocket p99 of sessions driven by a trained policy, at a game's tick rate (and of undriven ones).

    python bench/driven_serving.py --policy lander-landing               # 1,000 clients at 11 Hz, 2 processes
    python bench/driven_serving.py --policy lander-landing --compare-undriven --json
    python bench/driven_serving.py --policy lander-landing --binary --goal-every 2 --data path/to/data

Starts ``--replicas`` emulator processes (``bench/_server.py``: ``ARTIFACTS_DIR=--artifacts``,
``DATA_DIR=--data``, REPLICA_ID r1..rN). The policy's manifest is read here, from the same two
folders (``resolve_policy``, ``read_policy``): its version, the emulator version it was trained
through, and its goal range. Each client creates a session of ``--model`` driven by the policy
(``{"policy": {"name", "version", "goal"}}``, the goal drawn uniformly in ``goal_low``..``goal_high``),
on replica ``i % N`` which it then talks to directly, and ticks at ``--rate`` Hz as ``ws_load.py``'s
clients do: send one lock-step ``step``, wait for its state, sleep until the next tick. Every
``--goal-every`` seconds (the clients' changes spread evenly over that period) its step carries a new
goal drawn in the same range; the other steps carry none (the last goal holds). In JSON frames
(the default) every step is ``{"type": "step", "seq": k[, "goal": [...]]}`` and a reply counts when it
is the state of that ``seq`` echoing the goal last sent; with ``--binary`` the ticks without a new goal
are binary frames (whose control values a driven session ignores) and the replies binary frames.

With ``--compare-undriven`` the same number of clients then step undriven sessions of the same
emulator version on the same processes (``ws_load._client``: random controls in range, the same frames
and rate). Each phase's sessions are deleted after it. Each phase reports steps/s, p50/p99 latency
(ms, measured per step on the client), errors, how many clients got replies in the counted window and
the fewest replies one client got, and CPU shares of the load generator and the servers. Prints a table
and, with ``--json``, one JSON object as the last line.

Meaningful on a quiet machine only (``uptime``: load below 1.5): it refuses to start otherwise unless
``--force``.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import os
import time
from collections.abc import Callable, Coroutine
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import httpx
import numpy as np
from _server import REPO, serve
from _wsclient import WsClient
from ws_load import (
    _PREFIX,
    MAX_CLIENTS,
    MAX_DURATION_S,
    MAX_RATE_HZ,
    MAX_REPLICAS,
    RING,
    Stats,
    _client,
    _cpu_s,
    _runner,
    control_ring,
)

from neuroanimator.artifacts import registry
from neuroanimator.artifacts.policies import PolicyError, read_policy, resolve_policy
from neuroanimator.core.policy_manifest import PolicyManifest
from services.emulator import binary

P99_LIMIT_MS = 50.0  # what a game ticking at 11 Hz (91 ms per tick) tolerates for one step


@dataclass
class Phase:
    """What every client of one phase shares: its events and the count of clients connected."""

    ready: asyncio.Event
    stop: asyncio.Event
    connected: list[int]


Start = Callable[[Stats, Phase], Coroutine[Any, Any, None]]
"""A client of a phase, given its own ``Stats`` and the phase's events."""


def goal_ring(manifest: PolicyManifest, seed: int) -> tuple[list[float], list[str]]:
    """A first goal and ``RING`` more, uniform in the policy's goal range: float32 values (so that the
    service's echo equals what was sent) and the same as pre-encoded JSON arrays."""
    lo, hi = np.asarray(manifest.goal_low), np.asarray(manifest.goal_high)
    g = np.random.default_rng(seed).uniform(lo, hi, size=(RING + 1, len(lo))).astype(np.float32)
    return g[0].tolist(), [json.dumps(row.tolist()) for row in g[1:]]


async def _driven_client(
    ws_url: str,
    first: list[float],
    goals: list[str],
    tail: bytes | None,
    rate: float,
    goal_every: float,
    phase: float,
    stats: Stats,
    run: Phase,
) -> None:
    """One client of a policy-driven session: lock-step ticks at ``rate`` Hz (as ``ws_load._client``),
    starting at goal ``first``, a new one from ``goals`` (JSON arrays) every ``goal_every`` s; with
    ``tail`` (the frame's U+F float32 inputs) the ticks without a new goal are binary frames."""
    ws: WsClient | None = None
    counted = False
    try:
        ws = await WsClient.connect(ws_url, timeout=60)
        if tail is not None:
            json.loads(await ws.recv())  # "started"
        run.connected[0] += 1
        counted = True
        await run.ready.wait()
        loop = asyncio.get_running_loop()
        period = 1.0 / rate if rate > 0 else 0.0
        nxt = loop.time() + phase * period
        next_goal = loop.time() + phase * goal_every
        perf = time.perf_counter
        latencies = stats.latencies
        sent = first  # the goal last sent (JSON frames check its echo)
        k = changes = 0
        while not run.stop.is_set():
            if period:
                delay = nxt - loop.time()
                if delay > 0:
                    await asyncio.sleep(delay)
                nxt += period
                late = loop.time() - nxt
                if late > 0:  # ticks missed while waiting for a state are skipped, not made up
                    nxt += (late // period + 1) * period
            goal = None
            if loop.time() >= next_goal:
                goal = goals[changes & (RING - 1)]
                changes += 1
                while next_goal <= loop.time():  # (changes missed while waiting are not made up)
                    next_goal += goal_every
            t0 = perf()
            if tail is not None and goal is None:
                ws.send_binary(_PREFIX.pack(binary.WS_CLIENT_MAGIC, k) + tail)
            elif goal is None:
                ws.send_text(f'{{"type":"step","seq":{k}}}')
            else:
                ws.send_text(f'{{"type":"step","goal":{goal},"seq":{k}}}')
            reply = await ws.recv()
            dt = perf() - t0
            if goal is not None:
                sent = json.loads(goal)
            if tail is not None:
                ok = (
                    isinstance(reply, bytes)
                    and len(reply) >= binary.WS_STATE_HEADER.size
                    and _PREFIX.unpack_from(reply) == (binary.WS_STATE_MAGIC, k)
                )
            else:
                msg = json.loads(reply)
                ok = msg.get("type") == "state" and msg.get("seq") == k
                ok = ok and msg.get("goal") == sent
            if stats.counting:
                if ok:
                    latencies.append(dt)
                else:
                    stats.errors += 1
            k += 1
    except Exception:  # a failed connection or send is an error of the run, not of the tool
        stats.errors += 1
        if not counted:
            run.connected[0] += 1
    finally:
        if ws is not None:
            await ws.close(timeout=10)


async def _sessions(http: httpx.AsyncClient, urls: list[str], bodies: list[dict[str, Any]]) -> list[str]:
    """Session i created from ``bodies[i]`` on replica ``urls[i % len(urls)]``: their ids."""
    sem = asyncio.Semaphore(64)

    async def create(i: int, body: dict[str, Any]) -> str:
        async with sem:
            r = await http.post(f"{urls[i % len(urls)]}/sessions", json=body)
            if r.status_code != 201:
                raise SystemExit(f"POST /sessions {body} answered {r.status_code}: {r.text}")
            sid: str = r.json()["id"]
            return sid

    return list(await asyncio.gather(*(create(i, b) for i, b in enumerate(bodies))))


async def _delete(http: httpx.AsyncClient, urls: list[str], sids: list[str]) -> None:
    sem = asyncio.Semaphore(64)

    async def delete(i: int, sid: str) -> None:
        async with sem:
            await http.delete(f"{urls[i % len(urls)]}/sessions/{sid}")

    await asyncio.gather(*(delete(i, s) for i, s in enumerate(sids)))


async def measure(clients: list[Start], rate: float, duration: float, pids: list[int]) -> dict[str, Any]:
    """Run every client (each with a ``Stats`` of its own), count ``duration`` s once all are connected
    and warmed up: the phase's numbers."""
    run = Phase(asyncio.Event(), asyncio.Event(), [0])
    stats = [Stats() for _ in clients]
    tasks: list[asyncio.Task[None]] = []
    for i, (make, s) in enumerate(zip(clients, stats, strict=True)):
        tasks.append(asyncio.create_task(make(s, run)))
        if i % 50 == 49:
            await asyncio.sleep(0.01)  # connect gradually
    deadline = time.monotonic() + 120
    while run.connected[0] < len(clients) and time.monotonic() < deadline:
        await asyncio.sleep(0.05)
    run.ready.set()
    await asyncio.sleep(min(1.0, duration / 5) + (1.0 / rate if rate > 0 else 0.0))  # warm-up
    for s in stats:
        s.counting = True
    t0, cpu0 = time.perf_counter(), time.process_time()
    srv0 = sum(_cpu_s(p) for p in pids)
    await asyncio.sleep(duration)
    for s in stats:
        s.counting = False
    elapsed = time.perf_counter() - t0
    client_cpu = time.process_time() - cpu0
    server_cpu = sum(_cpu_s(p) for p in pids) - srv0
    run.stop.set()
    await asyncio.wait(tasks, timeout=30)
    lat = np.concatenate([np.asarray(s.latencies) for s in stats]) * 1000.0
    replies = [len(s.latencies) for s in stats]
    p99 = round(float(np.percentile(lat, 99)), 3) if lat.size else None
    return {
        "clients": len(clients),
        "connected": run.connected[0],
        "duration_s": round(elapsed, 3),
        "steps": int(lat.size),
        "steps_per_s": round(lat.size / elapsed, 1),
        "target_steps_per_s": round(len(clients) * rate, 1) if rate > 0 else None,
        "p50_ms": round(float(np.percentile(lat, 50)), 3) if lat.size else None,
        "p99_ms": p99,
        "p99_within_limit": p99 is not None and p99 <= P99_LIMIT_MS,
        "errors": sum(s.errors for s in stats),
        "clients_replied": sum(n > 0 for n in replies),
        "min_replies": min(replies),
        "client_cpu_pct": round(100.0 * client_cpu / elapsed, 1),
        "server_cpu_pct": round(100.0 * server_cpu / elapsed, 1),
    }


@dataclass
class Plan:
    """One run's settings (the command line, checked)."""

    model: str
    manifest: PolicyManifest
    clients: int
    rate: float
    duration: float
    goal_every: float
    use_binary: bool
    compare_undriven: bool


async def run(plan: Plan, urls: list[str], pids: list[int]) -> dict[str, Any]:
    """The driven phase, then (``compare_undriven``) the undriven one, on the same servers."""
    m = plan.manifest
    bases = [u.replace("http://", "ws://", 1) + "/ws/sessions/" for u in urls]
    query = "?format=binary" if plan.use_binary else ""
    async with httpx.AsyncClient(timeout=60, limits=httpx.Limits(max_connections=64)) as http:
        d = (await http.get(f"{urls[0]}/models/{plan.model}", params={"version": m.emulator_version})).json()
        lo = np.array([c["low"] for c in d["controls"]] + [f["low"] for f in d["forces"]])
        hi = np.array([c["high"] for c in d["controls"]] + [f["high"] for f in d["forces"]])
        # a driven session's binary frame: neutral inputs (its control values are ignored anyway)
        tail = np.clip(0.0, lo, hi).astype("<f4").tobytes() if plan.use_binary else None
        rings = [goal_ring(m, i) for i in range(plan.clients)]
        policy = {"name": m.name, "version": m.version}
        bodies = [
            {"model": plan.model, "seed": i, "policy": {**policy, "goal": first}}
            for i, (first, _) in enumerate(rings)
        ]
        sids = await _sessions(http, urls, bodies)

        def driven(i: int) -> Start:
            url, (first, goals), phase = bases[i % len(urls)] + sids[i] + query, rings[i], i / plan.clients
            return lambda s, p: _driven_client(
                url, first, goals, tail, plan.rate, plan.goal_every, phase, s, p
            )

        result: dict[str, Any] = {
            "driven": await measure([driven(i) for i in range(plan.clients)], plan.rate, plan.duration, pids)
        }
        await _delete(http, urls, sids)
        result["undriven"] = None
        if plan.compare_undriven:
            version = m.emulator_version
            bodies = [{"model": plan.model, "version": version, "seed": i} for i in range(plan.clients)]
            sids = await _sessions(http, urls, bodies)

            def undriven(i: int) -> Start:
                url, phase = bases[i % len(urls)] + sids[i] + query, i / plan.clients
                ring = control_ring(lo, hi, i, plan.use_binary)
                return lambda s, p: _client(url, ring, plan.rate, phase, s, p.ready, p.stop, p.connected)

            clients = [undriven(i) for i in range(plan.clients)]
            result["undriven"] = await measure(clients, plan.rate, plan.duration, pids)
            await _delete(http, urls, sids)
    return result


def _row(name: str, r: dict[str, Any]) -> str:
    return (
        f"| {name} | {r['steps_per_s']:,.0f} | {r['p50_ms']} | {r['p99_ms']} "
        f"| {'yes' if r['p99_within_limit'] else 'no'} | {r['errors']} "
        f"| {r['clients_replied']} / {r['clients']} | {r['client_cpu_pct']:.0f} / {r['server_cpu_pct']:.0f} |"
    )


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--policy", default="lander-landing", help="the policy driving every session")
    p.add_argument("--policy-version", help="a stored version of it (default: its latest)")
    p.add_argument("--model", default="lander", help="the model the policy drives")
    p.add_argument("--clients", type=int, default=1000)
    p.add_argument("--rate", type=float, default=11.0, help="each client's ticks per second (0: unpaced)")
    p.add_argument("--duration", type=float, default=15.0, help="seconds counted per phase")
    p.add_argument("--goal-every", type=float, default=3.0, help="seconds between a client's new goals")
    p.add_argument("--replicas", type=int, default=2, help="emulator processes")
    p.add_argument("--binary", action="store_true", help="binary frames for the steps without a goal")
    p.add_argument("--compare-undriven", action="store_true", help="then the same with undriven sessions")
    p.add_argument("--artifacts", type=Path, default=REPO / "artifacts", help="the committed defaults")
    p.add_argument("--data", type=Path, default=None, help="the data directory (default: the service's)")
    p.add_argument("--loop", choices=["auto", "uvloop", "asyncio"], default="auto", help="the clients' loop")
    p.add_argument("--force", action="store_true", help="run even on a busy machine (numbers not comparable)")
    p.add_argument("--json", action="store_true")
    args = p.parse_args()
    if not 1 <= args.clients <= MAX_CLIENTS or not 0 < args.duration <= MAX_DURATION_S:
        p.error(f"--clients must be 1..{MAX_CLIENTS} and --duration in (0, {MAX_DURATION_S}], got {args}")
    if not 0 <= args.rate <= MAX_RATE_HZ or not 1 <= args.replicas <= MAX_REPLICAS:
        p.error(f"--rate must be in 0..{MAX_RATE_HZ} and --replicas 1..{MAX_REPLICAS}")
    if not args.goal_every > 0:
        p.error(f"--goal-every must be > 0 seconds, got {args.goal_every}")
    load = os.getloadavg()[0]
    if load >= 1.5 and not args.force:
        print(f"the machine is busy (load {load:.2f}); run it when `uptime` says below 1.5 (or --force)")
        return 2
    data = (args.data or registry.default_data_dir()).absolute()
    try:
        folder = resolve_policy(
            registry.Roots(data, args.artifacts), args.model, args.policy, args.policy_version
        )
        manifest = read_policy(folder)
    except PolicyError as exc:
        p.error(f"--policy: {exc} (looked in --data {data} and --artifacts {args.artifacts})")
    plan = Plan(
        args.model,
        manifest,
        args.clients,
        args.rate,
        args.duration,
        args.goal_every,
        args.binary,
        args.compare_undriven,
    )
    loop_name, run_on_loop = _runner(args.loop)
    with contextlib.ExitStack() as stack:
        servers = [
            stack.enter_context(serve(str(args.artifacts), DATA_DIR=str(data), REPLICA_ID=f"r{k + 1}"))
            for k in range(args.replicas)
        ]
        result = run_on_loop(run(plan, [u for u, _ in servers], [pid for _, pid in servers]))
    frames = "binary (goals in JSON steps)" if args.binary else "json"
    out = {
        "policy": {
            "model": manifest.model,
            "name": manifest.name,
            "version": manifest.version,
            "emulator_version": manifest.emulator_version,
            "goal_variables": manifest.goal_variables,
            "goal_low": manifest.goal_low,
            "goal_high": manifest.goal_high,
        },
        "clients": args.clients,
        "rate_hz": args.rate,
        "goal_every_s": args.goal_every,
        "replicas": args.replicas,
        "frames": frames,
        "p99_limit_ms": P99_LIMIT_MS,
        "load": load,
        "loop": loop_name,
        **result,
    }
    print(
        f"{args.clients} clients at {args.rate:g} Hz, emulator processes: {args.replicas}, frames: {frames}, "
        f"policy {manifest.name} {manifest.version} (emulator {manifest.emulator_version}), "
        f"a new goal every {args.goal_every:g} s"
    )
    print(
        f"| sessions | steps/s | p50 ms | p99 ms | p99 ≤ {P99_LIMIT_MS:g} ms | errors | clients replied "
        "| CPU % client / server |"
    )
    print("|---|---|---|---|---|---|---|---|")
    print(_row("driven", result["driven"]))
    if result["undriven"] is not None:
        print(_row("undriven", result["undriven"]))
    if args.json:
        print(json.dumps(out))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
