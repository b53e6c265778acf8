"""``python -m services.controller``: serve the controller API on HOST:PORT (default 8001) with uvicorn."""

from __future__ import annotations

from services.common.server import serve
from services.controller.app import create_app
from services.controller.settings import Settings


def main() -> None:
    serve(create_app, Settings())


if __name__ == "__main__":
    main()
