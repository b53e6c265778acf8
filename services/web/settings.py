"""Settings of the dashboard's static server, read from the environment."""

from __future__ import annotations

from pathlib import Path

from pydantic import Field

from services.common.settings import Port, RegistrySettings, ServiceSettings

ROOT = Path(__file__).resolve().parents[2]


class Settings(ServiceSettings, RegistrySettings):
    """``EMULATOR_URL``, ``CONTROLLER_URL`` and ``TRAINER_URL`` are what the *browser* calls: absolute
    URLs, or paths on this server's origin when a proxy serves everything from one place
    (``/api/emulator``)."""

    web_dist: Path = Field(ROOT / "web" / "dist", description="the built dashboard (npm run build)")
    emulator_url: str = Field(
        "http://127.0.0.1:8000", description="the emulator service, as the browser sees it"
    )
    controller_url: str = Field(
        "http://127.0.0.1:8001", description="the controller API, as the browser sees it"
    )
    trainer_url: str = Field(
        "http://127.0.0.1:8002", description="the trainer API, as the browser sees it (empty: none)"
    )
    api_keys: str = Field(
        "",
        description="the APIs' keys (API_KEYS, read here only to know whether keys are on): with keys on, "
        "this server, which takes no key, answers results only for models everybody sees",
    )
    port: Port = 8080
