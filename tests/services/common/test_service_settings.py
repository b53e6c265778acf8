"""The settings every service shares: HOST, PORT (each service its own default), LOG_LEVEL, and for the
APIs API_KEYS and CORS_ORIGINS, all from the environment."""

from __future__ import annotations

import pydantic
import pytest

from services.common.settings import ApiSettings, ServiceSettings
from services.controller.settings import Settings as ControllerSettings
from services.emulator.settings import Settings as EmulatorSettings
from services.web.settings import Settings as WebSettings

SHARED = ("HOST", "PORT", "LOG_LEVEL", "API_KEYS", "CORS_ORIGINS")
SERVICES: list[tuple[type[ServiceSettings], int]] = [
    (EmulatorSettings, 8000),
    (ControllerSettings, 8001),
    (WebSettings, 8080),
]


@pytest.fixture(autouse=True)
def _clean_environment(monkeypatch: pytest.MonkeyPatch) -> None:
    for name in SHARED:
        monkeypatch.delenv(name, raising=False)


@pytest.mark.parametrize(("settings", "port"), SERVICES)
def test_defaults_and_environment(
    settings: type[ServiceSettings], port: int, monkeypatch: pytest.MonkeyPatch
) -> None:
    s = settings()
    assert (s.host, s.port, s.log_level) == ("127.0.0.1", port, "info")
    monkeypatch.setenv("HOST", "0.0.0.0")
    monkeypatch.setenv("PORT", "9123")
    monkeypatch.setenv("LOG_LEVEL", "warning")
    s = settings()
    assert (s.host, s.port, s.log_level) == ("0.0.0.0", 9123, "warning")
    monkeypatch.setenv("PORT", "70000")
    with pytest.raises(pydantic.ValidationError, match="port"):
        settings()


@pytest.mark.parametrize("settings", [EmulatorSettings, ControllerSettings])
def test_api_settings(settings: type[ApiSettings], monkeypatch: pytest.MonkeyPatch) -> None:
    assert (settings().api_keys, settings().cors_list()) == ("", [])
    monkeypatch.setenv("API_KEYS", "alpha,beta")
    monkeypatch.setenv("CORS_ORIGINS", " http://localhost:5173, http://x ,")
    s = settings()
    assert s.api_keys == "alpha,beta"
    assert s.cors_list() == ["http://localhost:5173", "http://x"]
