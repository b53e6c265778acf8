"""Session checkpoints in Redis: a restarted replica restores its sessions, losing at most one interval.

Layout: one Redis hash per replica, ``<REDIS_PREFIX>:sessions:<REPLICA_ID>``; its fields are session
ids (which start with the replica id), its values compact records (``encode``): a JSON header
(model, version, steps, diverged flag, seed, owner key id, last-used wall-clock time; a driven
session's driver parameters, or its policy's name and version with its goal and the step the goal was
set at) then a NUL byte then the state, S little-endian float32 (4·S bytes).

Every ``CHECKPOINT_INTERVAL_S`` a background task writes, in one pipeline, the sessions that changed
since the last successful checkpoint (a new step count, diverged flag or goal; reading a session is
not a change) and removes the sessions that are gone (deleted or expired). A failed checkpoint changes
nothing on this side, so the next one writes everything it missed. Each checkpoint first asks Redis
whether it still holds what was written: when its server restarted (a new ``run_id``: it may have
come back empty, or from an append-only file a second behind) or the hash holds fewer records than
were written (flushed, evicted, deleted), every live session is written again in that same
checkpoint, so that a Redis that lost data has every session back within one interval. The same
question is Redis's health: ``status`` turns ``degraded`` within an interval of Redis going away,
changed sessions or not (and ``/readyz`` asks it afresh, ``check``). On startup a replica with the same
REPLICA_ID reads its hash back and recreates the sessions with their ids, versions, states and owners.
If Redis is unreachable the service still starts (status ``degraded``, on ``/readyz``) and the restore
is retried before each checkpoint until it succeeds. Without REDIS_URL nothing is persisted (``off``).
"""

from __future__ import annotations

import asyncio
import json
import logging
import time
from dataclasses import dataclass
from typing import Any, Literal, cast

import numpy as np
import redis.asyncio as aioredis
from numpy.typing import NDArray
from prometheus_client import Counter, Gauge, Histogram
from redis.asyncio.retry import Retry
from redis.backoff import ExponentialBackoff
from redis.exceptions import RedisError, ResponseError

from neuroanimator.sim.driver import load_driver
from services.emulator.errors import EmulatorError
from services.emulator.service import EmulatorService
from services.emulator.sessions import Session

log = logging.getLogger(__name__)
Status = Literal["off", "ok", "degraded"]
_CHUNK = 1000  # fields per HSET / HDEL command inside the pipeline


@dataclass
class Record:
    """One checkpointed session; ``state`` is (S,) float32, ``last_used`` wall-clock seconds."""

    model: str
    version: str
    state: NDArray[np.float32]
    steps: int
    diverged: bool
    seed: int | None
    owner: str | None
    last_used: float
    driver: dict[str, float] | None = None  # a driven session's driver parameters
    policy: PolicyRecord | None = None  # a policy-driven session's policy and goal


@dataclass
class PolicyRecord:
    """A policy-driven session's policy (name, version), its (G,) goal and the step it was set at."""

    name: str
    version: str
    goal: list[float]
    goal_step: int


Mark = tuple[int, bool, int]
"""What a checkpoint compares to know that a session changed: its steps, diverged flag, goal changes."""


def mark_of(sess: Session) -> Mark:
    return (sess.steps, sess.diverged, sess.goal_rev)


def encode(sess: Session, last_used_wall: float) -> bytes:
    """The record of a live session: JSON header, NUL, (S,) little-endian float32 state."""
    head = {
        "m": sess.emu.model,
        "v": sess.emu.version,
        "n": sess.steps,
        "d": sess.diverged,
        "s": sess.seed,
        "o": sess.owner,
        "u": round(last_used_wall, 3),
        "r": sess.driver_params,
    }
    if sess.policy is not None:
        head["p"] = {
            "n": sess.policy.name,
            "v": sess.policy.version,
            "g": [float(v) for v in sess.goal],
            "k": sess.goal_step,
        }
    state = sess.pool.states[sess.slot].astype("<f4")
    return json.dumps(head, separators=(",", ":")).encode() + b"\0" + state.tobytes()


def decode(raw: bytes) -> Record:
    """Inverse of ``encode``; ValueError (or KeyError) on a malformed record."""
    head_bytes, sep, state = raw.partition(b"\0")
    if not sep or len(state) % 4:
        raise ValueError("not a session record")
    head: dict[str, Any] = json.loads(head_bytes)
    pol = head.get("p")
    return Record(
        model=str(head["m"]),
        version=str(head["v"]),
        state=np.frombuffer(state, dtype="<f4").astype(np.float32),
        steps=int(head["n"]),
        diverged=bool(head["d"]),
        seed=None if head["s"] is None else int(head["s"]),
        owner=None if head["o"] is None else str(head["o"]),
        last_used=float(head["u"]),
        driver=None if head.get("r") is None else {str(k): float(v) for k, v in head["r"].items()},
        policy=None
        if pol is None
        else PolicyRecord(str(pol["n"]), str(pol["v"]), [float(v) for v in pol["g"]], int(pol["k"])),
    )


