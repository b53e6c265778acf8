"""Jobs in Redis: their records, progress, events and results, and every change of their state.

RQ only *delivers* a job to a worker: each delivery is an RQ job ``<job id>-<n>`` that runs
``services.controller.execution.perform(job_id, n)`` in a forked process. What a client sees is this
module's record of the job, under ``<REDIS_PREFIX>``:

    job:<id>       hash: owner, spec, status, times, attempt, delivery (n), rq_id, failures, worker, error
    progress:<id>  hash: the current attempt's last iteration, objective, best objective, best controller
    history:<id>   list: the current attempt's objective per iteration
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
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import logging
import math
import time
import uuid
from collections.abc import Callable
from typing import Any, TypeVar

import redis
from redis.client import Pipeline
from rq import Queue
from rq.exceptions import InvalidJobOperation, NoSuchJobError
from rq.job import Job
from rq.serializers import JSONSerializer

from neuroanimator.control.spec import JobSpec
from neuroanimator.controller_schemas import FINAL_STATES, JobOutcome
from services.controller.settings import Settings

log = logging.getLogger(__name__)

PERFORM = "services.controller.execution.perform"
FINAL = frozenset(FINAL_STATES)
MAX_EVENTS = 20_000  # a stream keeps about this many events (SSE replays what is left)
MAX_OWNER_JOBS = 1000  # a caller's job list keeps the newest this many ids
DURATION_BUCKETS = (0.5, 1.0, 2.0, 5.0, 10.0, 20.0, 30.0, 60.0, 120.0, 300.0, 600.0, 1800.0, 3600.0)
ITERATION_BUCKETS = (1.0, 2.0, 5.0, 10.0, 20.0, 50.0, 100.0, 200.0, 500.0, 1000.0, 2000.0, 5000.0)
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


class QueueFull(Exception):
    """The queue holds ``MAX_QUEUE`` jobs already."""


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


def dumps(value: Any) -> str:
    return json.dumps(clean(value), separators=(",", ":"), allow_nan=False)


def _str(value: Any) -> str:
    """A Redis reply (bytes; str from a decoding client) as text."""
    return value.decode() if isinstance(value, bytes) else str(value)


def _text(raw: Any) -> dict[str, str]:
    return {_str(k): _str(v) for k, v in dict(raw).items()}


def _observe(pipe: Pipeline, key: str, name: str, value: float, buckets: tuple[float, ...]) -> None:
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

    def __init__(self, conn: redis.Redis, settings: Settings) -> None:
        self.r = conn
        self.settings = settings
        self.keys = Keys(settings.redis_prefix)
        # JSON, not RQ's default pickle: what is on the queue is data, never code to unpickle
        self.queue = Queue(settings.queue_name, connection=conn, serializer=JSONSerializer)
        self._seen = conn.register_script(_WORKER_SEEN)
        self._count = conn.register_script(_WORKER_COUNT)

    # ------------------------------------------------------------ plumbing
    def _transition(self, job_id: str, change: Callable[[Pipeline, dict[str, str]], T]) -> T:
        """Run ``change(pipe, record)`` with the record WATCHed; it calls ``pipe.multi()`` before queueing
        its writes, which then commit only if nobody changed the record since it was read (else retry)."""
        key = self.keys.job(job_id)
        with self.r.pipeline() as pipe:
            while True:
                try:
                    pipe.watch(key)
                    out = change(pipe, _text(pipe.hgetall(key)))
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
            func=PERFORM,
            args=(job_id, delivery),
            job_id=rq_id(job_id, delivery),
            # the job stops itself at JOB_TIMEOUT_S; RQ kills its process if it is still there after the grace
            timeout=math.ceil(s.job_timeout_s + s.job_timeout_grace_s),
            result_ttl=s.result_ttl_s,
            failure_ttl=s.result_ttl_s,
            description=f"controller job {job_id} (delivery {delivery})",
            pipeline=pipe,
        )

    def _event(self, pipe: Pipeline, job_id: str, event: str, data: dict[str, Any]) -> None:
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
        rec: dict[str, str],
        status: str,
        reason: str | None,
        result: dict[str, Any],
    ) -> None:
        """Queue the writes that end a job: status, result, ``end`` event, expiry and statistics."""
        k, ttl, now = self.keys, self.settings.result_ttl_s, time.time()
        spec = json.loads(rec.get("spec", "{}"))
        body = {
            "task": spec.get("task"),
            "model": spec.get("model"),
            "version": spec.get("version"),
            **result,
            "id": job_id,
            "status": status,
            "reason": reason,
        }
        pipe.hset(k.job(job_id), mapping={"status": status, "error": reason or "", "ended_at": repr(now)})
        pipe.set(k.result(job_id), dumps(body), ex=ttl)
        best = body.get("best_objective")
        if best is None and body.get("objective_history"):
            finite = [v for v in clean(body["objective_history"]) if v is not None]
            best = min(finite) if finite else None
        end = {
            "status": status,
            "reason": reason,
            "iterations": body.get("iterations"),
            "best_objective": best,
        }
        self._event(pipe, job_id, "end", end)
        pipe.zrem(k.running, job_id)
        pipe.delete(k.lease(job_id), k.yield_(job_id))
        for key in (k.job(job_id), k.progress(job_id), k.history(job_id), k.events(job_id), k.cancel(job_id)):
            pipe.expire(key, ttl)
        pipe.hincrby(k.stats, f"finished:{status}", 1)
        if rec.get("started_at"):
            _observe(pipe, k.stats, "duration", now - float(rec["started_at"]), DURATION_BUCKETS)
        _observe(pipe, k.stats, "turnaround", now - float(rec.get("created_at", now)), DURATION_BUCKETS)
        if isinstance(body.get("iterations"), int):
            _observe(pipe, k.stats, "iterations", float(body["iterations"]), ITERATION_BUCKETS)

    # ------------------------------------------------------------ API side
    def queue_depth(self) -> int:
        return int(self.queue.count)

    def submit(self, spec: JobSpec, owner: str, idempotency_key: str | None = None) -> tuple[str, str, bool]:
        """Queue a validated job; returns (id, status, created). A repeated idempotency key returns its
        job; raises ``QueueFull`` or ``IdempotencyConflict``."""
        s, k = self.settings, self.keys
        spec_json = json.dumps(spec.model_dump(mode="json"), sort_keys=True, separators=(",", ":"))
        spec_hash = hashlib.sha256(spec_json.encode()).hexdigest()[:32]
        idem = k.idem(owner, idempotency_key) if idempotency_key else None
        if idem and (found := self._idempotent(idem, spec_hash)):
            return (*found, False)
        depth = self.queue_depth()
        if depth >= s.max_queue:
            raise QueueFull(
                f"the queue is full: {depth} jobs wait (MAX_QUEUE={s.max_queue}); try again later"
            )
        job_id = uuid.uuid4().hex
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
            self._event(pipe, job_id, "status", {"status": "queued", "attempt": 1})
            pipe.expire(k.events(job_id), s.queued_ttl_s)
            self._enqueue(pipe, job_id, 1)
            pipe.execute()
        self.r.zremrangebyrank(k.owner(owner), 0, -(MAX_OWNER_JOBS + 1))
        log.info("job queued", extra={"job": job_id, "owner": owner, "task": spec.task})
        return job_id, "queued", True

    def _idempotent(self, idem: str, spec_hash: str) -> tuple[str, str] | None:
        raw = self.r.get(idem)
        if raw is None:
            return None
        job_id = _str(raw)
        status, saved_hash = self.r.hmget(self.keys.job(job_id), ["status", "spec_hash"])
        if status is None:
            return None  # the job expired: the key may make a new one
        if _str(saved_hash) != spec_hash:
            raise IdempotencyConflict(
                f"idempotency_key was already used for job {job_id} with a different request"
            )
        return job_id, _str(status)

    def record(self, job_id: str, owner: str | None = None) -> dict[str, Any] | None:
        """The job's record with its progress and history; None if absent or ``owner`` is not its owner."""
        k = self.keys
        with self.r.pipeline(transaction=False) as pipe:
            pipe.hgetall(k.job(job_id))
            pipe.hgetall(k.progress(job_id))
            pipe.lrange(k.history(job_id), 0, -1)
            rec_raw, prog_raw, hist = pipe.execute()
        if not rec_raw:
            return None
        rec: dict[str, Any] = _text(rec_raw)
        if owner is not None and rec.get("owner") != owner:
            return None
        rec["progress"] = {key: json.loads(v) for key, v in _text(prog_raw).items()}
        rec["history"] = [json.loads(v) for v in hist]
        return rec

    def result(self, job_id: str) -> dict[str, Any] | None:
        raw = self.r.get(self.keys.result(job_id))
        return None if raw is None else dict(json.loads(_str(raw)))

    def jobs_of(self, owner: str, limit: int) -> list[dict[str, Any]]:
        """The owner's newest jobs (expired ones are dropped from the list)."""
        ids = [_str(i) for i in self.r.zrevrange(self.keys.owner(owner), 0, limit - 1)]
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
        """Cancel a job: a queued one ends now; a running one is flagged and stops at its next iteration.
        Returns its status after this call."""
        cancelled_delivery: list[str] = []

        def change(pipe: Pipeline, rec: dict[str, str]) -> str:
            status = rec.get("status", "")
            if not rec or status in FINAL:
                return status
            pipe.multi()
            pipe.set(self.keys.cancel(job_id), "1", ex=self.settings.queued_ttl_s)
            if status == "queued":
                self._final(pipe, job_id, rec, "cancelled", "cancelled before it started", {"iterations": 0})
                cancelled_delivery.append(rec.get("rq_id", ""))
                return "cancelled"
            return status

        status = self._transition(job_id, change)
        for rid in cancelled_delivery:  # a worker that takes it anyway finds it ended and does nothing
            with contextlib.suppress(NoSuchJobError, InvalidJobOperation):
                Job.fetch(rid, connection=self.r, serializer=JSONSerializer).cancel()
        log.info("job cancel requested", extra={"job": job_id, "status": status})
        return status

    def stats(self) -> dict[str, str]:
        return _text(self.r.hgetall(self.keys.stats))

    def worker_count(self) -> int:
        """Workers heard from within ``WORKER_ALIVE_S`` (a killed one drops out; a Redis that lost its
        data counts each worker again at its next heartbeat)."""
        return int(self._count(keys=[self.keys.workers], args=[self.settings.worker_alive_s()]))

    # ------------------------------------------------------------ worker side
    def worker_seen(self, name: str, pipe: Pipeline | None = None) -> None:
        """A worker's heartbeat (``ControllerWorker.heartbeat``)."""
        self._seen(keys=[self.keys.workers], args=[name, self.settings.worker_alive_s()], client=pipe)

    def worker_gone(self, name: str) -> None:
        """A worker that stopped cleanly."""
        self.r.zrem(self.keys.workers, name)

    def start(self, job_id: str, delivery: int, worker: str, pid: int) -> tuple[dict[str, str] | None, str]:
        """Mark delivery ``n`` running and take the lease; (record, "started"), or (None, why not)."""
        k, s = self.keys, self.settings

        def change(pipe: Pipeline, rec: dict[str, str]) -> tuple[dict[str, str] | None, str]:
            if not rec:
                return None, "gone"
            if rec["status"] in FINAL:
                return None, f"already {rec['status']}"
            if rec.get("rq_id") != rq_id(job_id, delivery):
                return None, f"superseded by {rec.get('rq_id')}"
            cancelled = pipe.exists(k.cancel(job_id))
            pipe.multi()
            if cancelled:
                self._final(pipe, job_id, rec, "cancelled", "cancelled before it started", {"iterations": 0})
                return None, "cancelled"
            attempt = int(rec.get("attempt", "0")) + 1
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
            self._event(pipe, job_id, "status", {"status": "running", "attempt": attempt})
            return {**rec, "attempt": str(attempt)}, "started"

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
        return bool(cancel), bool(yld), None if current is None else _str(current)

    def progress(self, job_id: str, attempt: int, p: dict[str, Any]) -> None:
        """Record one iteration: the progress hash, the objective history and a ``progress`` event."""
        k = self.keys
        data = {**clean(p), "attempt": attempt}
        fields = {key: json.dumps(v) for key, v in data.items()}
        with self.r.pipeline(transaction=False) as pipe:
            pipe.hset(k.progress(job_id), mapping=fields)
            pipe.rpush(k.history(job_id), json.dumps(data.get("objective")))
            self._event(pipe, job_id, "progress", data)
            # so that a job nobody ever ends (every worker gone for good) leaves nothing forever
            for key in (k.progress(job_id), k.history(job_id)):
                pipe.expire(key, self.settings.queued_ttl_s)
            pipe.execute()

    def set_yield(self, job_id: str) -> None:
        self.r.set(self.keys.yield_(job_id), "1", ex=max(60, int(self.settings.job_timeout_s)))

    def finish(self, job_id: str, delivery: int, result: JobOutcome) -> bool:
        """End the job with ``run_job``'s outcome; False if it had already ended or was superseded."""

        def change(pipe: Pipeline, rec: dict[str, str]) -> bool:
            if not rec or rec["status"] in FINAL or rec.get("rq_id") != rq_id(job_id, delivery):
                return False
            pipe.multi()
            self._final(pipe, job_id, rec, result.status, result.reason, result.model_dump())
            return True

        done = self._transition(job_id, change)
        log.info("job ended", extra={"job": job_id, "status": result.status, "recorded": done})
        return done

    def requeue_or_fail(self, job_id: str, delivery: int, reason: str, count_failure: bool) -> str:
        """Put the job back on the queue as delivery n+1, or end it failed when this failure exceeds
        ``JOB_RETRIES`` (or cancelled when that was asked). Returns requeued | failed | cancelled | stale."""
        k, retries = self.keys, self.settings.job_retries

        def change(pipe: Pipeline, rec: dict[str, str]) -> str:
            if not rec or rec["status"] in FINAL or rec.get("rq_id") != rq_id(job_id, delivery):
                return "stale"
            failures = int(rec.get("failures", "0")) + int(count_failure)
            cancelled = pipe.exists(k.cancel(job_id))
            progress = _text(pipe.hgetall(k.progress(job_id)))
            history = [json.loads(v) for v in pipe.lrange(k.history(job_id), 0, -1)]
            partial = {
                "iterations": json.loads(progress.get("iteration", "0")),
                "objective_history": history,
                "best_objective": json.loads(progress.get("best_objective", "null")),
            }
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
            self._event(pipe, job_id, "status", {"status": "queued", "attempt": nxt, "reason": reason})
            self._enqueue(pipe, job_id, nxt)
            return "requeued"

        outcome = self._transition(job_id, change)
        log.warning("job run ended early", extra={"job": job_id, "reason": reason, "outcome": outcome})
        return outcome

    def reap(self) -> list[str]:
        """Re-queue (or fail) every running job whose lease expired: its worker died or lost Redis."""
        k = self.keys
        ids = [_str(i) for i in self.r.zrange(k.running, 0, -1)]
        reaped = []
        for job_id in ids:
            if self.r.exists(k.lease(job_id)):
                continue
            status, rid, worker = self.r.hmget(k.job(job_id), ["status", "rq_id", "worker"])
            if status is None or _str(status) != "running":
                self.r.zrem(k.running, job_id)
                continue
            delivery = int(_str(rid).rsplit("-", 1)[1])
            who = _str(worker) if worker else "?"
            reason = f"abandoned: worker {who} stopped renewing the job's lease"
            if self.requeue_or_fail(job_id, delivery, reason, count_failure=True) != "stale":
                reaped.append(job_id)
        return reaped
