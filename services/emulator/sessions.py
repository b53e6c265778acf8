"""Sessions: everything about the sessions of one (model, version) lives in contiguous arrays.

``StatePool`` holds, per *slot* (one row per session): ``states`` (capacity, S) float32, and
``steps``, ``last_used``, ``diverged``, ``outside`` (the last step left the training envelope), ``busy``
(a step is in flight), ``taken``, ``gen`` (bumped whenever the slot changes hands) and ``owner_code``
(the API key that owns it) as (capacity,) arrays, and the columns of policy-driven slots
(``policy_rows.PolicyColumns``: the policy, its goal, when the goal was set, its last controls). Freed
slots go on a free list and are reused; the arrays double when full. The batcher gathers the rows
of a batch with one fancy index and scatters the results back the same way, so stepping N sessions
costs a few numpy calls, not N Python operations.

A ``Session`` is a small handle (id, model, pool, slot) whose attributes read and write its row.
Session ids are ``<replica_id>-<token>``: the replica that owns the session is in its id.
"""

from __future__ import annotations

import asyncio
import logging
import secrets
import time
from collections import OrderedDict
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from neuroanimator.sim.driver import Driver
from services.common.auth import CALLER
from services.emulator.binary import decode_ids
from services.emulator.errors import BadInput, QuotaExceeded, UnknownSession
from services.emulator.policies import LoadedPolicy
from services.emulator.policy_rows import PolicyColumns
from services.emulator.registry import LoadedEmulator

log = logging.getLogger(__name__)

NO_OWNER = -1  # owner_code of a session created without API keys


class StatePool:
    """Rows of per-session arrays handed out to the sessions of one (model, version)."""

    def __init__(self, state_size: int, capacity: int = 64, num_controls: int = 0) -> None:
        self.states = np.zeros((capacity, state_size), dtype=np.float32)
        self.steps = np.zeros(capacity, dtype=np.int64)
        self.last_used = np.zeros(capacity, dtype=np.float64)  # time.monotonic()
        self.diverged = np.zeros(capacity, dtype=bool)
        self.outside = np.zeros(capacity, dtype=bool)
        self.driven = np.zeros(capacity, dtype=bool)  # its model's driver sets its controls
        self.busy = np.zeros(capacity, dtype=bool)
        self.taken = np.zeros(capacity, dtype=bool)
        self.gen = np.zeros(capacity, dtype=np.uint32)
        self.owner_code = np.full(capacity, NO_OWNER, dtype=np.int32)
        self.owner: list[Session | None] = [None] * capacity
        self.driving = PolicyColumns(capacity, num_controls)  # the policy-driven slots' columns
        self.free = list(range(capacity - 1, -1, -1))  # pop() hands out low slots first
        # tasks waiting for a busy slot: slot -> futures, woken when it is released
        self.waiters: dict[int, list[asyncio.Future[None]]] = {}

    def _grow(self) -> None:
        old = self.states.shape[0]
        for name in (
            "states",
            "steps",
            "last_used",
            "diverged",
            "outside",
            "driven",
            "busy",
            "taken",
            "gen",
            "owner_code",
        ):
            arr = getattr(self, name)
            grown = np.zeros((old * 2, *arr.shape[1:]), dtype=arr.dtype)
            if name == "owner_code":
                grown[:] = NO_OWNER
            grown[:old] = arr
            setattr(self, name, grown)
        self.owner.extend([None] * old)
        self.driving.grow(2 * old)
        self.free = list(range(2 * old - 1, old - 1, -1))

    def acquire(self, session: Session, state: NDArray[np.float32], owner_code: int) -> int:
        if not self.free:
            self._grow()
        slot = self.free.pop()
        self.states[slot] = state
        self.steps[slot] = 0
        self.last_used[slot] = time.monotonic()
        self.diverged[slot] = False
        self.outside[slot] = False
        self.driven[slot] = False
        self.busy[slot] = False
        self.taken[slot] = True
        self.owner_code[slot] = owner_code
        self.owner[slot] = session
        return slot

    def release(self, slot: int) -> None:
        """The slot is free again; a step of its old session still in flight sees ``gen`` changed."""
        self.owner[slot] = None
        self.driven[slot] = False
        self.driving.detach(slot)
        self.gen[slot] += 1
        self.busy[slot] = False
        self.taken[slot] = False
        self.owner_code[slot] = NO_OWNER
        self.free.append(slot)
        self.wake(np.asarray([slot]))

    def lock_rows(self, slots: NDArray[np.intp]) -> None:
        """Mark these (free) slots busy: the bulk form of ``SessionLock.acquire``."""
        self.busy[slots] = True

    def unlock_rows(self, slots: NDArray[np.intp], gens: NDArray[np.uint32]) -> None:
        """Clear the busy flag of the slots still held by the sessions locked (same ``gens``)."""
        mine = slots[self.gen[slots] == gens]
        self.busy[mine] = False
        self.wake(mine)

    def wake(self, slots: NDArray[np.intp]) -> None:
        if not self.waiters:
            return
        for slot in np.intersect1d(slots, np.fromiter(self.waiters, np.intp)).tolist():
            for fut in self.waiters.pop(slot):
                if not fut.done():
                    fut.set_result(None)

    @property
    def used(self) -> int:
        return len(self.owner) - len(self.free)


