"""``python -m services.controller``: serve the controller API on HOST:PORT (default 8001) with uvicorn."""

from __future__ import annotations

import uvicorn

from services.controller import logs
from services.controller.app import create_app
from services.controller.settings import Settings


def main() -> None:
    settings = Settings()
    logs.setup(settings.log_level)
    uvicorn.run(
        create_app(settings),
        host=settings.host,
        port=settings.port,
        log_level=settings.log_level,
        log_config=None,  # keep the JSON log handler set up above
    )


if __name__ == "__main__":
    main()
