"""Sessions: the states of all sessions of one (model, version) live in one contiguous array.

``StatePool.states`` is a (capacity, S) float32 array; a session owns one row (its *slot*), freed
slots go on a free list and are reused, and the array doubles when full. The batcher gathers the rows
of a batch with one fancy index and scatters the results back the same way.

Session ids are ``<replica_id>-<token>``: the replica that owns the session is in its id.
"""

from __future__ import annotations

import asyncio
import logging
import secrets
import time
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from services.emulator.auth import CALLER
from services.emulator.errors import ApiError
from services.emulator.registry import Loaded

log = logging.getLogger(__name__)


class StatePool:
    """Rows of a (capacity, S) float32 array handed out to sessions of one (model, version)."""

    def __init__(self, state_size: int, capacity: int = 64) -> None:
        self.states = np.zeros((capacity, state_size), dtype=np.float32)
        self.owner: list[Session | None] = [None] * capacity
        self.free = list(range(capacity - 1, -1, -1))  # pop() hands out low slots first

    def acquire(self, session: Session, state: NDArray[np.float32]) -> int:
        if not self.free:
            old = self.states.shape[0]
            grown = np.zeros((old * 2, self.states.shape[1]), dtype=np.float32)
            grown[:old] = self.states
            self.states = grown
            self.owner.extend([None] * old)
            self.free = list(range(2 * old - 1, old - 1, -1))
        slot = self.free.pop()
        self.states[slot] = state
        self.owner[slot] = session
        return slot

    def release(self, slot: int) -> None:
        self.owner[slot] = None
        self.free.append(slot)

    @property
    def used(self) -> int:
        return len(self.owner) - len(self.free)


@dataclass(eq=False)
class Session:
    """One client's emulated system; its state is ``pool.states[slot]``."""

    id: str
    emu: Loaded
    pool: StatePool
    slot: int = -1
    steps: int = 0
    diverged: bool = False
    seed: int | None = None
    owner: str | None = None  # the id of the API key that created it (None: auth off)
    last_used: float = field(default_factory=time.monotonic)
    lock: asyncio.Lock = field(default_factory=asyncio.Lock)

    @property
    def alive(self) -> bool:
        return self.slot >= 0 and self.pool.owner[self.slot] is self

    @property
    def state(self) -> NDArray[np.float32]:
        """(S,) a copy of the current state."""
        return self.pool.states[self.slot].copy()

    @property
    def t(self) -> float:
        return self.steps * self.emu.super_timestep


class SessionStore:
    """All sessions of this replica, by id, with TTL expiry and a cap on their number."""

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

    def __len__(self) -> int:
        return len(self.sessions)

    def create(
        self,
        emu: Loaded,
        state: NDArray[np.float32],
        seed: int | None = None,
        owner: str | None = None,
        sid: str | None = None,
    ) -> Session:
        """A new session at ``state`` (S,), owned by the API key id ``owner``; ``sid`` is given only when
        a checkpoint is restored. 429 beyond MAX_SESSIONS, or beyond MAX_SESSIONS_PER_KEY for the owner."""
        if owner is not None and self.max_per_key is not None:
            held = self.per_owner.get(owner, 0)
            if held >= self.max_per_key:
                raise ApiError(
                    429,
                    "key_quota_exceeded",
                    f"this API key holds its maximum of {self.max_per_key} sessions "
                    "(MAX_SESSIONS_PER_KEY); delete some or wait for idle ones to expire",
                    expected=self.max_per_key,
                    got=held + 1,
                )
        if len(self.sessions) >= self.max_sessions:
            self.expire()
        if len(self.sessions) >= self.max_sessions:
            raise ApiError(
                429,
                "too_many_sessions",
                f"this replica holds its maximum of {self.max_sessions} sessions; delete some or retry later",
                expected=self.max_sessions,
                got=len(self.sessions) + 1,
            )
        key = (emu.model, emu.version)
        pool = self.pools.get(key)
        if pool is None:
            pool = self.pools[key] = StatePool(emu.state_size)
        sid = sid or f"{self.replica_id}-{secrets.token_urlsafe(12)}"
        sess = Session(sid, emu, pool, seed=seed, owner=owner)
        sess.slot = pool.acquire(sess, state)
        self.sessions[sid] = sess
        if owner is not None:
            self.per_owner[owner] = self.per_owner.get(owner, 0) + 1
        return sess

    def get(self, sid: str) -> Session:
        """The live session (its idle clock restarts); 404 when unknown or expired, or when API keys
        are on and the caller's key (``auth.CALLER``) does not own it."""
        sess = self.sessions.get(sid)
        now = time.monotonic()
        if sess is not None and now - sess.last_used > self.ttl_s:
            self.delete(sid)
            sess = None
        caller = CALLER.get()
        if sess is not None and caller is not None and sess.owner != caller:
            sess = None
        if sess is None:
            raise ApiError(404, "unknown_session", f"no session {sid!r} (never created, deleted or expired)")
        sess.last_used = now
        return sess

    def delete(self, sid: str) -> bool:
        sess = self.sessions.pop(sid, None)
        if sess is None:
            return False
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
        """Remove every session idle for longer than the TTL; returns how many."""
        cutoff = time.monotonic() - self.ttl_s
        old = [sid for sid, s in self.sessions.items() if s.last_used < cutoff and not s.lock.locked()]
        for sid in old:
            self.delete(sid)
        if old:
            log.info("expired %d idle sessions", len(old))
        return len(old)

    def count_by_model(self) -> dict[tuple[str, str], int]:
        return {key: pool.used for key, pool in self.pools.items()}
