"""Shared by the benchmarks: start the emulator service as a uvicorn subprocess on 127.0.0.1 (a free
port), wait until it is ready, stop it afterwards; read a process's resident memory."""

from __future__ import annotations

import contextlib
import os
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import httpx

from services.stack import free_port

REPO = Path(__file__).resolve().parents[1]


@contextlib.contextmanager
def serve(
    artifacts: str, module: str = "services.emulator", ready: str = "/readyz", **env: str
) -> Iterator[tuple[str, int]]:
    """(base URL, server pid) of a fresh ``python -m <module>`` with these extra env vars, once it
    answers 200 on ``ready`` (``/healthz`` for an emulator service whose registry is still empty)."""
    port = free_port()
    full = {
        **os.environ,
        "ARTIFACTS_DIR": str(Path(artifacts).resolve()),
        "HOST": "127.0.0.1",
        "PORT": str(port),
        "LOG_LEVEL": "warning",
        "API_KEYS": "",
        "REDIS_URL": "",
        **env,
    }
    proc = subprocess.Popen([sys.executable, "-m", module], env=full, cwd=REPO)
    url = f"http://127.0.0.1:{port}"
    try:
        deadline = time.monotonic() + 120
        while True:
            if proc.poll() is not None:
                raise RuntimeError(f"{module} exited with code {proc.returncode}")
            with contextlib.suppress(httpx.HTTPError):
                if httpx.get(f"{url}{ready}", timeout=2).status_code == 200:
                    break
            if time.monotonic() > deadline:
                raise RuntimeError(f"{module} did not become ready in 120 s")
            time.sleep(0.1)
        yield url, proc.pid
    finally:
        proc.terminate()
        try:
            proc.wait(10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


def rss_bytes(pid: int) -> int:
    """VmRSS of a process, from /proc/<pid>/status."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) * 1024
    raise RuntimeError(f"no VmRSS for pid {pid}")
