"""Jobs on a Redis queue, as the controller and the trainer run them: records, progress, events,
results, leases and every change of a job's state (``JobStore``), and the settings they share.

RQ only *delivers* a job to a worker: each delivery is an RQ job ``<job id>-<n>`` that runs the
service's ``perform(job_id, n)`` (``JobStore.perform``) in a forked process. What a client sees is this
module's record of the job, under ``<REDIS_PREFIX>``:

    job:<id>       hash: owner, spec, status, times, attempt, delivery (n), rq_id, failures, worker, error
    progress:<id>  hash: the current attempt's last progress (each value JSON)
    history:<id>   list: the current attempt's curve (the controller's objective per iteration, the
                   trainer's validation loss per epoch)
    events:<id>    stream: ``status``, ``progress`` and one last ``end`` event (what SSE replays)
    result:<id>    the finished job's result (JSON)
    lease:<id>     the running attempt's lease, renewed by the job; gone: its worker died
    cancel:<id>    set by DELETE; yield:<id> set by a worker shutting down
    running        sorted set of running jobs (the reaper looks there for expired leases)
    workers        sorted set of worker names by their last heartbeat (Redis's clock): the live workers
    owner:<key id> sorted set of a caller's jobs; idem:<key id>:<hash> the job of an idempotency key
    stats          hash: counts and histogram buckets of finished jobs (``/metrics``)

Every change of state is one optimistic transaction on the job's record (WATCH, check, MULTI): it
starts a run only if this delivery is still the job's current one, and ends, re-queues or cancels a
job only once. Re-queueing enqueues the next delivery in the same transaction, so a job is never
marked queued without being on the queue. A job may thus run twice (at-least-once delivery: its
worker seemed dead but was not); the second finish is refused and a superseded run stops by itself.

A service subclasses ``JobStore``: the function its deliveries run, what of a job's spec its result
repeats, and what its ``end`` event, statistics and partial results (of a job given up) hold.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import logging
import math
import time
import uuid
from collections.abc import Callable, Iterable, Mapping
from typing import Any, ClassVar, Literal, TypeVar

import redis
from pydantic import BaseModel, ConfigDict, Field, ValidationInfo, field_validator
from redis.client import Pipeline
from rq import Queue
from rq.exceptions import InvalidJobOperation, NoSuchJobError
from rq.job import Job
from rq.serializers import JSONSerializer

from neuroanimator.contracts.controller import StatusEvent
from services.common.settings import ApiSettings, RegistrySettings

log = logging.getLogger(__name__)

FINAL = frozenset(("succeeded", "failed", "cancelled"))
MAX_EVENTS = 20_000  # a stream keeps about this many events (SSE replays what is left)
MAX_OWNER_JOBS = 1000  # a caller's job list keeps the newest this many ids
DURATION_BUCKETS = (0.5, 1.0, 2.0, 5.0, 10.0, 20.0, 30.0, 60.0, 120.0, 300.0, 600.0, 1800.0, 3600.0)
T = TypeVar("T")
# Worker heartbeats on Redis's own clock (so machines' clocks need not agree): seen marks a worker alive
# now and drops the ones silent longer than ARGV[2]; count counts the ones heard within ARGV[1] seconds.
_WORKER_SEEN = """
local t = redis.call('TIME')
local now = tonumber(t[1]) + tonumber(t[2]) / 1000000
redis.call('ZADD', KEYS[1], now, ARGV[1])
redis.call('ZREMRANGEBYSCORE', KEYS[1], '-inf', now - tonumber(ARGV[2]))
return 1
"""
_WORKER_COUNT = """
local t = redis.call('TIME')
local now = tonumber(t[1]) + tonumber(t[2]) / 1000000
return redis.call('ZCOUNT', KEYS[1], now - tonumber(ARGV[1]), '+inf')
"""


class QueueSettings(ApiSettings, RegistrySettings):
    """The knobs of a service with a job queue and its workers (the controller's, the trainer's);
    environment variables have the upper-case names. A service gives its own prefix, queue and port."""

    redis_url: str = Field("redis://127.0.0.1:6379/0", description="the Redis that holds the queue and jobs")
    redis_prefix: str = Field(min_length=1, description="prefix of the service's own Redis keys")
    queue_name: str = Field(
        pattern=r"^[A-Za-z0-9_.:-]+$",
        description="the RQ queue (RQ's keys are rq:queue:<name>, rq:wip:<name>, ...)",
    )
    redis_timeout_s: float = Field(2.0, gt=0.0, description="connect and command timeout of the API's Redis")
    max_queue: int = Field(
        100, ge=1, description="queued (not yet running) jobs; beyond, a submission is 503"
    )
    job_timeout_s: float = Field(600.0, gt=0.0, description="time limit of one job: it then stops and fails")
    job_timeout_grace_s: float = Field(
        30.0, gt=0.0, description="past the limit by this much, the job's process is killed (hard limit)"
    )
    job_retries: int = Field(
        2, ge=0, le=20, description="re-runs of a job whose process crashed, raised or was abandoned"
    )
    result_ttl_s: int = Field(
        86_400, ge=1, description="a finished job (status, result, events) is kept this long"
    )
    queued_ttl_s: int = Field(7 * 86_400, ge=1, description="an unfinished job's records expire after this")
    max_list: int = Field(200, ge=1, description="most jobs listed at once")
    sse_keepalive_s: float = Field(15.0, gt=0.0, description="an SSE comment is sent when idle this long")
    lease_ttl_s: float = Field(
        15.0,
        gt=0.0,
        description="a running job renews its lease this often ×3; an expired lease means a dead worker",
    )
    reap_interval_s: float = Field(
        5.0,
        gt=0.0,
        description="how often an idle worker looks for jobs whose lease expired and re-queues them",
    )

    def heartbeat_s(self) -> int:
        """How often a worker reports itself alive: RQ's dequeue timeout while idle (the reap interval)
        and its job monitoring interval while a job runs (the lease's time to live), whole seconds."""
        return max(1, min(30, math.ceil(self.lease_ttl_s)), math.ceil(self.reap_interval_s))

    def worker_alive_s(self) -> float:
        """A worker not heard from for this long is counted gone (killed, or cut off from Redis)."""
        return 3.0 * self.heartbeat_s()


JobState = Literal["queued", "running", "succeeded", "failed", "cancelled"]


class JobRecord(BaseModel):
    """A job's record: its ``job:<id>`` hash (every value text there; empty: not set), validated once
    when read, with the current attempt's progress and history when read by ``JobStore.record``."""

    model_config = ConfigDict(extra="ignore")
    id: str
    owner: str
    spec: str = Field(description="the job's spec as JSON (each service reads it with its own type)")
    spec_hash: str = ""
    status: JobState
    created_at: float
    started_at: float | None = None
    ended_at: float | None = None
    attempt: int = 0
    delivery: int = 1
    rq_id: str = ""
    failures: int = 0
    worker: str | None = None
    error: str | None = None
    idempotency_key: str | None = None
    # free-form: what the service's job reported last (each value a JSON document of its own)
    progress: dict[str, Any] = Field(default_factory=dict)
    history: list[Any] = Field(
        default_factory=list, description="the attempt's curve, one JSON value a point"
    )

    @field_validator(
        "started_at", "ended_at", "worker", "error", "idempotency_key", "attempt", "failures", mode="before"
    )
    @classmethod
    def _unset(cls, value: object, info: ValidationInfo) -> object:
        if value == "":  # the hash keeps an unset field as the empty string
            return 0 if info.field_name in ("attempt", "failures") else None
        return value

    @classmethod
    def of(cls, fields: Mapping[str, str]) -> JobRecord | None:
        """The record of a ``job:<id>`` hash read as text; None when there is none (expired)."""
        return cls.model_validate(fields) if fields else None


class JobEnd(BaseModel):
    """The data of a job's ``end`` event, at the least (a service's own says more)."""

    status: str
    reason: str | None


class QueueFull(Exception):
    """The queue holds ``MAX_QUEUE`` jobs already (``limit``; ``depth`` were waiting)."""

    def __init__(self, message: str, limit: int, depth: int) -> None:
        super().__init__(message)
        self.limit = limit
        self.depth = depth


class IdempotencyConflict(Exception):
    """An idempotency key came again with a different job."""


def rq_id(job_id: str, delivery: int) -> str:
    return f"{job_id}-{delivery}"


def clean(value: Any) -> Any:
    """``value`` as plain JSON: numpy values become Python ones, NaN and ±inf become None."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, (bool, int, str)) or value is None:
        return value
    if isinstance(value, dict):
        return {str(k): clean(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [clean(v) for v in value]
    if hasattr(value, "tolist"):  # numpy arrays and scalars
        return clean(value.tolist())
    return str(value)


def dumps(value: object) -> str:
    return json.dumps(clean(value), separators=(",", ":"), allow_nan=False)


def text_of(value: Any) -> str:
    """A Redis reply (bytes; str from a decoding client) as text."""
    return value.decode() if isinstance(value, bytes) else str(value)


def texts(raw: Any) -> dict[str, str]:
    """A Redis hash reply as text keys and values."""
    return {text_of(k): text_of(v) for k, v in dict(raw).items()}


def observe(pipe: Pipeline, key: str, name: str, value: float, buckets: tuple[float, ...]) -> None:
    """A Prometheus histogram kept in a Redis hash: cumulative bucket counts, sum and count."""
    for le in buckets:
        if value <= le:
            pipe.hincrby(key, f"{name}_bucket:{le:g}", 1)
    pipe.hincrby(key, f"{name}_bucket:+Inf", 1)
    pipe.hincrbyfloat(key, f"{name}_sum", value)
    pipe.hincrby(key, f"{name}_count", 1)


class Keys:
    """The Redis key names under one prefix."""

    def __init__(self, prefix: str) -> None:
        self.prefix = prefix
        self.running = f"{prefix}:running"
        self.stats = f"{prefix}:stats"
        self.workers = f"{prefix}:workers"

    def job(self, job_id: str) -> str:
        return f"{self.prefix}:job:{job_id}"

    def progress(self, job_id: str) -> str:
        return f"{self.prefix}:progress:{job_id}"

    def history(self, job_id: str) -> str:
        return f"{self.prefix}:history:{job_id}"

    def events(self, job_id: str) -> str:
        return f"{self.prefix}:events:{job_id}"

    def result(self, job_id: str) -> str:
        return f"{self.prefix}:result:{job_id}"

    def lease(self, job_id: str) -> str:
        return f"{self.prefix}:lease:{job_id}"

    def cancel(self, job_id: str) -> str:
        return f"{self.prefix}:cancel:{job_id}"

    def yield_(self, job_id: str) -> str:
        return f"{self.prefix}:yield:{job_id}"

    def owner(self, owner: str) -> str:
        return f"{self.prefix}:owner:{owner}"

    def idem(self, owner: str, key: str) -> str:
        return f"{self.prefix}:idem:{owner}:{hashlib.sha256(key.encode()).hexdigest()[:32]}"


class JobStore:
    """The jobs of one deployment (one prefix and one RQ queue), for the API and for workers."""

    perform: ClassVar[str] = ""
    """The function a delivery runs (``module.function``); a worker runs nothing else."""
    noun: ClassVar[str] = "job"
    """What a job is called in RQ's descriptions and the logs."""

    def __init__(self, conn: redis.Redis, settings: QueueSettings) -> None:
        self.r = conn
        self.settings = settings
        self.keys = Keys(settings.redis_prefix)
        # JSON, not RQ's default pickle: what is on the queue is data, never code to unpickle
        self.queue = Queue(settings.queue_name, connection=conn, serializer=JSONSerializer)
        self._seen = conn.register_script(_WORKER_SEEN)
        self._count = conn.register_script(_WORKER_COUNT)

    # ------------------------------------------------------------ what a service says of its jobs
    def summary(self, spec: str) -> dict[str, str | None]:
        """What of a job's spec (JSON) its result repeats (the controller: task, model, version)."""
        return {}

    def end_event(
        self, rec: JobRecord, status: str, reason: str | None, result: BaseModel | None
    ) -> BaseModel:
        """The ``end`` event of a job that ends with ``status``, ``reason`` and ``result``."""
        return JobEnd(status=status, reason=reason)

    def result_fields(self, result: BaseModel) -> Mapping[str, object]:
        """What of a run's result the stored result holds, in its order."""
        return result.model_dump()

    def observe_end(self, pipe: Pipeline, result: BaseModel | None) -> None:
        """Statistics of a finished job beyond its count, duration and turnaround."""

    def partial(self, progress: dict[str, str], history: list[Any]) -> BaseModel | None:
        """The result of a job given up or cancelled while it ran, from its progress (each value JSON)
        and history."""
        return None

    def time_limit_s(self) -> float:
        """How long a delivery may run before it stops itself (RQ kills its process
        ``JOB_TIMEOUT_GRACE_S`` later): ``JOB_TIMEOUT_S``; a service whose jobs have limits of their own
        gives the longest of them."""
        return self.settings.job_timeout_s

    # ------------------------------------------------------------ plumbing
    def _transition(self, job_id: str, change: Callable[[Pipeline, JobRecord | None], T]) -> T:
        """Run ``change(pipe, record)`` with the record WATCHed (None: there is none); it calls
        ``pipe.multi()`` before queueing its writes, which then commit only if nobody changed the record
        since it was read (else retry)."""
        key = self.keys.job(job_id)
        with self.r.pipeline() as pipe:
            while True:
                try:
                    pipe.watch(key)
                    out = change(pipe, JobRecord.of(texts(pipe.hgetall(key))))
                    if pipe.explicit_transaction:
                        pipe.execute()
                    else:
                        pipe.reset()
                    return out
                except redis.WatchError:
                    continue

    def _enqueue(self, pipe: Pipeline, job_id: str, delivery: int) -> None:
        """Queue delivery ``n`` of a job (inside the caller's transaction)."""
        s = self.settings
        self.queue.enqueue_call(
            func=self.perform,
            args=(job_id, delivery),
            job_id=rq_id(job_id, delivery),
            # the job stops itself at its time limit; RQ kills its process if it is still there after the grace
            timeout=math.ceil(self.time_limit_s() + s.job_timeout_grace_s),
            result_ttl=s.result_ttl_s,
            failure_ttl=s.result_ttl_s,
            description=f"{self.noun} {job_id} (delivery {delivery})",
            pipeline=pipe,
        )

    def _event(self, pipe: Pipeline, job_id: str, event: str, data: Mapping[str, object]) -> None:
        pipe.xadd(
            self.keys.events(job_id),
            {"event": event, "data": dumps(data)},
            maxlen=MAX_EVENTS,
            approximate=True,
        )

    def _final(
        self,
        pipe: Pipeline,
        job_id: str,
        rec: JobRecord,
        status: str,
        reason: str | None,
        result: BaseModel | None,
    ) -> None:
        """Queue the writes that end a job: status, result, ``end`` event, expiry and statistics. The
        stored result: the summary of the spec, the ``result``'s fields, then the id, status and reason."""
        k, ttl, now = self.keys, self.settings.result_ttl_s, time.time()
        fields = self.result_fields(result) if result is not None else {}
        body = {**self.summary(rec.spec), **fields, "id": job_id, "status": status, "reason": reason}
        pipe.hset(k.job(job_id), mapping={"status": status, "error": reason or "", "ended_at": repr(now)})
        pipe.set(k.result(job_id), dumps(body), ex=ttl)
        self._event(pipe, job_id, "end", self.end_event(rec, status, reason, result).model_dump())
        pipe.zrem(k.running, job_id)
        pipe.delete(k.lease(job_id), k.yield_(job_id))
        for key in (k.job(job_id), k.progress(job_id), k.history(job_id), k.events(job_id), k.cancel(job_id)):
            pipe.expire(key, ttl)
        pipe.hincrby(k.stats, f"finished:{status}", 1)
        if rec.started_at:
            observe(pipe, k.stats, "duration", now - rec.started_at, DURATION_BUCKETS)
        observe(pipe, k.stats, "turnaround", now - rec.created_at, DURATION_BUCKETS)
        self.observe_end(pipe, result)

    # ------------------------------------------------------------ API side
    def queue_depth(self) -> int:
        return int(self.queue.count)

    def submit_spec(
        self,
        spec_json: str,
        owner: str,
        idempotency_key: str | None = None,
        job_id: str | None = None,
        log_extra: Mapping[str, object] | None = None,
    ) -> tuple[str, str, bool]:
        """Queue a validated job (its spec as JSON); returns (id, status, created). A repeated idempotency
        key returns its job; raises ``QueueFull`` or ``IdempotencyConflict``. ``job_id``: an id made by
        the caller (``new_id``), e.g. to name what it stored for the job beforehand."""
        s, k = self.settings, self.keys
        spec_hash = hashlib.sha256(spec_json.encode()).hexdigest()[:32]
        idem = k.idem(owner, idempotency_key) if idempotency_key else None
        if idem and (found := self._idempotent(idem, spec_hash)):
            return (*found, False)
        depth = self.queue_depth()
        if depth >= s.max_queue:
            raise QueueFull(
                f"the queue is full: {depth} {self.noun}s wait (MAX_QUEUE={s.max_queue}); try again later",
                s.max_queue,
                depth,
            )
        job_id = job_id or new_id()
        keep = s.queued_ttl_s + s.result_ttl_s
        if idem and not self.r.set(idem, job_id, nx=True, ex=keep):
            if found := self._idempotent(idem, spec_hash):  # a concurrent request with the same key won
                return (*found, False)
            self.r.set(idem, job_id, ex=keep)
        now = time.time()
        rec: dict[Any, str] = {
            "id": job_id,
            "owner": owner,
            "spec": spec_json,
            "spec_hash": spec_hash,
            "status": "queued",
            "created_at": repr(now),
            "attempt": "0",
            "delivery": "1",
            "rq_id": rq_id(job_id, 1),
            "failures": "0",
            "idempotency_key": idempotency_key or "",
        }
        with self.r.pipeline() as pipe:  # one MULTI: the record exists exactly when its delivery is queued
            pipe.multi()  # explicit, as RQ's enqueue expects of a pipeline it is handed
            pipe.hset(k.job(job_id), mapping=rec)
            pipe.expire(k.job(job_id), s.queued_ttl_s)
            pipe.zadd(k.owner(owner), {job_id: now})
            self._event(pipe, job_id, "status", _status_event("queued", 1))
            pipe.expire(k.events(job_id), s.queued_ttl_s)
            self._enqueue(pipe, job_id, 1)
            pipe.execute()
        self.r.zremrangebyrank(k.owner(owner), 0, -(MAX_OWNER_JOBS + 1))
        log.info(f"{self.noun} queued", extra={"job": job_id, "owner": owner, **(log_extra or {})})
        return job_id, "queued", True

    def _idempotent(self, idem: str, spec_hash: str) -> tuple[str, str] | None:
        raw = self.r.get(idem)
        if raw is None:
            return None
        job_id = text_of(raw)
        status, saved_hash = self.r.hmget(self.keys.job(job_id), ["status", "spec_hash"])
        if status is None:
            return None  # the job expired: the key may make a new one
        if text_of(saved_hash) != spec_hash:
            raise IdempotencyConflict(
                f"idempotency_key was already used for {self.noun} {job_id} with a different request"
            )
        return job_id, text_of(status)

    def record(self, job_id: str, owner: str | None = None) -> JobRecord | None:
        """The job's record with its progress and history; None if absent or ``owner`` is not its owner."""
        k = self.keys
        with self.r.pipeline(transaction=False) as pipe:
            pipe.hgetall(k.job(job_id))
            pipe.hgetall(k.progress(job_id))
            pipe.lrange(k.history(job_id), 0, -1)
            rec_raw, prog_raw, hist = pipe.execute()
        rec = JobRecord.of(texts(rec_raw))
        if rec is None or (owner is not None and rec.owner != owner):
            return None
        rec.progress = {key: json.loads(v) for key, v in texts(prog_raw).items()}
        rec.history = [json.loads(v) for v in hist]
        return rec

    def result(self, job_id: str) -> str | None:
        """The finished job's result as stored (JSON), for the service to read with its own type."""
        raw = self.r.get(self.keys.result(job_id))
        return None if raw is None else text_of(raw)

    def jobs_of(self, owner: str, limit: int) -> list[JobRecord]:
        """The owner's newest jobs (expired ones are dropped from the list)."""
        ids = [text_of(i) for i in self.r.zrevrange(self.keys.owner(owner), 0, limit - 1)]
        out, gone = [], []
        for job_id in ids:
            rec = self.record(job_id)
            if rec is None:
                gone.append(job_id)
            else:
                out.append(rec)
        if gone:
            self.r.zrem(self.keys.owner(owner), *gone)
        return out

    def cancel(self, job_id: str) -> str:
        """Cancel a job: a queued one ends now; a running one is flagged and stops soon after.
        Returns its status after this call."""
        cancelled_delivery: list[str] = []

        def change(pipe: Pipeline, rec: JobRecord | None) -> str:
            if rec is None or rec.status in FINAL:
                return "" if rec is None else rec.status
            status = rec.status
            pipe.multi()
            pipe.set(self.keys.cancel(job_id), "1", ex=self.settings.queued_ttl_s)
            if status == "queued":
                self._final(
                    pipe, job_id, rec, "cancelled", "cancelled before it started", self.partial({}, [])
                )
                cancelled_delivery.append(rec.rq_id)
                return "cancelled"
            return status

        status = self._transition(job_id, change)
        for rid in cancelled_delivery:  # a worker that takes it anyway finds it ended and does nothing
            with contextlib.suppress(NoSuchJobError, InvalidJobOperation):
                Job.fetch(rid, connection=self.r, serializer=JSONSerializer).cancel()
        log.info(f"{self.noun} cancel requested", extra={"job": job_id, "status": status})
        return status

    def stats(self) -> dict[str, str]:
        return texts(self.r.hgetall(self.keys.stats))

    def worker_count(self) -> int:
        """Workers heard from within ``WORKER_ALIVE_S`` (a killed one drops out; a Redis that lost its
        data counts each worker again at its next heartbeat)."""
        return int(self._count(keys=[self.keys.workers], args=[self.settings.worker_alive_s()]))

    # ------------------------------------------------------------ worker side
    def worker_seen(self, name: str, pipe: Pipeline | None = None) -> None:
        """A worker's heartbeat (``JobWorker.heartbeat``)."""
        self._seen(keys=[self.keys.workers], args=[name, self.settings.worker_alive_s()], client=pipe)

    def worker_gone(self, name: str) -> None:
        """A worker that stopped cleanly."""
        self.r.zrem(self.keys.workers, name)

    def start(self, job_id: str, delivery: int, worker: str, pid: int) -> tuple[JobRecord | None, str]:
        """Mark delivery ``n`` running and take the lease; (record, "started"), or (None, why not)."""
        k, s = self.keys, self.settings

        def change(pipe: Pipeline, rec: JobRecord | None) -> tuple[JobRecord | None, str]:
            if rec is None:
                return None, "gone"
            if rec.status in FINAL:
                return None, f"already {rec.status}"
            if rec.rq_id != rq_id(job_id, delivery):
                return None, f"superseded by {rec.rq_id}"
            cancelled = pipe.exists(k.cancel(job_id))
            pipe.multi()
            if cancelled:
                self._final(
                    pipe, job_id, rec, "cancelled", "cancelled before it started", self.partial({}, [])
                )
                return None, "cancelled"
            attempt = rec.attempt + 1
            now = time.time()
            pipe.hset(
                k.job(job_id),
                mapping={
                    "status": "running",
                    "started_at": repr(now),
                    "attempt": str(attempt),
                    "worker": worker,
                    "pid": str(pid),
                },
            )
            pipe.delete(k.progress(job_id), k.history(job_id))  # a new attempt starts from scratch
            pipe.zadd(k.running, {job_id: now})
            pipe.set(k.lease(job_id), worker, px=int(s.lease_ttl_s * 1000))
            for key in (k.job(job_id), k.events(job_id)):  # a run may start late: keep the records
                pipe.expire(key, s.queued_ttl_s)
            self._event(pipe, job_id, "status", _status_event("running", attempt))
            return rec.model_copy(update={"attempt": attempt}), "started"

        return self._transition(job_id, change)

    def heartbeat(self, job_id: str, worker: str, renew: bool) -> tuple[bool, bool, str | None]:
        """Renew the lease (when ``renew``) and read (cancelled, yield requested, current rq id)."""
        k = self.keys
        with self.r.pipeline(transaction=False) as pipe:
            if renew:
                pipe.set(k.lease(job_id), worker, px=int(self.settings.lease_ttl_s * 1000))
            pipe.exists(k.cancel(job_id))
            pipe.exists(k.yield_(job_id))
            pipe.hget(k.job(job_id), "rq_id")
            out = pipe.execute()
        cancel, yld, current = out[-3:]
        return bool(cancel), bool(yld), None if current is None else text_of(current)

    def record_progress(
        self,
        job_id: str,
        attempt: int,
        p: Mapping[str, object],
        history: Iterable[object],
        event_extra: Mapping[str, object] | None = None,
    ) -> None:
        """Record progress: the progress hash, values appended to the history and a ``progress`` event
        (``p``, plus ``event_extra``: what the event carries but the progress hash does not keep). ``p``
        is the service's report, a JSON object of its own (each value kept as JSON in the hash)."""
        k = self.keys
        data = {**clean(p), "attempt": attempt}
        fields = {key: json.dumps(v) for key, v in data.items()}
        points = [json.dumps(clean(v)) for v in history]
        with self.r.pipeline(transaction=False) as pipe:
            pipe.hset(k.progress(job_id), mapping=fields)
            if points:
                pipe.rpush(k.history(job_id), *points)
            self._event(pipe, job_id, "progress", {**data, **clean(event_extra or {})})
            # so that a job nobody ever ends (every worker gone for good) leaves nothing forever
            for key in (k.progress(job_id), k.history(job_id)):
                pipe.expire(key, self.settings.queued_ttl_s)
            pipe.execute()

    def set_yield(self, job_id: str) -> None:
        self.r.set(self.keys.yield_(job_id), "1", ex=max(60, int(self.settings.job_timeout_s)))

    def end(
        self, job_id: str, delivery: int, status: str, reason: str | None, result: BaseModel | None = None
    ) -> bool:
        """End the job with its outcome (``result``: what the run made, if anything); False if it had
        already ended or was superseded."""

        def change(pipe: Pipeline, rec: JobRecord | None) -> bool:
            if rec is None or rec.status in FINAL or rec.rq_id != rq_id(job_id, delivery):
                return False
            pipe.multi()
            self._final(pipe, job_id, rec, status, reason, result)
            return True

        done = self._transition(job_id, change)
        log.info(f"{self.noun} ended", extra={"job": job_id, "status": status, "recorded": done})
        return done

    def requeue_or_fail(self, job_id: str, delivery: int, reason: str, count_failure: bool) -> str:
        """Put the job back on the queue as delivery n+1, or end it failed when this failure exceeds
        ``JOB_RETRIES`` (or cancelled when that was asked). Returns requeued | failed | cancelled | stale."""
        k, retries = self.keys, self.settings.job_retries

        def change(pipe: Pipeline, rec: JobRecord | None) -> str:
            if rec is None or rec.status in FINAL or rec.rq_id != rq_id(job_id, delivery):
                return "stale"
            failures = rec.failures + int(count_failure)
            cancelled = pipe.exists(k.cancel(job_id))
            progress = texts(pipe.hgetall(k.progress(job_id)))
            history = [json.loads(v) for v in pipe.lrange(k.history(job_id), 0, -1)]
            partial = self.partial(progress, history)
            pipe.multi()
            pipe.hset(k.job(job_id), "failures", str(failures))
            if cancelled:
                self._final(pipe, job_id, rec, "cancelled", f"cancelled ({reason})", partial)
                return "cancelled"
            if failures > retries:
                why = f"{reason}; gave up after {failures} failed runs (JOB_RETRIES={retries})"
                self._final(pipe, job_id, rec, "failed", why, partial)
                return "failed"
            nxt = delivery + 1
            pipe.hset(
                k.job(job_id),
                mapping={
                    "status": "queued",
                    "delivery": str(nxt),
                    "rq_id": rq_id(job_id, nxt),
                    "error": reason,
                    "worker": "",
                    "pid": "",
                },
            )
            pipe.zrem(k.running, job_id)
            pipe.delete(k.lease(job_id), k.yield_(job_id))
            pipe.hincrby(k.stats, "requeued", 1)
            self._event(pipe, job_id, "status", _status_event("queued", nxt, reason))
            self._enqueue(pipe, job_id, nxt)
            return "requeued"

        outcome = self._transition(job_id, change)
        log.warning(
            f"{self.noun} run ended early", extra={"job": job_id, "reason": reason, "outcome": outcome}
        )
        return outcome

    def reap(self) -> list[str]:
        """Re-queue (or fail) every running job whose lease expired: its worker died or lost Redis."""
        k = self.keys
        ids = [text_of(i) for i in self.r.zrange(k.running, 0, -1)]
        reaped = []
        for job_id in ids:
            if self.r.exists(k.lease(job_id)):
                continue
            status, rid, worker = self.r.hmget(k.job(job_id), ["status", "rq_id", "worker"])
            if status is None or text_of(status) != "running":
                self.r.zrem(k.running, job_id)
                continue
            delivery = int(text_of(rid).rsplit("-", 1)[1])
            who = text_of(worker) if worker else "?"
            reason = f"abandoned: worker {who} stopped renewing the {self.noun}'s lease"
            if self.requeue_or_fail(job_id, delivery, reason, count_failure=True) != "stale":
                reaped.append(job_id)
        return reaped


def _status_event(status: JobState, attempt: int, reason: str | None = None) -> dict[str, object]:
    """A ``status`` event's data: ``reason`` only when there is one."""
    return StatusEvent(status=status, attempt=attempt, reason=reason).model_dump(exclude_none=True)


def new_id() -> str:
    """A new job id (32 hex digits)."""
    return uuid.uuid4().hex
