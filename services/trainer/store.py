"""Trainings in Redis (``services.common.jobs.JobStore``): a delivery runs
``services.trainer.execution.perform``; a training's spec is the checked upload and its options, its
progress the phase, percent and detail, its history the loss curve (``[epoch, loss]`` points), and its
result the artifact it made (``TrainingResult``).

What is stored, and how every change of a training's state is one transaction, is told in
``services.common.jobs``.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from typing import Any

from services.common.jobs import FINAL
from services.common.jobs import JobStore as BaseStore

PERFORM = "services.trainer.execution.perform"


class TrainingStore(BaseStore):
    """The trainings of one deployment (one prefix and one RQ queue), for the API and for workers."""

    perform = PERFORM
    noun = "training"

    def summary(self, spec: dict[str, Any]) -> dict[str, Any]:
        return {"model": spec.get("model")}

    def end_event(self, body: dict[str, Any]) -> dict[str, Any]:
        phase = {"succeeded": "done"}.get(body["status"], body["status"])
        out = {"status": body["status"], "phase": phase, "reason": body["reason"], "model": body.get("model")}
        if body["status"] == "succeeded":
            out["result"] = {k: v for k, v in body.items() if k not in ("id", "status", "reason")}
        return out

    def progress(self, job_id: str, attempt: int, p: dict[str, Any], losses: Sequence[Any] = ()) -> None:
        """Record the phase, percent and detail, and new points of the loss curve (``[epoch, loss]``,
        also in the ``progress`` event as ``losses``)."""
        self.record_progress(job_id, attempt, p, losses, {"losses": list(losses)})

    def active(self, owner: str, model: str | None = None, but: str | None = None) -> int:
        """The owner's trainings that are queued or running (of ``model`` only, other than ``but``)."""
        return sum(
            1
            for rec in self.jobs_of(owner, self.settings.max_list)
            if rec["status"] not in FINAL
            and rec["id"] != but
            and (model is None or json.loads(rec["spec"]).get("model") == model)
        )
