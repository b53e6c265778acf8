"""What the dashboard's end-to-end tests share: whether they can run here (Chromium, node,
playwright-core, the built dashboard), a stack started for a test module (``services.stack`` on free
ports, its own Redis keys and queues, a Redis found or started as ``make up`` does), and one phase of a
browser script (``dashboard.mjs``, ``add_model.mjs``) run against it."""

from __future__ import annotations

import json
import logging
import os
import shutil
import subprocess
import time
import uuid
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import pytest

from services.stack import PortTakenError, Stack, StackConfig, StackError, free_port

ROOT = Path(__file__).resolve().parents[2]
SHOTS = ROOT / "tests" / "e2e" / "screenshots"
CHROMIUM = os.environ.get("CHROMIUM", "/usr/bin/chromium")
log = logging.getLogger(__name__)
PORT_ATTEMPTS = 3  # starts on fresh ports when a service finds its port taken


def missing(dashboard: bool = True) -> str | None:
    """Why the browser tests cannot run here, or None (``dashboard``: they need it built)."""
    if not Path(CHROMIUM).is_file():
        return f"no Chromium at {CHROMIUM} (make test installs Debian's chromium)"
    if shutil.which("node") is None:
        return "no node on PATH"
    if not (ROOT / "web" / "node_modules" / "playwright-core").is_dir():
        return "web/node_modules is not installed (make test runs npm ci in web/)"
    if dashboard and not (ROOT / "web" / "dist" / "index.html").is_file():
        return "the dashboard is not built (make test runs npm run build in web/)"
    return None


@contextmanager
def running_stack(log_dir: Path, **config: Any) -> Iterator[Stack]:
    """The whole stack on free ports (``StackConfig`` fields in ``config``); skips the test when there
    is no Redis to be had."""
    env = {"WORKER_THREADS": "1", **config.pop("env", {})}
    config.setdefault("data_dir", log_dir / "data")  # each stack its own: one test's uploads stay its own
    for attempt in range(1, PORT_ATTEMPTS + 1):
        s = Stack(
            StackConfig(
                emulator_port=free_port(),
                controller_port=free_port(),
                trainer_port=free_port(),
                web_port=free_port(),
                log_dir=log_dir,
                train_missing=False,
                namespace=f"test-e2e-{uuid.uuid4().hex[:8]}",
                env=env,
                **config,
            )
        )
        try:
            s.start()
            break
        except PortTakenError as exc:  # another process bound a port first: new ports, start again
            if attempt == PORT_ATTEMPTS:
                raise
            log.warning("a port was taken while the stack started (attempt %d): %s", attempt, exc)
        except StackError as exc:
            if "no Redis" in str(exc):
                pytest.skip(str(exc))
            raise
    log.info("stack up in %.1f s: %s", s.startup_s, s.urls)
    try:
        yield s
    finally:
        s.stop()


def run_phase(stack: Stack, script: Path, phase: str, timeout: float, **env: str) -> dict[str, Any]:
    """Run one phase of a browser script against the stack; its JSON result (``wall_s`` added, saved as
    ``screenshots/<phase>.json``). Fails the test with the script's output when a check failed."""
    t0 = time.monotonic()
    r = subprocess.run(
        ["node", str(script), phase],
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


def update_docs(shots: dict[str, str]) -> None:
    """Copy screenshots (name under ``screenshots/`` -> name under ``docs/``) that the README shows."""
    (ROOT / "docs").mkdir(exist_ok=True)
    for shot, doc in shots.items():
        if (SHOTS / shot).is_file():
            shutil.copyfile(SHOTS / shot, ROOT / "docs" / doc)
