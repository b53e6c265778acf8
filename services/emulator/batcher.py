"""Dynamic batching: every step request of one (model, version) that arrives within ``max_wait``
(or until ``max_batch`` rows are waiting) is answered by ONE ONNX Runtime call.

A request is (session, controls (U,), forces (F,)); the batch gathers the sessions' rows of the
contiguous state pool into (B, S), stacks the inputs into (B, U) and (B, F), runs
``OnnxEmulator.step`` (in a worker thread when the batch is large, so the event loop keeps serving),
and scatters the finite rows of the (B, S) result back. A row with NaN or Inf marks only its session diverged.

Policy-driven sessions (``policy_rows.py``) get their controls in the same tick: before the emulator's
call, each policy among the batch's sessions is evaluated ONCE over all its rows (their states and
goals), and its controls replace those rows' controls. Whatever a client put there is ignored. When
one policy drives every row of the batch (the usual tick of a policy's sessions), the policy and the
emulator run as ONE graph (``export.driven``, composed on first use): one ONNX Runtime call per tick.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import threading
import time
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from neuroanimator.artifacts.policies import POLICY_ONNX
from neuroanimator.artifacts.registry import ONNX_FILE
from neuroanimator.export.driven import DrivenStep, compose_driven
from services.emulator.errors import Diverged, StepFailed, UnknownSession
from services.emulator.metrics import Metrics
from services.emulator.policies import LoadedPolicy
from services.emulator.policy_rows import PolicyTick
from services.emulator.registry import LoadedEmulator
from services.emulator.sessions import Session, StatePool

log = logging.getLogger(__name__)


def _diverged(session: Session) -> Diverged:
    return Diverged.at_step(session.id, session.steps + 1)


def _deleted(session: Session) -> UnknownSession:
    return UnknownSession(f"session {session.id!r} was deleted while stepping")


@dataclass(slots=True)
class _SessionEntry:
    """One session's step: its (U+F,) inputs, controls then forces (an array, or a list of floats
    as a binary websocket frame unpacks to)."""

    session: Session
    inputs: NDArray[np.float32] | list[float]
    future: asyncio.Future[NDArray[np.float32]]

    @property
    def rows(self) -> int:
        return 1


@dataclass
class _BlockEntry:
    """Many sessions in one queue entry (binary ``POST /step``): their (K,) slots of ``pool`` with
    the (K,) ``gen`` of each slot when they were locked, and their inputs (K, U+F)."""

    pool: StatePool
    slots: NDArray[np.intp]
    gens: NDArray[np.uint32]
    inputs: NDArray[np.float32]
    future: asyncio.Future[BlockResult]

    @property
    def rows(self) -> int:
        return len(self.slots)


# Batches of at most this many rows run ORT on the event loop itself (see Batcher._run): up to about
# a millisecond for a small network, less than handing the call to a thread and back costs on a busy
# machine (0.5-1 ms measured); larger batches run in a worker thread so the loop keeps serving.
INLINE_ROWS = 4096
# A tick of one policy's sessions runs the policy composed with the emulator (one ONNX Runtime call)
# up to this many rows, where a call's fixed cost is what composing saves (lander, 1 thread: 29–30 µs
# against 31–33 for two calls at one row, 67–73 against 78–79 at 64); above it the composed graph
# gains nothing and was at times the slower (3,560–3,705 µs against 2,820–3,476 at 4,096 rows).
COMPOSED_MAX_ROWS = 256

BlockResult = tuple[NDArray[np.float32], NDArray[np.uint8], NDArray[np.bool_] | None]
"""What ``Batcher.step_block`` returns: (K, S) states, (K,) row outcomes, (K,) outside the envelope."""

# Row outcomes of ``Batcher.step_block`` (the binary format's status bytes, see services/emulator/binary.py).
ROW_OK, ROW_DIVERGED, ROW_GONE = 0, 2, 3


class Batcher:
    """The batching queue of one (model, version); its worker task lives on the running loop."""

    def __init__(self, emu: LoadedEmulator, max_batch: int, max_wait_s: float, metrics: Metrics) -> None:
        self.emu = emu
        self.max_batch = max_batch
        self.max_wait_s = max_wait_s
        self.metrics = metrics
        self.ort_calls = 0
        self.rows = 0
        self._pending: list[_SessionEntry | _BlockEntry] = []
        self._pending_rows = 0  # rows waiting in _pending, kept so that enqueueing is O(1)
        self._ready = asyncio.Event()
        self._task: asyncio.Task[None] | None = None
        self._driven: dict[str, DrivenStep | None] = {}  # per policy label: its composed step, if any
        self._compose_lock = threading.Lock()  # (composed in a worker thread at a large batch)

    async def step(self, session: Session, inputs: NDArray[np.float32] | list[float]) -> NDArray[np.float32]:
        """One super-step of one session under (U+F,) inputs, controls then forces (checked and
        clipped), batched with whatever else arrives now: returns its (S,) new state, written back."""
        if session.diverged:
            raise _diverged(session)
        fut: asyncio.Future[NDArray[np.float32]] = asyncio.get_running_loop().create_future()
        self._enqueue(_SessionEntry(session, inputs, fut))
        return await fut

    async def step_block(
        self,
        pool: StatePool,
        slots: NDArray[np.intp],
        gens: NDArray[np.uint32],
        inputs: NDArray[np.float32],
    ) -> BlockResult:
        """One super-step of the K sessions in ``slots`` of ``pool`` (K,) (whose ``gen`` was ``gens``
        (K,) when the caller locked them) under inputs (K, U+F), in one queue entry: returns
        (K, S) new states, (K,) row outcomes ``ROW_*`` and (K,) whether each new state is outside
        the training envelope (None: none is). A diverged session keeps (and returns) its last finite
        state; a session deleted meanwhile returns NaN."""
        fut: asyncio.Future[BlockResult] = asyncio.get_running_loop().create_future()
        self._enqueue(_BlockEntry(pool, slots, gens, inputs, fut))
        return await fut

    def _enqueue(self, req: _SessionEntry | _BlockEntry) -> None:
        if self._task is None or self._task.done():
            self._task = asyncio.get_running_loop().create_task(
                self._worker(), name=f"batcher-{self.emu.model}"
            )
        self._pending.append(req)
        self._pending_rows += req.rows
        self._ready.set()

    async def close(self) -> None:
        if self._task is not None:
            self._task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._task
        for req in self._pending:
            if not req.future.done():
                req.future.cancel()

    async def _worker(self) -> None:
        while True:
            await self._ready.wait()
            await self._gather()
            take, rows = 0, 0  # whole entries up to max_batch rows (a block entry is never split)
            while take < len(self._pending) and (
                take == 0 or rows + self._pending[take].rows <= self.max_batch
            ):
                rows += self._pending[take].rows
                take += 1
            batch, self._pending = self._pending[:take], self._pending[take:]
            self._pending_rows -= rows
            if not self._pending:
                self._ready.clear()
            try:
                await self._run(batch)
            except Exception as exc:  # ORT failed: every request of this batch gets the error
                log.exception("ORT call failed for %s/%s", self.emu.model, self.emu.version)
                err = StepFailed(f"the emulator step failed: {exc}")
                for req in batch:
                    if not req.future.done():
                        req.future.set_exception(err)

    async def _gather(self) -> None:
        """The batching window: event-loop turns (each reads the sockets that are ready and queues
        the requests read the turn before) while requests keep arriving, ending after two quiet
        turns, at ``max_wait`` or when ``max_batch`` rows wait. A lone request is thus stepped at once, and a busy server
        still fills its batches; a fixed wait would delay the one and not fill the other any better."""
        loop = asyncio.get_running_loop()
        deadline = loop.time() + self.max_wait_s
        quiet = 0  # turns in a row without a new request: bytes read in one turn are queued the next
        while self._pending_rows < self.max_batch and quiet < 2:
            before = self._pending_rows
            await asyncio.sleep(0)  # a loop turn: ready sockets are read and their requests queued
            if loop.time() >= deadline:
                return
            quiet = quiet + 1 if self._pending_rows == before else 0

    async def _run(self, batch: list[_SessionEntry | _BlockEntry]) -> None:
        """Step one batch: one ORT call over every live entry's rows, then each entry's answer."""
        single, blocks = self._live(batch)
        ns = len(single)
        parts = [np.fromiter((r.session.slot for r in single), np.intp, ns)]
        parts += [b.slots for b in blocks]
        slots = np.concatenate(parts)
        if not slots.size:
            return
        pool = single[0].session.pool if single else blocks[0].pool
        out = await self._infer(pool, slots, single, blocks)
        # (B,) rows without NaN or Inf; one flat test first, since that is the usual answer
        finite = (
            np.asarray(np.isfinite(out).all(axis=1))
            if not np.isfinite(out).all()
            else np.ones(len(out), bool)
        )
        # (B,) new states beyond the training envelope (None: none is), kept per session
        env = self.emu.envelope
        outside = None if env is None else env.outside(out)
        # (rows written back are all inside: flags of earlier steps are cleared, when there are any)
        clear = outside is None and env is not None and bool(pool.outside.any())
        if ns:
            self._answer_single(pool, single, slots[:ns], out[:ns], finite[:ns], outside, clear)
        start = ns
        for b in blocks:
            part = slice(start, start + len(b.slots))
            start += len(b.slots)
            self._answer_block(
                pool, b, out[part], finite[part], None if outside is None else outside[part], clear
            )

    @staticmethod
    def _live(batch: list[_SessionEntry | _BlockEntry]) -> tuple[list[_SessionEntry], list[_BlockEntry]]:
        """The entries still waiting, single and block apart; a single one whose session was deleted
        or expired while queued is answered now."""
        single: list[_SessionEntry] = []
        blocks: list[_BlockEntry] = []
        for r in batch:
            if r.future.done():
                continue
            if isinstance(r, _BlockEntry):
                blocks.append(r)
            elif r.session.alive:
                single.append(r)
            else:  # deleted or expired while queued
                r.future.set_exception(_deleted(r.session))
        return single, blocks

    async def _infer(
        self,
        pool: StatePool,
        slots: NDArray[np.intp],
        single: list[_SessionEntry],
        blocks: list[_BlockEntry],
    ) -> NDArray[np.float32]:
        """The ORT step of the (B,) ``slots`` of ``pool`` under the entries' inputs, single entries'
        rows first, the policy-driven rows' controls set by their policies first: the (B, S) new
        states (not yet written back)."""
        x = np.take(pool.states, slots, axis=0)  # (B, S) copy
        parts_in = [np.array([r.inputs for r in single], np.float32)] if single else []
        parts_in += [b.inputs for b in blocks]
        inputs = np.concatenate(parts_in) if len(parts_in) > 1 else parts_in[0]  # (B, U+F)
        tick = PolicyTick.plan(pool.driving, pool.steps, slots)
        shared = not single and len(blocks) == 1  # ``inputs`` is then the block's own array
        t0 = time.perf_counter()
        if len(slots) <= INLINE_ROWS:
            out = self._compute(x, inputs, tick, shared)
        else:  # a large one runs in a worker thread so that the event loop keeps serving meanwhile
            out = await asyncio.to_thread(self._compute, x, inputs, tick, shared)
        self.ort_calls += 1
        self.rows += len(slots)
        self.metrics.observe_batch(self.emu.model, len(slots), time.perf_counter() - t0)
        if tick is not None:
            tick.record(pool.driving)
            if tick.bad is not None:  # a policy's non-finite controls: those sessions diverge
                out[tick.bad] = np.nan
        return out

    def _compute(
        self, x: NDArray[np.float32], inputs: NDArray[np.float32], tick: PolicyTick | None, shared: bool
    ) -> NDArray[np.float32]:
        """States (B, S) and inputs (B, U+F) -> (B, S): the policies' calls (one per policy, or the
        sole policy composed with the emulator), then the emulator's. ``shared``: ``inputs`` is the
        caller's, not to be written. No pool is touched here (it may run in a worker thread)."""
        nu = self.emu.num_controls
        f = np.ascontiguousarray(inputs[:, nu:]) if self.emu.num_forces else None
        if tick is not None:
            policy = tick.sole_policy() if len(x) <= COMPOSED_MAX_ROWS else None
            driven = self.driven_step(policy) if policy is not None else None
            if policy is not None and driven is not None:
                g = tick.groups[0]
                left = policy.time_left(g.since) if policy.manifest.timed else None
                controls, out = driven.run(x, g.goals, left, f)
                tick.took(controls)
                return out
            bounds = self.emu.inputs
            if shared:
                inputs = inputs.copy()  # the policies' controls go into a copy
            tick.apply(x, inputs, bounds.low[:nu], bounds.high[:nu])
        u = inputs[:, :nu] if nu else None
        return self.emu.emulator.step(x, u, f, validate=False)

    def driven_step(self, policy: LoadedPolicy) -> DrivenStep | None:
        """The policy composed with this emulator into one graph, built on first use; None when the
        two would not compose (logged once: its ticks then make two calls)."""
        key = policy.label
        if key not in self._driven:
            with self._compose_lock:
                if key not in self._driven:
                    self._driven[key] = self._compose(policy)
        return self._driven[key]

    def _compose(self, policy: LoadedPolicy) -> DrivenStep | None:
        emu, nu = self.emu, self.emu.num_controls
        try:
            graph = compose_driven(
                (policy.path / POLICY_ONNX).read_bytes(),
                (emu.path / ONNX_FILE).read_bytes(),
                emu.inputs.low[:nu],
                emu.inputs.high[:nu],
            )
            return DrivenStep(graph, emu.emulator.threads, emu.emulator.wrap)
        except Exception:  # (onnx and ONNX Runtime raise types of their own) two calls still work
            log.warning(
                "policy %s not composed with its emulator: two calls a tick", policy.label, exc_info=True
            )
            return None

    def _answer_single(
        self,
        pool: StatePool,
        single: list[_SessionEntry],
        slots: NDArray[np.intp],
        out: NDArray[np.float32],
        finite: NDArray[np.bool_],
        outside: NDArray[np.bool_] | None,
        clear: bool,
    ) -> None:
        """Write back the (N, S) new states ``out`` of the single entries' (N,) ``slots`` where they
        are finite and the session is still alive (one deleted while in flight may have had its slot
        reused), in one scatter, then answer each entry. ``outside``: the whole batch's (B,) flags,
        single entries' rows first."""
        ns = len(single)
        # (a request cancelled meanwhile has let go of its lock: its session is not advanced)
        alive = np.fromiter((r.session.alive and not r.future.done() for r in single), bool, ns)
        keep = alive & finite
        written = slots[keep]
        pool.states[written] = out[keep]
        pool.steps[written] += 1
        if outside is not None:
            pool.outside[written] = outside[:ns][keep]
        elif clear:
            pool.outside[written] = False
        for i, req in enumerate(single):
            if req.future.done():
                continue
            if finite[i]:
                req.future.set_result(out[i])
            elif req.session.alive:
                self._diverge(req.session)
                req.future.set_exception(_diverged(req.session))
            else:
                req.future.set_exception(_deleted(req.session))

    def _answer_block(
        self,
        pool: StatePool,
        b: _BlockEntry,
        rows: NDArray[np.float32],
        ok: NDArray[np.bool_],
        outside: NDArray[np.bool_] | None,
        clear: bool,
    ) -> None:
        """Write back a block entry's (K, S) new ``rows`` where they are finite (``ok``) and the slot
        still holds the session it locked, and answer it: states, ``ROW_*`` outcomes, outside flags."""
        k = len(b.slots)
        alive = pool.gen[b.slots] == b.gens
        good = ok & alive
        everyone = bool(good.all())
        moved = b.slots if everyone else b.slots[good]
        pool.states[moved] = rows if everyone else rows[good]
        pool.steps[moved] += 1  # no slot twice in one entry: a request's ids are distinct
        flags = None
        if outside is not None:
            flags = outside & good
            pool.outside[moved] = flags if everyone else flags[good]
        elif clear:
            pool.outside[moved] = False
        status = np.zeros(k, np.uint8)
        if not everyone:  # rare: rows of diverged or deleted sessions, one by one
            for j in np.flatnonzero(~good).tolist():
                owner = pool.owner[int(b.slots[j])]
                if not alive[j] or owner is None:
                    status[j] = ROW_GONE
                    rows[j] = np.nan
                else:
                    self._diverge(owner)
                    status[j] = ROW_DIVERGED
                    rows[j] = pool.states[owner.slot]
        if not b.future.done():
            b.future.set_result((rows, status, flags))

    def _diverge(self, sess: Session) -> None:
        sess.diverged = True
        self.metrics.diverged.labels(self.emu.model).inc()
        log.warning("session diverged", extra={"session": sess.id, "model": self.emu.model})
