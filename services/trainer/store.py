"""Trainings in Redis (``services.common.jobs.JobStore``): a delivery runs
``services.trainer.execution.perform``; a training's spec is the checked upload and its options, its
progress the phase, percent and detail, its history the loss curve (``[epoch, loss]`` points), and its
result the artifact it made (``TrainingResult``).

What is stored, and how every change of a training's state is one transaction, is told in
``services.common.jobs``.
"""

from __future__ import annotations

import time
from collections.abc import Mapping, Sequence
from typing import Any

import redis
from pydantic import BaseModel

from neuroanimator.contracts.trainer import TrainingResult
from services.common.jobs import FINAL, JobRecord
from services.common.jobs import JobStore as BaseStore
from services.trainer import leftovers
from services.trainer.settings import Settings
from services.trainer.spec import LossPair, TrainingEnd, TrainingProgress, TrainingSpec, stored_order

PERFORM = "services.trainer.execution.perform"
RESERVATION_GRACE_S = 900.0  # an upload being received and checked holds its place this long at most

# KEYS[1]: the owner's places (a sorted set: training id -> when it was taken); ARGV: id, now, limit.
# 1 when the id holds a place (taken now, or before), 0 when every place is taken.
_RESERVE = """
if redis.call('ZSCORE', KEYS[1], ARGV[1]) then return 1 end
if redis.call('ZCARD', KEYS[1]) >= tonumber(ARGV[3]) then return 0 end
redis.call('ZADD', KEYS[1], ARGV[2], ARGV[1])
return 1
"""


class TrainingStore(BaseStore):
    """The trainings of one deployment (one prefix and one RQ queue), for the API and for workers."""

    perform = PERFORM
    noun = "training"

    def __init__(self, conn: redis.Redis, settings: Any) -> None:
        super().__init__(conn, settings)
        self._reserve = conn.register_script(_RESERVE)

    # ------------------------------------------------------------ an owner's places
    def _places(self, owner: str) -> str:
        return f"{self.keys.prefix}:places:{owner}"

    def reserve(self, owner: str, job_id: str, limit: int) -> tuple[bool, int]:
        """Take one of the owner's ``limit`` places for a training, atomically (an upload takes it before
        it is received and checked, so concurrent uploads cannot all pass the limit): (taken, places
        held). A place is held until the training ends (``settle`` gives it back then) or the upload is
        refused (``unreserve``)."""
        self.settle(owner)
        taken = bool(self._reserve(keys=[self._places(owner)], args=[job_id, time.time(), limit]))
        return taken, int(self.r.zcard(self._places(owner)))

    def unreserve(self, owner: str, job_id: str) -> None:
        self.r.zrem(self._places(owner), job_id)

    def settle(self, owner: str) -> None:
        """Give back the places of trainings that ended, and of uploads that never became one."""
        key = self._places(owner)
        now = time.time()
        held: list[tuple[Any, float]] = self.r.zrange(key, 0, -1, withscores=True)  # type: ignore[assignment]
        for raw, taken in held:
            job_id = raw.decode() if isinstance(raw, bytes) else str(raw)
            status = self.r.hget(self.keys.job(job_id), "status")
            status = status.decode() if isinstance(status, bytes) else status
            if (status is not None and status in FINAL) or (
                status is None and now - float(taken) > RESERVATION_GRACE_S
            ):
                self.r.zrem(key, job_id)

    def reap(self) -> list[str]:
        """Re-queue (or fail) trainings whose lease expired, then remove what dead trainings left on
        disk (``leftovers``)."""
        reaped = super().reap()
        if isinstance(self.settings, Settings):
            leftovers.reap(self.settings, self)
        return reaped

    def owner_lock(self, owner: str) -> Any:
        """A lock of the owner's (Redis, so across API processes) held while their stored models and
        bytes are counted and a name is claimed: concurrent uploads see each other's claims."""
        return self.r.lock(f"{self.keys.prefix}:lock:{owner}", timeout=30.0, blocking_timeout=15.0)

    def summary(self, spec: str) -> dict[str, str | None]:
        return {"model": TrainingSpec.model_validate_json(spec).model}

    def result_fields(self, result: BaseModel) -> Mapping[str, object]:
        return stored_order(result) if isinstance(result, TrainingResult) else result.model_dump()

    def end_event(
        self, rec: JobRecord, status: str, reason: str | None, result: BaseModel | None
    ) -> TrainingEnd:
        made = result if isinstance(result, TrainingResult) else None
        model = made.model if made is not None else TrainingSpec.model_validate_json(rec.spec).model
        return TrainingEnd(
            status=status,
            phase={"succeeded": "done"}.get(status, status),
            reason=reason,
            model=model,
            result=made if status == "succeeded" else None,
        )

    def progress(
        self, job_id: str, attempt: int, p: TrainingProgress, losses: Sequence[LossPair] = ()
    ) -> None:
        """Record the phase, percent and detail, and new points of the loss curve (``[epoch, loss]``,
        also in the ``progress`` event as ``losses``)."""
        self.record_progress(job_id, attempt, p.model_dump(), losses, {"losses": list(losses)})

    def active(self, owner: str, model: str | None = None, but: str | None = None) -> int:
        """The owner's trainings that are queued or running (of ``model`` only, other than ``but``)."""
        return sum(
            1
            for rec in self.jobs_of(owner, self.settings.max_list)
            if rec.status not in FINAL
            and rec.id != but
            and (model is None or TrainingSpec.model_validate_json(rec.spec).model == model)
        )
