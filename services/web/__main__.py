"""``python -m services.web``: serve the dashboard on HOST:PORT (default 127.0.0.1:8080)."""

from __future__ import annotations

import logging

import uvicorn

from services.web.app import create_app
from services.web.settings import Settings


def main() -> None:
    settings = Settings()
    logging.basicConfig(
        level=settings.log_level.upper(),
        format='{"time":"%(asctime)s","level":"%(levelname)s","logger":"%(name)s","message":"%(message)s"}',
    )
    uvicorn.run(create_app(settings), host=settings.host, port=settings.port, log_level=settings.log_level)


if __name__ == "__main__":
    main()
