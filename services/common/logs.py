"""Structured logs: one JSON object per line, with the ``extra={...}`` fields of each call.

``log.info("job queued", extra={"job": "j-1", "depth": 3})`` writes the line
``{"time": "2025-01-01T12:00:00", "level": "INFO", "logger": "...", "message": "job queued", "job": "j-1",
"depth": 3}``.
"""

from __future__ import annotations

import json
import logging
import re
import sys
from typing import Any

# Attributes every LogRecord has; anything else on a record came from ``extra=``.
_STANDARD = set(vars(logging.makeLogRecord({}))) | {"message", "asctime", "taskName", "color_message"}


SECRET_NAMES = ("api_key", "apikey", "access_token", "token")


def _spelled(name: str) -> str:
    """A pattern of ``name`` with any of its characters percent-encoded (``api%5Fkey`` is ``api_key``
    to the query parser, which takes the key from it all the same)."""
    return "".join(f"(?:{re.escape(c)}|%{ord(c):02x})" for c in name)


SECRET_PARAM = re.compile(
    "((?:" + "|".join(_spelled(n) for n in SECRET_NAMES) + r")=)[^&\s\"']*", re.IGNORECASE
)
"""A query parameter that carries a secret (browsers send API keys as ``?api_key=`` on websockets and
event streams), as uvicorn's access log would write it with the request's path: the raw query string,
where the name may be percent-encoded."""


def redact(text: str) -> str:
    """``text`` with the value of every secret query parameter replaced by ``***``."""
    return SECRET_PARAM.sub(r"\1***", text)


class RedactSecrets(logging.Filter):
    """Blanks secret query parameters in every record's message and arguments (uvicorn's access and
    websocket lines carry the path with its query string)."""

    def filter(self, record: logging.LogRecord) -> bool:
        if isinstance(record.msg, str) and "=" in record.msg:
            record.msg = redact(record.msg)
        if isinstance(record.args, tuple):
            record.args = tuple(redact(a) if isinstance(a, str) and "=" in a else a for a in record.args)
        elif isinstance(record.args, dict):
            record.args = {
                k: redact(v) if isinstance(v, str) and "=" in v else v for k, v in record.args.items()
            }
        return True


class JsonFormatter(logging.Formatter):
    """A record as one JSON line: time, level, logger, message, every ``extra`` field, the traceback."""

    def format(self, record: logging.LogRecord) -> str:
        out: dict[str, Any] = {
            "time": self.formatTime(record, "%Y-%m-%dT%H:%M:%S"),
            "level": record.levelname,
            "logger": record.name,
            "message": record.getMessage(),
        }
        for key, value in vars(record).items():
            if key not in _STANDARD and not key.startswith("_"):
                out[key] = value
        if record.exc_info:
            out["exception"] = self.formatException(record.exc_info)
        return json.dumps(out, default=str)


def setup(level: str, formatter: logging.Formatter | None = None) -> None:
    """One handler on stderr for the root logger (and so for uvicorn's and RQ's loggers too), writing
    JSON lines unless another ``formatter`` is given (a terminal's plain lines), with secret query
    parameters redacted (``RedactSecrets``)."""
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(formatter or JsonFormatter())
    handler.addFilter(RedactSecrets())  # no API key reaches a log line
    root = logging.getLogger()
    root.handlers[:] = [handler]
    root.setLevel(level.upper())
