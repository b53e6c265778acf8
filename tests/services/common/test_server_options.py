"""``serve``: what every service's entry point hands uvicorn (websocket messages bounded too)."""

from __future__ import annotations

from typing import Any

import pytest
import uvicorn

from services.common import server
from services.common.settings import ServiceSettings


class _Settings(ServiceSettings):
    port: int = 9999


def test_serve_bounds_websocket_messages(monkeypatch: pytest.MonkeyPatch) -> None:
    got: dict[str, Any] = {}
    monkeypatch.setattr(uvicorn, "run", lambda app, **kw: got.update(kw, app=app))
    monkeypatch.setattr(server.logs, "setup", lambda *a, **k: None)
    settings = _Settings(ws_max_message_bytes=4096)

    async def app(scope: Any, receive: Any, send: Any) -> None:
        return None

    server.serve(lambda s: app, settings, ws_per_message_deflate=False)
    assert got["app"] is app and got["ws_max_size"] == 4096 and got["ws_per_message_deflate"] is False
    assert (got["host"], got["port"], got["log_config"]) == ("127.0.0.1", 9999, None)
