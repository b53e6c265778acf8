"""``create_app(settings)``: the controller API as a FastAPI app, plus health, readiness and metrics.

The API validates and queues jobs (control synthesis at ``/jobs``, policy training at ``/policies``
and ``/policy-jobs``) and reads their progress from Redis; it runs none itself (see ``worker.py``). It never imports PyTorch. When Redis is down it still starts: calls that need Redis
answer 503 with a message, and ``/readyz`` says why it is not ready (``services.common.queue_app``).
"""

from __future__ import annotations

import logging

from fastapi import FastAPI

from services.common import tenancy
from services.common.queue_app import connect, queue_app
from services.controller.metrics import Metrics
from services.controller.routes import events, jobs, policies, policy_jobs, tasks
from services.controller.settings import Settings
from services.controller.store import JobStore

log = logging.getLogger(__name__)


def create_app(settings: Settings | None = None) -> FastAPI:
    """The app for these settings. Connecting to Redis is lazy, so this works while Redis is down."""
    settings = settings or Settings()
    store = JobStore(connect(settings), settings)

    def ready() -> tuple[dict[str, object], tuple[str, str] | None]:
        # an open endpoint: the models everybody sees (uploaded ones only once published)
        models = tenancy.public_models(settings.roots())
        if not models:  # the folder is named by its setting: its path goes to the log, not to anybody
            log.warning("readyz: no trained models", extra={"registries": str(settings.roots())})
            return {}, (
                "no artifacts",
                "no trained models in ARTIFACTS_DIR (train one: neuro train pendulum-active)",
            )
        return {"models": models}, None

    return queue_app(
        settings,
        title="NeuroAnimator controller service",
        store=store,
        metrics=Metrics(store),
        routers=(jobs.router, events.router, tasks.router, policies.router, policy_jobs.router),
        submit_path="/jobs",
        ready=ready,
        not_ready="there is no trained model",
    )
