"""``/docs`` and ``/redoc`` of the emulator, the controller and the dashboard's server render in headless
Chromium with every request off this machine aborted (``tests/e2e/docs_offline.mjs``): Swagger UI and
ReDoc come from the services themselves, not from a CDN."""

from __future__ import annotations

import json
import os
import socket
import subprocess
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import uvicorn
from fastapi import FastAPI

from services.controller.app import create_app as controller_app
from services.controller.settings import Settings as ControllerSettings
from services.emulator.app import create_app as emulator_app
from services.emulator.settings import Settings as EmulatorSettings
from services.web.app import create_app as web_app
from services.web.settings import Settings as WebSettings
from tests.e2e.harness import missing

ROOT = Path(__file__).resolve().parents[2]
SCRIPT = ROOT / "tests" / "e2e" / "docs_offline.mjs"
SHOTS = ROOT / "tests" / "e2e" / "screenshots"
pytestmark = pytest.mark.skipif(missing(dashboard=False) is not None, reason=missing(dashboard=False) or "")


def _serve(app: FastAPI) -> tuple[uvicorn.Server, threading.Thread, str]:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    server = uvicorn.Server(uvicorn.Config(app, host="127.0.0.1", port=port, log_level="warning"))
    th = threading.Thread(target=server.run, daemon=True)
    th.start()
    deadline = time.monotonic() + 30
    while not server.started:
        assert time.monotonic() < deadline and th.is_alive(), "uvicorn did not start"
        time.sleep(0.02)
    return server, th, f"http://127.0.0.1:{port}"


@pytest.fixture(scope="module")
def services(tmp_path_factory: pytest.TempPathFactory) -> Iterator[dict[str, str]]:
    tmp = tmp_path_factory.mktemp("docs-artifacts")  # no models: the docs need none
    apps = {
        "emulator": emulator_app(EmulatorSettings(artifacts_dir=tmp)),
        "controller": controller_app(
            ControllerSettings(artifacts_dir=tmp, redis_url="redis://127.0.0.1:1/0")
        ),
        "web": web_app(WebSettings(artifacts_dir=tmp, web_dist=tmp / "dist")),
    }
    running = {name: _serve(app) for name, app in apps.items()}
    yield {name: url for name, (_, _, url) in running.items()}
    for server, th, _ in running.values():
        server.should_exit = True
        th.join(10)


def test_docs_render_with_the_network_blocked(services: dict[str, str]) -> None:
    spec = ",".join(f"{name}={url}" for name, url in services.items())
    r = subprocess.run(
        ["node", str(SCRIPT)],
        cwd=ROOT,
        env={**os.environ, "SERVICE_URLS": spec, "SCREENSHOT_DIR": str(SHOTS)},
        capture_output=True,
        text=True,
        timeout=180,
        check=False,
    )
    print(r.stdout)
    lines = [ln for ln in r.stdout.splitlines() if ln.startswith("{")]
    result: dict[str, Any] = json.loads(lines[-1]) if lines else {"ok": False}
    assert r.returncode == 0 and result["ok"], f"{result.get('error')}\n{r.stdout}\n{r.stderr[-3000:]}"
    pages = {(p["service"], p["page"]) for p in result["pages"]}
    assert pages == {(s, k) for s in services for k in ("docs", "redoc")}
    assert all(p["items"] > 0 and not p["blocked"] for p in result["pages"])
