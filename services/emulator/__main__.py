"""``python -m services.emulator``: serve the emulator on HOST:PORT with uvicorn (settings from env)."""

from __future__ import annotations

from services.common.server import serve
from services.emulator.app import create_app
from services.emulator.settings import Settings


def main() -> None:
    # No per-message deflate: state frames are a few dozen bytes, and compressing each one costs more
    # CPU than it saves bandwidth (the step rate of a 2-core server is bound by per-message work).
    serve(create_app, Settings(), ws_per_message_deflate=False)


if __name__ == "__main__":
    main()
