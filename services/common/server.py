"""``serve(create_app, settings)``: what each service's ``python -m`` entry point does."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, TypeVar

import uvicorn
from starlette.types import ASGIApp

from services.common import logs
from services.common.settings import ServiceSettings

S = TypeVar("S", bound=ServiceSettings)


def serve(create_app: Callable[[S], ASGIApp], settings: S, **uvicorn_options: Any) -> None:
    """Log JSON lines at ``LOG_LEVEL``, build the app for ``settings`` and serve it on HOST:PORT.

    ``uvicorn_options`` go to ``uvicorn.run`` (e.g. ``ws_per_message_deflate=False``).
    """
    logs.setup(settings.log_level)
    uvicorn.run(
        create_app(settings),
        host=settings.host,
        port=settings.port,
        log_level=settings.log_level,
        log_config=None,  # uvicorn's own logging config would replace the JSON handler set up above
        ws_max_size=settings.ws_max_message_bytes,
        **uvicorn_options,
    )
