"""``python -m services.web``: serve the dashboard on HOST:PORT (default 127.0.0.1:8080)."""

from __future__ import annotations

from services.common.server import serve
from services.web.app import create_app
from services.web.settings import Settings


def main() -> None:
    serve(create_app, Settings())


if __name__ == "__main__":
    main()
