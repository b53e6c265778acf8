"""The dashboard end to end, in headless Chromium: the stack (``services.stack``) is started here on
free ports with a Redis found or started as ``make up`` does, then ``tests/e2e/dashboard.mjs`` drives
the browser phase by phase at 1280×800:

- Models: every model, its rollout curves labelled by whether the emulator serves their version, the
  lander's errors in physical units;
- Playground: a live lander session driven by the keyboard, on screen with the ground below it, the
  MuJoCo ghost and the gap to it (number and curve), the frame rate; then, without reloading, a
  pendulum-force session framed with its ground and driven through its force sliders;
- Controllers: a truck-parking job (goal dragged, objective curve live and falling), its outcome
  checked against the job's result check by check, the replay with model and goal on screen and the
  gap plotted; switching to lander-landing clears the job and frames the lander and its goal, and its
  job's outcome and replay are checked the same way;
- with the worker stopped, the message that no worker is taking jobs.

Screenshots go to ``tests/e2e/screenshots/`` (ignored by git); ``E2E_UPDATE_DOCS=1`` copies those the
README shows into ``docs/`` (``DOC_SHOTS``).
"""

from __future__ import annotations

import json
import logging
import os
import shutil
import subprocess
import time
import urllib.request
import uuid
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from services.stack import Stack, StackConfig, StackError, free_port

ROOT = Path(__file__).resolve().parents[2]
SCRIPT = ROOT / "tests" / "e2e" / "dashboard.mjs"
SHOTS = ROOT / "tests" / "e2e" / "screenshots"
CHROMIUM = os.environ.get("CHROMIUM", "/usr/bin/chromium")
# screenshot of a phase -> its name under docs/ (shown in the README)
DOC_SHOTS = {
    "models.png": "models.png",
    "playground.png": "playground.png",
    "playground-pendulum-force.png": "playground-pendulum-force.png",
    "controllers.png": "controllers.png",
    "controllers-lander.png": "controllers-lander.png",
    "replay.png": "replay.png",
    "replay-lander.png": "replay-lander.png",
}
log = logging.getLogger(__name__)


def _missing() -> str | None:
    if not Path(CHROMIUM).is_file():
        return f"no Chromium at {CHROMIUM} (make test installs Debian's chromium)"
    if shutil.which("node") is None:
        return "no node on PATH"
    if not (ROOT / "web" / "node_modules" / "playwright-core").is_dir():
        return "web/node_modules is not installed (make test runs npm ci in web/)"
    if not (ROOT / "web" / "dist" / "index.html").is_file():
        return "the dashboard is not built (make test runs npm run build in web/)"
    return None


pytestmark = pytest.mark.skipif(_missing() is not None, reason=_missing() or "")


@pytest.fixture(scope="module")
def stack(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Stack]:
    cfg = StackConfig(
        emulator_port=free_port(),
        controller_port=free_port(),
        trainer_port=free_port(),
        web_port=free_port(),
        log_dir=tmp_path_factory.mktemp("stack-logs"),
        train_missing=False,
        namespace=f"test-e2e-{uuid.uuid4().hex[:8]}",
        env={"WORKER_THREADS": "1"},
    )
    s = Stack(cfg)
    try:
        s.start()
    except StackError as exc:
        if "no Redis" in str(exc):
            pytest.skip(str(exc))
        raise
    log.info("stack up in %.1f s: %s", s.startup_s, s.urls)
    yield s
    s.stop()


def _phase(stack: Stack, phase: str, timeout: float, **env: str) -> dict[str, Any]:
    t0 = time.monotonic()
    r = subprocess.run(
        ["node", str(SCRIPT), phase],
        cwd=ROOT,
        env={
            **os.environ,
            "DASHBOARD_URL": stack.urls["web"],
            "SCREENSHOT_DIR": str(SHOTS),
            "DOCS": os.environ.get("E2E_UPDATE_DOCS", "0"),
            **env,
        },
        capture_output=True,
        text=True,
        timeout=timeout,
        check=False,
    )
    print(r.stdout)
    lines = [ln for ln in r.stdout.splitlines() if ln.startswith("{")]
    result: dict[str, Any] = json.loads(lines[-1]) if lines else {"ok": False}
    result["wall_s"] = round(time.monotonic() - t0, 1)
    assert r.returncode == 0 and result.get("ok"), (
        f"{phase} failed: {result.get('error')}\nstdout:\n{r.stdout}\nstderr:\n{r.stderr[-3000:]}"
    )
    (SHOTS / f"{phase}.json").write_text(json.dumps(result, indent=2))
    return result


def _truck_task(stack: Stack) -> str:
    with urllib.request.urlopen(f"{stack.urls['controller']}/tasks", timeout=10) as r:
        body = json.loads(r.read())
    tasks = body["tasks"] if isinstance(body, dict) else body
    names = [t["name"] for t in tasks if t.get("model") == "truck"]
    assert names, f"no truck task in {tasks}"
    return str(names[0])


def test_models_page(stack: Stack) -> None:
    r = _phase(stack, "models", 120)
    assert r["models"] >= 5


def test_playground_drives_a_lander_then_a_pendulum(stack: Stack) -> None:
    r = _phase(stack, "playground", 180)
    assert r["changed_cells"] > 20
    print(
        "dashboard fps with a live lander session and its ghost (headless Chromium, software WebGL): "
        f"{r['fps']} at resolution scale {r['resolution_scale']}"
    )


def test_controller_job_and_replay(stack: Stack) -> None:
    r = _phase(stack, "controllers", 420, TRUCK_TASK=_truck_task(stack))
    assert r["objective_last"] < r["objective_first"]
    if os.environ.get("E2E_UPDATE_DOCS") == "1":
        _update_docs()


def _update_docs() -> None:
    (ROOT / "docs").mkdir(exist_ok=True)
    for shot, doc in DOC_SHOTS.items():
        if (SHOTS / shot).is_file():
            shutil.copyfile(SHOTS / shot, ROOT / "docs" / doc)


def test_stopped_worker_is_reported(stack: Stack) -> None:
    task = _truck_task(stack)
    stack.stop_service("worker")
    r = _phase(stack, "worker-down", 120, TRUCK_TASK=task)
    assert "worker" in r["message"]