class Persistence:
    """Checkpoints ``service.store`` to Redis (when REDIS_URL is set) and restores it at startup."""

    def __init__(self, service: EmulatorService) -> None:
        s = service.settings
        self.service = service
        self.interval_s = s.checkpoint_interval_s
        self.key = f"{s.redis_prefix}:sessions:{s.replica_id}"
        self.client: aioredis.Redis | None = None
        if s.redis_url:
            # Fail fast when Redis is down (one quick retry): the service must start without it.
            self.client = aioredis.Redis.from_url(
                s.redis_url,
                socket_connect_timeout=1.0,
                socket_timeout=5.0,
                retry=Retry(ExponentialBackoff(cap=0.2, base=0.05), retries=1),
            )
        self.status: Status = "degraded" if self.client else "off"
        self.restored = self.client is None
        self.last_error: str | None = None
        self._saved: dict[str, Mark] = {}  # session id -> what Redis holds of it (``mark_of``)
        self._run_id: str | None = None  # the Redis server written to (INFO's run_id): new after a restart
        self.rewrites = 0  # times Redis was found to have lost data and every session was written again
        self._lock = asyncio.Lock()  # one checkpoint at a time (the timer, a forced one, the last one)
        r = service.metrics.registry
        self._seconds = Histogram(
            "emulator_checkpoint_seconds", "duration of one checkpoint to Redis", registry=r
        )
        self._written = Counter(
            "emulator_checkpoint_records", "session records written to or removed from Redis", registry=r
        )
        self._up = Gauge("emulator_persistence_up", "1 when the last Redis operation succeeded", registry=r)

    @property
    def enabled(self) -> bool:
        return self.client is not None

    def _failed(self, what: str, exc: Exception) -> None:
        if self.status != "degraded" or self.last_error is None:
            log.warning(
                "persistence degraded: %s failed (%s); sessions are kept in memory and retried every %.1f s",
                what,
                exc,
                self.interval_s,
            )
        self.status = "degraded"
        self.last_error = f"{what}: {exc}"
        self._up.set(0)

    def _ok(self) -> None:
        if self.status == "degraded" and self.last_error is not None:
            log.info("persistence recovered: Redis answers again")
        self.status = "ok"
        self.last_error = None
        self._up.set(1)

    async def start(self) -> None:
        """Restore this replica's sessions; never raises (Redis down: status ``degraded``)."""
        if self.client is None:
            log.info("REDIS_URL is not set: sessions are not persisted (a restart loses them)")
            return
        try:
            n = await self.restore()
        except (RedisError, OSError) as exc:
            self._failed("restoring sessions from Redis", exc)
            return
        self._ok()
        log.info("persistence on", extra={"key": self.key, "restored": n, "interval_s": self.interval_s})

    async def _server_id(self, client: aioredis.Redis) -> str | None:
        """The Redis server's ``run_id`` (new at each start), or None where INFO is not allowed."""
        try:
            info = await client.info("server")
        except ResponseError:  # a managed Redis may refuse INFO: the record count still tells
            return None
        run_id = info.get("run_id")
        return None if run_id is None else str(run_id)

    async def _lost_data(self, client: aioredis.Redis) -> str | None:
        """Why Redis no longer holds every record this replica wrote (None: it does). Also the health
        check of every checkpoint: it raises when Redis does not answer."""
        count = int(await client.hlen(self.key))
        run_id = await self._server_id(client)
        restarted = run_id is not None and self._run_id is not None and run_id != self._run_id
        if run_id is not None:
            self._run_id = run_id
        if restarted:
            return "the Redis server restarted"
        if count < len(self._saved):
            return f"the hash holds {count} of the {len(self._saved)} records written"
        return None

    async def restore(self) -> int:
        """Recreate the sessions of this replica's hash that are not here yet; returns how many."""
        assert self.client is not None
        self._run_id = await self._server_id(self.client)
        raw = cast(dict[bytes, bytes], await self.client.hgetall(self.key))  # decode_responses is off
        store = self.service.store
        now_wall, now_mono = time.time(), time.monotonic()
        n = 0
        for field, value in raw.items():
            sid = field.decode()
            if sid in store.sessions or sid in self._saved:
                continue
            try:
                rec = decode(value)
            except (ValueError, KeyError, TypeError) as exc:
                log.warning("skipping a malformed session record %r: %s", sid, exc)
                continue
            idle = max(0.0, now_wall - rec.last_used)
            if idle > store.ttl_s:
                self._saved[sid] = (-1, False, 0)  # expired while down: the next checkpoint removes it
                continue
            try:
                emu = self.service.registry.get(rec.model, rec.version)
                if rec.state.shape != (emu.state_size,):
                    raise ValueError(f"state of {rec.state.size} values, the model has {emu.state_size}")
                driver = None
                if rec.driver is not None:  # the controller starts afresh (its phase is not checkpointed)
                    params = self.service.driver_params(emu, rec.driver)
                    spec = emu.manifest.spec.driver
                    assert spec is not None  # driver_params refuses a model without one
                    driver = load_driver(spec, emu.physical, emu.substeps, params)
                policy, goal = None, None
                if rec.policy is not None:  # the same version, checked against the emulator again
                    policy = self.service.policies.get(rec.model, rec.policy.name, rec.policy.version)
                    policy.check_emulator(emu.model, emu.version)
                    goal = policy.check_goal(rec.policy.goal, "goal")
                sess = store.create(emu, rec.state, rec.seed, owner=rec.owner, sid=sid)
                if driver is not None:
                    sess.attach_driver(driver, params)
                if policy is not None and goal is not None and rec.policy is not None:
                    sess.attach_policy(policy, goal, rec.policy.goal_step)
            except (EmulatorError, ValueError) as exc:
                log.warning("cannot restore session %s (%s/%s): %s", sid, rec.model, rec.version, exc)
                continue
            sess.steps, sess.diverged = rec.steps, rec.diverged
            sess.last_used = now_mono - idle
            self._saved[sid] = mark_of(sess)
            n += 1
        self.restored = True
        if n:
            self.service.update_gauges()
            log.info("restored %d sessions from Redis", n, extra={"key": self.key})
        return n

    async def checkpoint(self) -> int:
        """Write changed sessions and remove gone ones in one pipeline; returns the records touched.
        Raises ``RedisError`` / ``OSError`` when Redis fails (nothing is marked saved then)."""
        if self.client is None:
            return 0
        async with self._lock:
            return await self._checkpoint(self.client)

    async def _checkpoint(self, client: aioredis.Redis) -> int:
        if not self.restored:
            await self.restore()
        t0 = time.perf_counter()
        why = await self._lost_data(client)
        if why is not None:
            # every record counts as unwritten (the ids are kept: gone sessions are still removed)
            self._saved = dict.fromkeys(self._saved, (-2, False, 0))
            self.rewrites += 1
            log.warning(
                "Redis lost session checkpoints (%s): writing all %d sessions again",
                why,
                len(self.service.store.sessions),
                extra={"key": self.key},
            )
        sessions = self.service.store.sessions
        now_wall, now_mono = time.time(), time.monotonic()
        records: dict[str, bytes] = {}
        marks: dict[str, Mark] = {}
        for sid, sess in sessions.items():  # a synchronous snapshot: no step lands in between
            mark = mark_of(sess)
            if self._saved.get(sid) != mark and sess.alive:
                records[sid] = encode(sess, now_wall - (now_mono - sess.last_used))
                marks[sid] = mark
        gone = [sid for sid in self._saved if sid not in sessions]
        if not records and not gone:
            return 0
        pipe = client.pipeline(transaction=False)
        items = list(records.items())
        for i in range(0, len(items), _CHUNK):
            pipe.hset(self.key, mapping=dict(items[i : i + _CHUNK]))
        for i in range(0, len(gone), _CHUNK):
            pipe.hdel(self.key, *gone[i : i + _CHUNK])
        await pipe.execute()
        self._saved.update(marks)
        for sid in gone:
            self._saved.pop(sid, None)
        self._written.inc(len(records) + len(gone))
        self._seconds.observe(time.perf_counter() - t0)
        return len(records) + len(gone)

    async def check(self, timeout_s: float = 1.0) -> Status:
        """Ask Redis now (``/readyz``): ``ok`` when it answers a PING within ``timeout_s``, else
        ``degraded``; ``off`` without persistence."""
        if self.client is None:
            return self.status
        try:
            await asyncio.wait_for(self.client.ping(), timeout_s)
        except (RedisError, OSError, TimeoutError) as exc:
            self._failed("a readiness check of Redis", exc)
        else:
            if self.restored:  # ok only once the restore, which a checkpoint retries, is done
                self._ok()
        return self.status

    async def run_forever(self) -> None:
        """Checkpoint every interval until cancelled; Redis errors are logged, not raised."""
        while True:
            await asyncio.sleep(self.interval_s)
            try:
                await self.checkpoint()
            except (RedisError, OSError) as exc:
                self._failed("checkpoint to Redis", exc)
            else:
                self._ok()

    async def close(self) -> None:
        """A last checkpoint (a clean shutdown loses nothing), then the connection is closed."""
        if self.client is None:
            return
        try:
            n = await self.checkpoint()
            log.info("final checkpoint: %d session records written or removed", n)
        except (RedisError, OSError) as exc:
            log.warning("final checkpoint failed: %s", exc)
        await self.client.aclose()
