"""The settings every service has, read from the environment (upper-case names: ``HOST=0.0.0.0``).

A service's ``Settings`` subclasses ``ServiceSettings`` (a static server) or ``ApiSettings`` (an API
with keys and CORS), adds its own knobs and gives its default port: ``port: Port = 8001``.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

from pydantic import Field, field_validator
from pydantic_settings import BaseSettings, SettingsConfigDict

from neuroanimator.artifacts import registry

Port = Annotated[int, Field(ge=1, le=65535, description="the TCP port to listen on")]


class ServiceSettings(BaseSettings):
    """Where a service listens and how much it logs; environment variables have the upper-case names."""

    model_config = SettingsConfigDict(env_prefix="", case_sensitive=False, extra="ignore")

    host: str = Field("127.0.0.1", description="the address to listen on (0.0.0.0: every interface)")
    port: Port
    log_level: str = Field("info", description="debug, info, warning or error")
    max_body_bytes: int = Field(
        65_536,
        ge=1024,
        description="the largest request body: a larger one is answered 413 before it is read or parsed",
    )
    ws_max_message_bytes: int = Field(
        1024 * 1024,
        ge=1024,
        description="the largest websocket message a client may send (uvicorn closes the connection "
        "with 1009 beyond)",
    )


class ApiSettings(ServiceSettings):
    """A service's settings plus who may call it: API keys, and the origins a browser may call from."""

    api_keys: str = Field(
        "", description="comma-separated API keys; empty: no auth (every endpoint but ops then needs one)"
    )
    operator_keys: str = Field(
        "",
        description="comma-separated API keys with an operator's rights (keys too, beside API_KEYS): they see "
        "every uploaded model, and publish and delete them",
    )
    api_key_secret: str = Field(
        "",
        description="the server secret of API key ids (HMAC-SHA256): the same on every replica and across "
        "restarts, so that restored sessions and jobs keep their owners; empty: a random one at each start",
    )
    cors_origins: str = Field(
        "",
        description="comma-separated origins a browser may call from (e.g. the dashboard's "
        "http://127.0.0.1:8080), or * for any; empty: no CORS headers",
    )

    def cors_list(self) -> list[str]:
        """``CORS_ORIGINS`` as a list, blanks dropped: ``"a, b,"`` -> ``["a", "b"]``."""
        return [o.strip() for o in self.cors_origins.split(",") if o.strip()]


class RegistrySettings(BaseSettings):
    """Where a service finds trained emulators: the committed defaults (read-only) under a data directory
    of uploads and trainings (``registry.Roots``)."""

    model_config = SettingsConfigDict(env_prefix="", case_sensitive=False, extra="ignore")

    artifacts_dir: Path = Field(
        registry.DEFAULTS_DIR,
        description="the committed default emulators (the catalog's), read-only: nothing is written there",
    )
    data_dir: Path = Field(
        default_factory=registry.default_data_dir,
        description="uploads, trainings and their emulators (default $NEUROANIMATOR_DATA_DIR, else "
        "$XDG_DATA_HOME/neuroanimator, else ~/.local/share/neuroanimator); a model here takes precedence "
        "over a committed one of the same name",
    )

    @field_validator("artifacts_dir", "data_dir")
    @classmethod
    def _absolute_dir(cls, path: Path) -> Path:
        """Made absolute where the settings are read: a worker may run in another folder."""
        return path.expanduser().absolute()

    def roots(self) -> registry.Roots:
        """The registries this service reads: the data directory first, then the committed defaults."""
        return registry.Roots(self.data_dir, self.artifacts_dir)
