"""``python -m services.trainer``: serve the trainer API on HOST:PORT (default 8002) with uvicorn.

Training workers run apart: ``python -m services.trainer.worker``. The ``neuro`` command
(``neuroanimator.cli``) trains on the command line without either.
"""

from __future__ import annotations

from services.common.server import serve
from services.trainer.app import create_app
from services.trainer.settings import Settings


def main() -> None:
    serve(create_app, Settings())


if __name__ == "__main__":
    main()
