"""The dashboard end to end, in headless Chromium: the stack (``services.stack``) is started here on
free ports with a Redis found or started as ``make up`` does, then ``tests/e2e/dashboard.mjs`` drives
the browser phase by phase: the Models page, a live lander session driven by the keyboard (the
canvas shows the model and changes as it moves; the frame rate is measured), a truck-parking job
(goal dragged, objective curve live and falling, replay playing), and with the worker stopped, the
message that no worker is taking jobs. Screenshots go to ``tests/e2e/screenshots/`` (ignored by git);
``E2E_UPDATE_DOCS=1`` also copies the Controllers page to ``docs/dashboard.png``.
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
        env={**os.environ, "DASHBOARD_URL": stack.urls["web"], "SCREENSHOT_DIR": str(SHOTS), **env},
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


def test_playground_drives_a_lander(stack: Stack) -> None:
    r = _phase(stack, "playground", 180)
    assert r["changed_cells"] > 20
    print(f"dashboard fps with a live lander session (headless Chromium, software WebGL): {r['fps']}")


def test_controller_job_and_replay(stack: Stack) -> None:
    r = _phase(stack, "controllers", 420, TRUCK_TASK=_truck_task(stack))
    assert r["objective_last"] < r["objective_first"]
    if os.environ.get("E2E_UPDATE_DOCS") == "1" or not (ROOT / "docs" / "dashboard.png").is_file():
        (ROOT / "docs").mkdir(exist_ok=True)
        shutil.copyfile(SHOTS / "controllers.png", ROOT / "docs" / "dashboard.png")


def test_stopped_worker_is_reported(stack: Stack) -> None:
    task = _truck_task(stack)
    stack.stop_service("worker")
    r = _phase(stack, "worker-down", 120, TRUCK_TASK=task)
    assert "worker" in r["message"]
