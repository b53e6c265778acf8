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
    # No per-message deflate: state frames are a few dozen bytes, and compressing each one costs more
    # CPU than it saves bandwidth (the step rate of a 2-core server is bound by per-message work).
    uvicorn.run(
        create_app(settings),
        host=settings.host,
        port=settings.port,
        log_level=settings.log_level,
        ws_per_message_deflate=False,
    )


if __name__ == "__main__":
    main()
