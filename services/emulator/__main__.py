"""``python -m services.emulator``: serve the emulator on HOST:PORT with uvicorn (settings from env)."""

from __future__ import annotations

import logging

import uvicorn

from services.emulator.app import create_app
from services.emulator.settings import Settings


def main() -> None:
    settings = Settings()
    logging.basicConfig(
        level=settings.log_level.upper(),
        format='{"time":"%(asctime)s","level":"%(levelname)s","logger":"%(name)s","message":"%(message)s"}',
    )
    uvicorn.run(create_app(settings), host=settings.host, port=settings.port, log_level=settings.log_level)


if __name__ == "__main__":
    main()