class SessionLock:
    """Mutual exclusion of the steps of one session (``async with sess.lock``), kept as the pool's
    ``busy`` flag so that a bulk request can test and take thousands of them in one numpy call."""

    __slots__ = ("session",)

    def __init__(self, session: Session) -> None:
        self.session = session

    def locked(self) -> bool:
        s = self.session
        return s.alive and bool(s.pool.busy[s.slot])

    async def acquire(self) -> None:
        s = self.session
        if s.try_lock():
            return
        while s.alive and s.pool.busy[s.slot]:
            fut: asyncio.Future[None] = asyncio.get_running_loop().create_future()
            s.pool.waiters.setdefault(s.slot, []).append(fut)
            await fut
        if s.alive:  # a session deleted meanwhile needs no lock: its next step finds it unknown
            s.pool.busy[s.slot] = True

    def release(self) -> None:
        self.session.unlock()

    async def __aenter__(self) -> None:
        await self.acquire()

    async def __aexit__(self, *exc: object) -> None:
        self.release()


@dataclass(eq=False, slots=True)
class Session:
    """One client's emulated system: a handle on row ``slot`` of ``pool`` (-1 once deleted)."""

    id: str
    emu: LoadedEmulator
    pool: StatePool
    slot: int = -1
    seed: int | None = None
    owner: str | None = None  # the id of the API key that created it (None: auth off)
    # what its row said when it was deleted (a step in flight may still report on it)
    final_steps: int = 0
    final_diverged: bool = False
    # the model's controller setting the controls each super-step (``neuroanimator.sim.driver``), and its
    # parameters as the client set them; None: the client's controls
    driver: Driver | None = None
    driver_params: dict[str, float] | None = None
    # a trained policy setting the controls each super-step from the state and the goal (``policies``);
    # the goal lives in the pool's policy columns, ``goal_rev`` counts its changes (for checkpoints)
    policy: LoadedPolicy | None = None
    goal_rev: int = 0

    def attach_driver(self, driver: Driver, params: dict[str, float]) -> None:
        """From now on ``driver`` sets this session's controls on every transport."""
        self.driver, self.driver_params = driver, params
        if self.slot >= 0:
            self.pool.driven[self.slot] = True

    def attach_policy(
        self, policy: LoadedPolicy, goal: NDArray[np.float32], goal_step: int | None = None
    ) -> None:
        """From now on ``policy`` sets this session's controls towards (G,) ``goal``, set at step
        ``goal_step`` (now when None), on every transport."""
        self.policy = policy
        if self.slot >= 0:
            self.pool.driving.attach(self.slot, policy, goal, self.steps if goal_step is None else goal_step)

    def set_goal(self, goal: NDArray[np.float32]) -> None:
        """A new (G,) goal for the policy; the clock of a timed policy restarts only when it changes."""
        if self.slot < 0 or np.array_equal(goal, self.goal):
            return
        self.pool.driving.set_goal(self.slot, goal, self.steps)
        self.goal_rev += 1

    @property
    def goal(self) -> NDArray[np.float32]:
        """(G,) a copy of the policy's goal (empty without a policy or once deleted)."""
        if self.policy is None or self.slot < 0:
            return np.zeros(0, np.float32)
        return self.pool.driving.goals[self.slot, : self.policy.goal_size].copy()

    @property
    def goal_step(self) -> int:
        """The step count when the goal was set."""
        return int(self.pool.driving.goal_step[self.slot]) if self.slot >= 0 else 0

    @property
    def applied_controls(self) -> NDArray[np.float32]:
        """(U,) a copy of the controls the policy chose for the last super-step."""
        if self.slot < 0:
            return np.full(self.pool.driving.applied.shape[1], np.nan, np.float32)
        return self.pool.driving.applied[self.slot].copy()

    @property
    def alive(self) -> bool:
        return self.slot >= 0 and self.pool.owner[self.slot] is self

    @property
    def state(self) -> NDArray[np.float32]:
        """(S,) a copy of the current state (NaN once deleted: its row may be another session's)."""
        if self.slot < 0:
            return np.full(self.pool.states.shape[1], np.nan, np.float32)
        return self.pool.states[self.slot].copy()

    # A deleted session (slot -1) has no row: reads give what it had, writes are dropped.
    @property
    def steps(self) -> int:
        return int(self.pool.steps[self.slot]) if self.slot >= 0 else self.final_steps

    @steps.setter
    def steps(self, value: int) -> None:
        if self.slot >= 0:
            self.pool.steps[self.slot] = value

    @property
    def diverged(self) -> bool:
        return bool(self.pool.diverged[self.slot]) if self.slot >= 0 else self.final_diverged

    @diverged.setter
    def diverged(self, value: bool) -> None:
        if self.slot >= 0:
            self.pool.diverged[self.slot] = value

    @property
    def outside_envelope(self) -> bool:
        """Its last step left the envelope of the training states (``envelope.py``)."""
        return bool(self.pool.outside[self.slot]) if self.slot >= 0 else False

    @property
    def last_used(self) -> float:
        return float(self.pool.last_used[self.slot]) if self.slot >= 0 else 0.0

    @last_used.setter
    def last_used(self, value: float) -> None:
        if self.slot >= 0:
            self.pool.last_used[self.slot] = value

    @property
    def lock(self) -> SessionLock:
        return SessionLock(self)

    def try_lock(self) -> bool:
        """Take the lock if it is free (without waiting); False if another step holds it."""
        pool, slot = self.pool, self.slot
        if slot < 0 or pool.owner[slot] is not self:
            return True  # deleted: nothing to guard (its next step finds it unknown)
        if pool.busy[slot]:
            return False
        pool.busy[slot] = True
        return True

    def unlock(self) -> None:
        pool, slot = self.pool, self.slot
        if slot >= 0 and pool.owner[slot] is self:
            pool.busy[slot] = False
            if pool.waiters:
                pool.wake(np.asarray([slot]))

    @property
    def t(self) -> float:
        return self.steps * self.emu.super_timestep


