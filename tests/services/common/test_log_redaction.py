"""No API key reaches a log line: uvicorn writes each request's path with its query string, and browsers
send keys as ``?api_key=`` on websockets and event streams."""

from __future__ import annotations

import contextlib
import logging
import os
import subprocess
import sys
import time
import urllib.error
import urllib.request
from pathlib import Path

import pytest
from websockets.sync.client import connect

from services.common.logs import JsonFormatter, RedactSecrets, redact
from tests.services.common.test_json_logs import ROOT, _free_port, _lines_until

SECRET = "s3cret-KEY-value-0123"


def test_redact_blanks_secret_parameters_only() -> None:
    assert redact(f"/ws/sessions/r0-1?api_key={SECRET}&x=1") == "/ws/sessions/r0-1?api_key=***&x=1"
    assert (
        redact(f'GET /jobs/a/events?API_KEY={SECRET} HTTP/1.1"') == 'GET /jobs/a/events?API_KEY=*** HTTP/1.1"'
    )
    assert redact(f"?token={SECRET}") == "?token=***"
    # the query parser decodes names: a percent-encoded one carries the key as well
    assert redact(f"/ws/sessions/r0-1?api%5Fkey={SECRET}") == "/ws/sessions/r0-1?api%5Fkey=***"
    assert redact(f"?%61pi%5fKEY={SECRET}&b=1") == "?%61pi%5fKEY=***&b=1"
    assert redact("/models?version=3") == "/models?version=3"


def test_the_filter_rewrites_uvicorns_access_record() -> None:
    record = logging.LogRecord(
        "uvicorn.access",
        logging.INFO,
        __file__,
        1,
        '%s - "%s %s HTTP/%s" %d',
        ("127.0.0.1:5000", "GET", f"/jobs/x/events?api_key={SECRET}", "1.1", 200),
        None,
    )
    assert RedactSecrets().filter(record)
    line = JsonFormatter().format(record)
    assert SECRET not in line and "api_key=***" in line


SERVED = {
    "services.emulator": ("/models", "/sessions/r0-x", "/ws/sessions/r0-x"),
    "services.controller": ("/jobs", "/jobs/x/events", "/ws/jobs/x"),
    "services.trainer": ("/trainings", "/trainings/x/events", "/models"),
}


@pytest.mark.parametrize("module", sorted(SERVED))
def test_a_running_service_does_not_log_the_key(tmp_path: Path, module: str) -> None:
    port = _free_port()
    env = {
        **os.environ,
        "PYTHONPATH": str(ROOT),
        "ARTIFACTS_DIR": str(tmp_path),
        "PORT": str(port),
        "API_KEYS": SECRET,
        # the emulator: no persistence; the others start without Redis (their calls are then 503)
        "REDIS_URL": "" if module == "services.emulator" else f"redis://127.0.0.1:{_free_port()}/0",
        "LOG_LEVEL": "info",
    }
    proc = subprocess.Popen([sys.executable, "-m", module], env=env, cwd=tmp_path, stderr=subprocess.PIPE)
    try:
        _lines_until(proc, f"Uvicorn running on http://127.0.0.1:{port} (Press CTRL+C to quit)", timeout=90)
        for path in SERVED[module]:
            for query in (f"api_key={SECRET}&b=2", f"api%5Fkey={SECRET}"):
                url = f"127.0.0.1:{port}{path}?{query}"
                if path.startswith("/ws/"):  # uvicorn logs the handshake's path and query too
                    with contextlib.suppress(Exception), connect(f"ws://{url}", open_timeout=10) as ws:
                        ws.recv(timeout=5)
                    continue
                # 401 or 503 mostly: the line is logged all the same
                with contextlib.suppress(urllib.error.HTTPError):
                    urllib.request.urlopen(f"http://{url}", timeout=10).read()
        time.sleep(0.5)
    finally:
        proc.terminate()
        _, err = proc.communicate(timeout=15)
    text = err.decode(errors="replace")
    assert "api_key=***" in text and "api%5Fkey=***" in text, text[-2000:]
    assert SECRET not in text
