"""Time from `make up` to a usable stack: the dashboard answers and the emulator, controller and trainer
are ready.

    python bench/stack_startup.py                 # one run of `make up` on free ports
    python bench/stack_startup.py --runs 3 --json
    python bench/stack_startup.py --command "python -m services.stack"

On a warm machine (venv installed, web/dist built) `make up` only checks that and starts the services.
Each run launches the command in its own process group on free ports (EMULATOR_PORT, CONTROLLER_PORT,
TRAINER_PORT, WEB_PORT), polls until every part answers, then sends Ctrl-C (SIGINT) as a person would
and times the shutdown. Prints a table and, with --json, one JSON object as the last line.
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import signal
import statistics
import subprocess
import sys
import tempfile
import time
import urllib.error
import urllib.request
from pathlib import Path
from typing import Any

from services.stack import free_port

ROOT = Path(__file__).resolve().parents[1]


def answers(url: str) -> bool:
    try:
        with urllib.request.urlopen(url, timeout=1) as r:
            return bool(r.status == 200)
    except (urllib.error.URLError, OSError):
        return False


def one_run(command: str, timeout: float) -> dict[str, Any]:
    ports = {
        "EMULATOR_PORT": free_port(),
        "CONTROLLER_PORT": free_port(),
        "TRAINER_PORT": free_port(),
        "WEB_PORT": free_port(),
    }
    urls = {
        "dashboard": f"http://127.0.0.1:{ports['WEB_PORT']}/",
        "emulator": f"http://127.0.0.1:{ports['EMULATOR_PORT']}/readyz",
        "controller": f"http://127.0.0.1:{ports['CONTROLLER_PORT']}/readyz",
        "trainer": f"http://127.0.0.1:{ports['TRAINER_PORT']}/readyz",
    }
    env = {**os.environ, **{k: str(v) for k, v in ports.items()}}
    with tempfile.TemporaryFile() as out:
        t0 = time.monotonic()
        proc = subprocess.Popen(
            shlex.split(command),
            cwd=ROOT,
            env=env,
            stdout=out,
            stderr=subprocess.STDOUT,
            start_new_session=True,
        )
        ready_at: dict[str, float] = {}
        try:
            while len(ready_at) < len(urls):
                if proc.poll() is not None:
                    out.seek(0)
                    raise RuntimeError(
                        f"{command!r} exited with {proc.returncode}:\n{out.read().decode()[-3000:]}"
                    )
                if time.monotonic() - t0 > timeout:
                    raise RuntimeError(f"not usable within {timeout} s; ready: {sorted(ready_at)}")
                for name, url in urls.items():
                    if name not in ready_at and answers(url):
                        ready_at[name] = time.monotonic() - t0
                time.sleep(0.1)
            usable = time.monotonic() - t0
        finally:
            t1 = time.monotonic()
            os.killpg(proc.pid, signal.SIGINT)  # Ctrl-C reaches the whole foreground group
            try:
                proc.wait(60)
            except subprocess.TimeoutExpired:
                os.killpg(proc.pid, signal.SIGKILL)
                proc.wait()
            stop_s = time.monotonic() - t1
    left = [name for name, url in urls.items() if answers(url)]
    return {
        "usable_s": round(usable, 2),
        **{f"{k}_ready_s": round(v, 2) for k, v in ready_at.items()},
        "stop_s": round(stop_s, 2),
        "still_answering_after_stop": left,
    }


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--command", default="make up", help="what starts the stack (default: make up)")
    p.add_argument("--runs", type=int, default=1)
    p.add_argument("--timeout", type=float, default=300.0)
    p.add_argument("--json", action="store_true")
    args = p.parse_args()
    runs = [one_run(args.command, args.timeout) for _ in range(args.runs)]
    print(
        f"{'run':>3}  {'usable s':>8}  {'emulator':>8}  {'controller':>10}  {'dashboard':>9}  {'stop s':>6}"
    )
    for i, r in enumerate(runs, 1):
        print(
            f"{i:>3}  {r['usable_s']:>8.2f}  {r.get('emulator_ready_s', 0):>8.2f}  "
            f"{r.get('controller_ready_s', 0):>10.2f}  {r.get('dashboard_ready_s', 0):>9.2f}  {r['stop_s']:>6.2f}"
        )
    usable = [r["usable_s"] for r in runs]
    summary = {
        "command": args.command,
        "runs": runs,
        "usable_s_median": statistics.median(usable),
        "usable_s_max": max(usable),
        "target_s": 60,
        "clean_stop": all(not r["still_answering_after_stop"] for r in runs),
    }
    print(f"median time to usable: {summary['usable_s_median']:.2f} s (target < 60 s)")
    if args.json:
        print(json.dumps(summary))
    return 0


if __name__ == "__main__":
    sys.exit(main())
