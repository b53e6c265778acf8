"""The dashboard's frame rate: the Playground with a live lander session and its MuJoCo ghost, in headless
Chromium with software WebGL (SwiftShader: no GPU, every pixel on the CPU), at 1280×800.

    python bench/dashboard_fps.py                          # one run: 10 s to settle, 6 windows of 5 s
    python bench/dashboard_fps.py --runs 3 --json
    python bench/dashboard_fps.py --settle 20 --windows 12 --seconds 5

Each run starts the whole stack on free ports (``services.stack``, as ``make up`` does), runs the ``frame-rate`` phase of ``tests/e2e/dashboard.mjs`` (the
lander at rest 20 m up under hover thrust, the ghost on; the frames are timed in the page from its
animation frames) and stops the stack. Per window: the frame rate, the frames that came late (a vsync
missed: an interval over 25 ms) and the resolution scale the views drew at (the governor of
``web/src/scene/quality.ts`` lowers it while frames are dropped). Needs what the end-to-end tests need
(Chromium, node, web/node_modules, a built dashboard) and a Redis (found or started as ``make up`` does).
Prints a table and, with --json, one JSON object as the last line.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import statistics
import subprocess
import tempfile
import uuid
from pathlib import Path
from typing import Any

from services.stack import Stack, StackConfig, free_port

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "tests" / "e2e" / "dashboard.mjs"
log = logging.getLogger("bench.dashboard_fps")


def one_run(settle: float, windows: int, seconds: float) -> dict[str, Any]:
    """Start a stack, measure the Playground's frame rate, stop the stack."""
    with tempfile.TemporaryDirectory(prefix="neuro-fps-") as tmp:
        stack = Stack(
            StackConfig(
                emulator_port=free_port(),
                controller_port=free_port(),
                trainer_port=free_port(),
                web_port=free_port(),
                log_dir=Path(tmp),
                train_missing=False,
                namespace=f"bench-fps-{uuid.uuid4().hex[:8]}",
            )
        )
        stack.start()
        try:
            timeout = 90 + settle + windows * seconds
            r = subprocess.run(
                ["node", str(SCRIPT), "frame-rate"],
                cwd=ROOT,
                env={
                    **os.environ,
                    "DASHBOARD_URL": stack.urls["web"],
                    "SCREENSHOT_DIR": tmp,
                    "FPS_SETTLE": str(settle),
                    "FPS_WINDOWS": str(windows),
                    "FPS_SECONDS": str(seconds),
                },
                capture_output=True,
                text=True,
                timeout=timeout,
                check=False,
            )
        finally:
            stack.stop()
    lines = [ln for ln in r.stdout.splitlines() if ln.startswith("{")]
    result: dict[str, Any] = json.loads(lines[-1]) if lines else {"ok": False}
    for line in r.stdout.splitlines():
        if line.startswith("["):
            log.debug("%s", line)
    if r.returncode != 0 or not result.get("ok"):
        raise SystemExit(
            f"the frame-rate phase failed: {result.get('error')}\n{r.stdout}\n{r.stderr[-2000:]}"
        )
    return result


def summary(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """Over all windows: the mean and lowest frame rate, the share of late frames, the scales seen."""
    fps = [w["fps"] for w in rows]
    frames = sum(w["frames"] for w in rows)
    return {
        "fps_mean": round(statistics.fmean(fps), 2),
        "fps_min": round(min(fps), 2),
        "late_share": round(sum(w["late"] for w in rows) / max(1, frames), 4),
        "scales": sorted({w["scale"] for w in rows}),
    }


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--runs", type=int, default=1)
    p.add_argument("--settle", type=float, default=10.0, help="seconds of the live session before measuring")
    p.add_argument("--windows", type=int, default=6)
    p.add_argument("--seconds", type=float, default=5.0, help="length of a window")
    p.add_argument("--json", action="store_true", help="print one JSON object as the last line")
    p.add_argument("--verbose", action="store_true", help="also log the browser script's progress lines")
    a = p.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    log.setLevel(logging.DEBUG if a.verbose else logging.INFO)
    runs = []
    for i in range(a.runs):
        res = one_run(a.settle, a.windows, a.seconds)
        runs.append({"windows": res["windows"], **summary(res["windows"]), "renderer": res.get("renderer")})
        log.info("run %d of %d done", i + 1, a.runs)
    print(f"renderer: {runs[0]['renderer']}")
    print(f"{'run':>3}  {'window':>6}  {'fps':>6}  {'late':>5}  {'scale':>5}")
    for i, run in enumerate(runs, 1):
        for j, w in enumerate(run["windows"], 1):
            print(f"{i:>3}  {j:>6}  {w['fps']:>6.1f}  {w['late']:>5}  {w['scale']:>5}")
        print(
            f"{i:>3}  {'all':>6}  {run['fps_mean']:>6.1f}  {run['late_share']:>5.1%}  "
            f"lowest window {run['fps_min']:.1f} fps"
        )
    if a.json:
        print(json.dumps({"settle_s": a.settle, "window_s": a.seconds, "runs": runs}))


if __name__ == "__main__":
    main()
