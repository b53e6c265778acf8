"""Does training starve serving? Websocket p99 at a game's tick rate, with and without one training.

    python bench/train_serving.py                      # 1,000 clients at 11 Hz, 2 emulator processes
    python bench/train_serving.py --duration 20 --json
    python bench/train_serving.py --model path/to/model.zip --examples 40000

Runs ``bench/ws_load.py --clients N --rate R --binary --replicas 2`` (its own emulator processes on the
committed artifacts) twice: once on a quiet machine, then again while the trainer service trains one
model: a trainer API and one training worker (``python -m services.trainer.worker``, at its default
lower priority ``WORKER_NICE``) on a registry of their own, the model uploaded through ``POST
/trainings``, the load started once the training samples, and the training cancelled afterwards. The
training is the service's as deployed, less compose's CPU limit (``cpus``), which a bare machine does
not have: only the lower priority keeps it off the serving cores here. Prints a table and, with
``--json``, one JSON object as the last line (both runs' ws_load results and the training's phases
during the loaded run).

Meaningful on a quiet machine only (``uptime``: load below 1.5): it refuses to start otherwise unless
``--force``. Redis: ``REDIS_URL``, else 127.0.0.1:6379 (the training's keys have a prefix of their own
and are removed afterwards).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
from _trainer import trainer

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_MODEL = ROOT / "neuroanimator" / "catalog" / "lander.xml"


def ws_load(clients: int, rate: float, duration: float, replicas: int) -> dict[str, Any]:
    """One run of ``ws_load.py``: its JSON result."""
    cmd = [sys.executable, str(ROOT / "bench" / "ws_load.py"), "--clients", str(clients), "--rate", str(rate)]
    cmd += ["--duration", str(duration), "--replicas", str(replicas), "--binary", "--json"]
    out = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, check=True, timeout=600).stdout
    result: dict[str, Any] = json.loads(out.strip().splitlines()[-1])
    return result


@contextlib.contextmanager
def training(model: Path, examples: int, redis_url: str, log_dir: Path) -> Iterator[tuple[str, str]]:
    """A trainer API and one training worker on a registry of their own, training ``model``; yields
    (the API's URL, the training's id). Cancels the training and stops both on exit."""
    with trainer(redis_url, log_dir) as t:
        answer, _ = t.upload(model, name="bench-model", examples=str(examples), super_step="50")
        yield t.url, answer["id"]


def _status(url: str, tid: str) -> dict[str, Any]:
    got: dict[str, Any] = httpx.get(f"{url}/trainings/{tid}", timeout=10).json()
    return got


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--clients", type=int, default=1000)
    p.add_argument("--rate", type=float, default=11.0, help="each client's ticks per second")
    p.add_argument("--duration", type=float, default=15.0, help="seconds counted per run")
    p.add_argument("--replicas", type=int, default=2, help="emulator processes")
    p.add_argument("--model", type=Path, default=DEFAULT_MODEL, help="the model the trainer trains meanwhile")
    p.add_argument("--examples", type=int, default=20_000, help="its sample budget")
    p.add_argument("--force", action="store_true", help="run even on a busy machine (numbers not comparable)")
    p.add_argument("--json", action="store_true")
    args = p.parse_args()
    load = os.getloadavg()[0]
    if load >= 1.5 and not args.force:
        print(f"the machine is busy (load {load:.2f}); run it when `uptime` says below 1.5 (or --force)")
        return 2
    redis_url = os.environ.get("REDIS_URL", "redis://127.0.0.1:6379/0")
    quiet = ws_load(args.clients, args.rate, args.duration, args.replicas)
    phases: list[str] = []
    with (
        tempfile.TemporaryDirectory(prefix="bench-train-serving-") as logs,
        training(args.model, args.examples, redis_url, Path(logs)) as (url, tid),
    ):
        deadline = time.monotonic() + 300
        while (s := _status(url, tid))["phase"] not in ("sampling", "training"):
            if s["status"] in ("succeeded", "failed", "cancelled") or time.monotonic() > deadline:
                raise SystemExit(f"the training did not start sampling: {s}")
            time.sleep(0.5)
        phases.append(s["phase"])
        loaded = ws_load(args.clients, args.rate, args.duration, args.replicas)
        after = _status(url, tid)
        phases.append(after["phase"])
        if after["status"] != "running":
            print(f"warning: the training ended during the run ({after['status']}): lower --duration")
    print(f"{args.clients} clients at {args.rate:g} Hz, {args.replicas} emulator processes, binary frames")
    print("| training | steps/s | p50 ms | p99 ms | errors | CPU % client / server |")
    print("|---|---|---|---|---|---|")
    for name, r in (("none", quiet), (f"one ({' → '.join(phases)})", loaded)):
        print(
            f"| {name} | {r['steps_per_s']:,.0f} | {r['p50_ms']} | {r['p99_ms']} | {r['errors']} "
            f"| {r['client_cpu_pct']:.0f} / {r['server_cpu_pct']:.0f} |"
        )
    if args.json:
        print(
            json.dumps(
                {"without_training": quiet, "with_training": loaded, "training_phases": phases, "load": load}
            )
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