@dataclass
class Resolved:
    """N session ids resolved at once: the pool of the known ones, their (N,) slots (-1: unknown)
    and the (N,) ``gen`` of each slot at resolution (a slot whose ``gen`` moved changed hands)."""

    emu: LoadedEmulator | None
    pool: StatePool | None
    slots: NDArray[np.intp]
    gens: NDArray[np.uint32]

    @property
    def known(self) -> NDArray[np.bool_]:
        return self.slots >= 0


class SessionStore:
    """All sessions of this replica, by id, with TTL expiry and a cap on their number."""

    ID_BLOCK_CACHE = 4  # id lists remembered by ``resolve_block`` (a game server repeats its own)

    def __init__(
        self, replica_id: str, ttl_s: float, max_sessions: int, max_per_key: int | None = None
    ) -> None:
        self.replica_id = replica_id
        self.ttl_s = ttl_s
        self.max_sessions = max_sessions
        self.max_per_key = max_per_key
        self.sessions: dict[str, Session] = {}
        self.pools: dict[tuple[str, str], StatePool] = {}
        self.per_owner: dict[str, int] = {}
        self.owner_codes: dict[str, int] = {}
        self._blocks: OrderedDict[bytes, Resolved] = OrderedDict()

    def __len__(self) -> int:
        return len(self.sessions)

    def create(
        self,
        emu: LoadedEmulator,
        state: NDArray[np.float32],
        seed: int | None = None,
        owner: str | None = None,
        sid: str | None = None,
    ) -> Session:
        """A new session at ``state`` (S,), owned by the API key id ``owner``; ``sid`` is given only when
        a checkpoint is restored. ``QuotaExceeded`` beyond MAX_SESSIONS, or beyond MAX_SESSIONS_PER_KEY for
        the owner."""
        if owner is not None and self.max_per_key is not None:
            held = self.per_owner.get(owner, 0)
            if held >= self.max_per_key:
                raise QuotaExceeded(
                    f"this API key holds its maximum of {self.max_per_key} sessions "
                    "(MAX_SESSIONS_PER_KEY); delete some or wait for idle ones to expire",
                    code="key_quota_exceeded",
                    field="MAX_SESSIONS_PER_KEY",
                    expected=self.max_per_key,
                    got=held + 1,
                )
        if len(self.sessions) >= self.max_sessions:
            self.expire()
        if len(self.sessions) >= self.max_sessions:
            raise QuotaExceeded(
                f"this replica holds its maximum of {self.max_sessions} sessions (MAX_SESSIONS); delete some "
                "or retry later",
                field="MAX_SESSIONS",
                expected=self.max_sessions,
                got=len(self.sessions) + 1,
            )
        key = (emu.model, emu.version)
        pool = self.pools.get(key)
        if pool is None:
            pool = self.pools[key] = StatePool(emu.state_size, num_controls=emu.num_controls)
        sid = sid or f"{self.replica_id}-{secrets.token_urlsafe(12)}"
        sess = Session(sid, emu, pool, seed=seed, owner=owner)
        sess.slot = pool.acquire(sess, state, self._owner_code(owner))
        self.sessions[sid] = sess
        if owner is not None:
            self.per_owner[owner] = self.per_owner.get(owner, 0) + 1
        return sess

    def _owner_code(self, owner: str | None) -> int:
        if owner is None:
            return NO_OWNER
        return self.owner_codes.setdefault(owner, len(self.owner_codes))

    def get(self, sid: str) -> Session:
        """The live session (its idle clock restarts); ``UnknownSession`` when unknown or expired, or when
        API keys are on and the caller's key (``auth.CALLER``) does not own it."""
        sess = self.sessions.get(sid)
        now = time.monotonic()
        if sess is not None and now - sess.pool.last_used[sess.slot] > self.ttl_s:
            self.delete(sid)
            sess = None
        caller = CALLER.get()
        if sess is not None and caller is not None and sess.owner != caller:
            sess = None
        if sess is None:
            raise UnknownSession.named(sid)
        sess.pool.last_used[sess.slot] = now
        return sess

    def resolve(self, ids: list[str]) -> tuple[list[Session | None], Resolved]:
        """Many ids at once, with the checks of ``get`` (unknown, expired or another key's: None and
        slot -1). ``BadInput`` (``mixed_models``) unless the known ones are all of one (model, version)."""
        found = list(map(self.sessions.get, ids))
        emu: LoadedEmulator | None = None
        first = -1
        caller = CALLER.get()
        cutoff = time.monotonic() - self.ttl_s
        for i, sess in enumerate(found):
            if sess is None:
                continue
            # expired and other keys' sessions are unknown before the model check, as with ``get``
            # (another key's session must neither fail the request nor reveal its model)
            if sess.pool.last_used[sess.slot] < cutoff:
                self.delete(sess.id)
                found[i] = sess = None
            elif caller is not None and sess.owner != caller:
                found[i] = sess = None
            if sess is None:
                continue
            if emu is None:
                emu, first = sess.emu, i
            elif sess.emu is not emu:
                raise BadInput(
                    f"session {i} ({ids[i]!r}) is of {sess.emu.model}/{sess.emu.version} but session "
                    f"{first} is of {emu.model}/{emu.version}; one binary request steps sessions of one "
                    "model version",
                    code="mixed_models",
                    field=f"ids[{i}]",
                    expected=f"{emu.model}/{emu.version}",
                    got=f"{sess.emu.model}/{sess.emu.version}",
                )
        if emu is None:
            n = len(ids)
            return found, Resolved(None, None, np.full(n, -1, np.intp), np.zeros(n, np.uint32))
        pool = self.pools[(emu.model, emu.version)]
        slots = np.fromiter((-1 if s is None else s.slot for s in found), np.intp, len(found))
        res = Resolved(emu, pool, slots, pool.gen[np.maximum(slots, 0)])
        self.check_resolved(res)
        return [s if k else None for s, k in zip(found, res.known.tolist(), strict=True)], res

    def resolve_block(self, block: bytes, width: int) -> Resolved:
        """``resolve`` for ids given as one block of NUL-padded ASCII slots of ``width`` bytes (the
        binary ``POST /step``). The same block seen again (a game server steps the same sessions
        every tick) is answered from a cache, checked in one comparison of the slots' ``gen``."""
        key = width.to_bytes(2, "little") + block  # the same bytes cut at another width are other ids
        hit = self._blocks.get(key)
        if hit is not None and hit.pool is not None and (hit.pool.gen[hit.slots] == hit.gens).all():
            self._blocks.move_to_end(key)
            res = Resolved(hit.emu, hit.pool, hit.slots.copy(), hit.gens)
            self.check_resolved(res)
            return res
        ids = decode_ids(block, width)
        if len(set(ids)) != len(ids):
            seen: set[str] = set()
            for i, sid in enumerate(ids):
                if sid in seen:
                    raise BadInput(
                        f"ids[{i}]: session {sid!r} appears more than once in the batch",
                        code="duplicate_session",
                        field=f"ids[{i}]",
                        expected="each session at most once",
                        got=sid,
                    )
                seen.add(sid)
        found, res = self.resolve(ids)
        if res.pool is not None and all(s is not None for s in found):
            self._blocks[key] = Resolved(res.emu, res.pool, res.slots.copy(), res.gens)
            if len(self._blocks) > self.ID_BLOCK_CACHE:
                self._blocks.popitem(last=False)
        return res

    def check_resolved(self, res: Resolved) -> None:
        """Vectorised ``get``: expired sessions are deleted, those of another key hidden (slot -1 both),
        and the idle clock of the rest restarts."""
        pool = res.pool
        if pool is None:
            return
        known = res.slots >= 0
        slots = res.slots[known]
        now = time.monotonic()
        expired = pool.last_used[slots] < now - self.ttl_s
        if expired.any():
            for slot in slots[expired].tolist():
                sess = pool.owner[slot]
                if sess is not None:
                    self.delete(sess.id)
        caller = CALLER.get()
        hidden = expired
        if caller is not None:
            hidden = hidden | (pool.owner_code[slots] != self.owner_codes.get(caller, -2))
        if hidden.any():
            idx = np.flatnonzero(known)[hidden]
            res.slots[idx] = -1
            slots = res.slots[res.slots >= 0]
        pool.last_used[slots] = now

    def delete(self, sid: str) -> bool:
        sess = self.sessions.pop(sid, None)
        if sess is None:
            return False
        sess.final_steps, sess.final_diverged = sess.steps, sess.diverged
        sess.pool.release(sess.slot)
        sess.slot = -1
        if sess.owner is not None:
            left = self.per_owner.get(sess.owner, 1) - 1
            if left > 0:
                self.per_owner[sess.owner] = left
            else:
                self.per_owner.pop(sess.owner, None)
        return True

    def expire(self) -> int:
        """Remove every session idle for longer than the TTL (and not stepping); returns how many."""
        cutoff = time.monotonic() - self.ttl_s
        old: list[str] = []
        for pool in self.pools.values():
            for slot in np.flatnonzero(pool.taken & (pool.last_used < cutoff) & ~pool.busy).tolist():
                sess = pool.owner[slot]
                assert sess is not None
                old.append(sess.id)
        for sid in old:
            self.delete(sid)
        if old:
            log.info("expired %d idle sessions", len(old))
        return len(old)

    def count_by_model(self) -> dict[tuple[str, str], int]:
        return {key: pool.used for key, pool in self.pools.items()}
