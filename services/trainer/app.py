"""``create_app(settings)``: the trainer API as a FastAPI app, plus health, readiness and metrics.

The API checks uploaded models, queues their trainings and reads their progress from Redis; training
workers (``worker.py``) run them. It never imports PyTorch. When Redis is down it still starts: calls
that need Redis answer 503 with a message, and ``/readyz`` says why it is not ready
(``services.common.queue_app``). Uploads go to ``WORK_DIR`` (shared with the workers), trained
emulators into ``ARTIFACTS_DIR``, where the emulator and controller services find them.
"""

from __future__ import annotations

import logging
import os
import threading

from fastapi import FastAPI

from services.common.queue_app import connect, queue_app
from services.trainer import models as stored_models
from services.trainer.metrics import Metrics
from services.trainer.routes import models, trainings
from services.trainer.settings import Settings
from services.trainer.store import TrainingStore

log = logging.getLogger(__name__)


def create_app(settings: Settings | None = None) -> FastAPI:
    """The app for these settings. Connecting to Redis is lazy, so this works while Redis is down."""
    settings = settings or Settings()
    store = TrainingStore(connect(settings), settings)

    def ready() -> tuple[dict[str, object], tuple[str, str] | None]:
        # /readyz answers anybody: the folders are named by their settings, their paths go to the log
        for name, folder in (("DATA_DIR", settings.data_dir), ("WORK_DIR", settings.uploads())):
            try:
                folder.mkdir(parents=True, exist_ok=True)
                writable = os.access(folder, os.W_OK)
                why = "" if writable else "no write permission"
            except OSError as exc:
                writable, why = False, exc.strerror or type(exc).__name__
            if not writable:
                log.warning("readyz: a folder cannot be written", extra={"folder": str(folder), "error": why})
                return {}, ("not writable", f"cannot write to {name}'s folder ({why})")
        return {}, None

    app = queue_app(
        settings,
        title="NeuroAnimator trainer service",
        store=store,
        metrics=Metrics(store),
        routers=(trainings.router, models.router),
        submit_path="/trainings",
        ready=ready,
        not_ready="the data directory or the uploads folder cannot be written",
        per_path_limits=[(r"/trainings", settings.max_upload_bytes)],
    )
    # the uploads being checked at once (each in a sandbox process): a bound, not a queue of threads
    app.state.checks = threading.BoundedSemaphore(settings.max_validations)
    stray = stored_models.uploaded(settings.artifacts_dir)
    if stray:  # uploads of an older version, beside the committed defaults: still served, not managed
        log.warning(
            "uploaded models among the committed defaults: move them into DATA_DIR to manage them here",
            extra={"models": stray, "from": str(settings.artifacts_dir), "to": str(settings.data_dir)},
        )
    return app
