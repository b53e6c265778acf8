"""JSON-line logs: every ``extra=`` field reaches the line, in a logger and in a running service."""

from __future__ import annotations

import io
import json
import logging
import os
import selectors
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from services.common.logs import JsonFormatter, setup
from services.stack import free_port as _free_port

ROOT = Path(__file__).resolve().parents[3]


@pytest.fixture
def captured() -> Iterator[io.StringIO]:
    """The ``test.logs`` logger writing through ``JsonFormatter`` into a string."""
    out = io.StringIO()
    handler = logging.StreamHandler(out)
    handler.setFormatter(JsonFormatter())
    logger = logging.getLogger("test.logs")
    logger.addHandler(handler)
    logger.setLevel(logging.INFO)
    yield out
    logger.removeHandler(handler)


def test_extra_fields_reach_the_line(captured: io.StringIO) -> None:
    logging.getLogger("test.logs").info(
        "job %s queued", "j-1", extra={"job": "j-1", "depth": 3, "where": Path("/tmp")}
    )
    line = json.loads(captured.getvalue())
    assert line["message"] == "job j-1 queued"
    assert (line["level"], line["logger"]) == ("INFO", "test.logs")
    assert (line["job"], line["depth"], line["where"]) == ("j-1", 3, "/tmp")  # unknown types as str
    assert not {"args", "msg", "levelno", "pathname", "exc_info"} & set(line)  # record internals stay out


def test_exceptions_are_one_line(captured: io.StringIO) -> None:
    try:
        1 / 0  # noqa: B018
    except ZeroDivisionError:
        logging.getLogger("test.logs").exception("failed", extra={"step": 7})
    text = captured.getvalue()
    assert text.count("\n") == 1  # the traceback is inside the JSON string, not on lines of its own
    line = json.loads(text)
    assert line["step"] == 7 and "ZeroDivisionError" in line["exception"]


def test_setup_replaces_the_root_handlers() -> None:
    root = logging.getLogger()
    before, level = root.handlers[:], root.level
    try:
        setup("warning")
        assert root.level == logging.WARNING and len(root.handlers) == 1
        assert isinstance(root.handlers[0].formatter, JsonFormatter)
        plain = logging.Formatter("%(message)s")
        setup("info", plain)
        assert root.handlers[0].formatter is plain
    finally:
        root.handlers[:] = before
        root.setLevel(level)


def _lines_until(proc: subprocess.Popen[bytes], wanted: str, timeout: float) -> list[dict[str, Any]]:
    """The process's stderr lines, parsed as JSON, up to the one whose message is ``wanted``."""
    assert proc.stderr is not None
    sel = selectors.DefaultSelector()
    sel.register(proc.stderr, selectors.EVENT_READ)
    lines: list[dict[str, Any]] = []
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if not sel.select(timeout=0.5):
            continue
        raw = proc.stderr.readline()
        if not raw:
            break
        lines.append(json.loads(raw))  # every line is JSON, uvicorn's own included
        if lines[-1]["message"] == wanted:
            return lines
    raise AssertionError(f"no {wanted!r} line in time; got {lines}")


def test_a_service_logs_its_extra_fields(tmp_path: Path) -> None:
    """The emulator's start-up line carries its ``extra`` fields, and uvicorn's lines are JSON too."""
    env = {
        **os.environ,
        "PYTHONPATH": str(ROOT),
        "ARTIFACTS_DIR": str(tmp_path),
        "PORT": str(_free_port()),
        "API_KEYS": "alpha,beta",
        "REDIS_URL": "",
        "LOG_LEVEL": "info",
    }
    proc = subprocess.Popen(
        [sys.executable, "-m", "services.emulator"], env=env, cwd=tmp_path, stderr=subprocess.PIPE
    )
    try:
        lines = _lines_until(proc, "emulator service up", timeout=90)
        up = lines[-1]
        assert (up["models"], up["api_keys"], up["persistence"]) == ([], 2, "off")
        running = f"Uvicorn running on http://127.0.0.1:{env['PORT']} (Press CTRL+C to quit)"
        assert _lines_until(proc, running, timeout=30)[-1]["logger"] == "uvicorn.error"
    finally:
        proc.terminate()
        proc.wait(15)
