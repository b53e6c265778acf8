"""Settings of the dashboard's static server, read from the environment."""

from __future__ import annotations

from pathlib import Path

from pydantic import Field
from pydantic_settings import BaseSettings, SettingsConfigDict

ROOT = Path(__file__).resolve().parents[2]


class Settings(BaseSettings):
    """``EMULATOR_URL`` and ``CONTROLLER_URL`` are what the *browser* calls: absolute URLs, or paths
    on this server's origin when a proxy serves everything from one place (``/api/emulator``)."""

    model_config = SettingsConfigDict(env_prefix="", case_sensitive=False, extra="ignore")

    web_dist: Path = Field(ROOT / "web" / "dist", description="the built dashboard (npm run build)")
    artifacts_dir: Path = Field(
        Path("artifacts"), description="where eval.json and bench.json of each model are read from"
    )
    emulator_url: str = Field(
        "http://127.0.0.1:8000", description="the emulator service, as the browser sees it"
    )
    controller_url: str = Field(
        "http://127.0.0.1:8001", description="the controller API, as the browser sees it"
    )
    host: str = "127.0.0.1"
    port: int = Field(8080, ge=1, le=65535)
    log_level: str = "info"
