"""The stepping core: every step of every transport is checked, clipped, locked and stepped here.

Transports parse and reply: REST (``routes/``), the binary ``POST /step`` (``fastpath.py``) and
websockets (``ws/``). They hand this module typed requests:

* one session (``Stepper.check`` or ``InputRange.check_row`` for its inputs, then ``Stepper.step``, or
  ``Lane.step`` where a connection keeps its model's lane): the session's slot is locked, the
  super-steps go through the batcher of its model version, and the outcome is a ``Stepped``;
* sessions of any models by id (``Stepper.step_items``, the JSON ``POST /step``): request-level problems
  fail the whole request before anything is stepped, a session's own problem is its own outcome;
* a block of sessions of one model version, resolved at once (``Stepper.step_block``, the binary
  ``POST /step``): checked, clipped, locked and stepped as arrays in ONE batcher entry.

Inputs are checked by ``inputs.py`` (lengths, float32, the trained range: the same check for every
transport); the batcher writes the new states back into the sessions' pool. A policy-driven session's
request carries a goal and forces, never controls (``Stepper.session_inputs``): its policy sets them in
the batcher's tick, and a step reports the controls it chose. Problems are typed domain errors
(``errors.py``); what a client receives for them is ``error_mapping.py``'s business.
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from neuroanimator.contracts.emulator import BatchStepItem
from services.emulator import binary
from services.emulator.batcher import ROW_DIVERGED, ROW_GONE, Batcher
from services.emulator.errors import BadInput, Diverged, EmulatorError, TooLarge
from services.emulator.inputs import CheckedInputs, RowLabel
from services.emulator.metrics import LatencySeries, Metrics
from services.emulator.registry import LoadedEmulator
from services.emulator.sessions import Resolved, Session, SessionStore
from services.emulator.settings import Settings


@dataclass(slots=True)
class Stepped:
    """A session after a step request: ``states`` (K, S) after each of its K super-steps, the inputs
    it was stepped with, the state groups of those states outside the training envelope,
    ``start`` (S,) its state before them (when the transport needs it) and ``controls`` (K, U) the
    controls its driver or policy chose for each super-step (None: the client's)."""

    session: Session
    states: NDArray[np.float32]
    inputs: CheckedInputs
    outside: list[str]
    start: NDArray[np.float32] | None = None
    controls: NDArray[np.float32] | None = None


class BlockStepped(NamedTuple):
    """A block after its step: (N,) binary status bytes, (N, S) states, (N,) outside the envelope."""

    status: NDArray[np.uint8]
    states: NDArray[np.float32]
    outside: NDArray[np.bool_]


def outside_groups(sess: Session, state: NDArray[np.float32]) -> list[str]:
    """The state groups of ``state``, the new state of a step of ``sess`` just taken, that are outside
    the training envelope (the batcher's flag says whether any is; this names them)."""
    env = sess.emu.envelope
    if env is None or not sess.outside_envelope:
        return []
    return env.groups_outside(state)


class Lane:
    """Single-session steps of one model version for one transport: its batcher and latency series
    (None: not observed), looked up once (a websocket connection keeps its lane)."""

    __slots__ = ("batcher", "latency")

    def __init__(self, batcher: Batcher, latency: LatencySeries | None) -> None:
        self.batcher = batcher
        self.latency = latency

    async def step(self, sess: Session, row: NDArray[np.float32] | list[float]) -> NDArray[np.float32]:
        """One super-step of ``sess`` under a (U+F,) input row (checked and clipped), its slot locked
        meanwhile: the (S,) new state."""
        t0 = time.perf_counter()
        if not sess.try_lock():
            await sess.lock.acquire()
        try:
            out = await self.batcher.step(sess, row)
        finally:
            sess.unlock()
        if self.latency is not None:
            self.latency.observe(time.perf_counter() - t0)
        return out

    async def run(
        self, sess: Session, row: NDArray[np.float32], steps: int
    ) -> tuple[NDArray[np.float32], NDArray[np.float32], NDArray[np.float32] | None]:
        """``steps`` super-steps under one held input row, the slot locked throughout: the (S,) state
        before them, the (steps, S) states after each and, for a policy-driven session, the (steps, U)
        controls its policy chose for each."""
        t0 = time.perf_counter()
        chosen: list[NDArray[np.float32]] | None = None if sess.policy is None else []
        async with sess.lock:
            start = sess.state
            out = []
            for _ in range(steps):
                out.append(await self.batcher.step(sess, row))
                if chosen is not None:
                    chosen.append(sess.applied_controls)
        if self.latency is not None:
            self.latency.observe((time.perf_counter() - t0) / steps)
        return start, np.stack(out), None if chosen is None else np.stack(chosen)


class Stepper:
    """The stepping core of one service process: the batchers of the running event loop and the
    steps of every transport."""

    def __init__(self, settings: Settings, store: SessionStore, metrics: Metrics) -> None:
        self.settings = settings
        self.store = store
        self.metrics = metrics
        self._batchers: dict[tuple[str, str], Batcher] = {}
        self._loop: asyncio.AbstractEventLoop | None = None

    # ------------------------------------------------------------------ batchers
    def batcher(self, emu: LoadedEmulator) -> Batcher:
        loop = asyncio.get_running_loop()
        if loop is not self._loop:  # a new event loop (a new server or test client): fresh queues
            self._batchers = {}
            self._loop = loop
        key = (emu.model, emu.version)
        b = self._batchers.get(key)
        if b is None:
            s = self.settings
            b = self._batchers[key] = Batcher(emu, s.max_batch, s.max_wait_ms / 1000.0, self.metrics)
        return b

    def lane(self, emu: LoadedEmulator, transport: str) -> Lane:
        return Lane(self.batcher(emu), self.metrics.latency(emu.model, transport))

    @property
    def ort_calls(self) -> int:
        """ORT calls made by the batchers of the current loop (tests compare it with request counts)."""
        return sum(b.ort_calls for b in self._batchers.values())

    async def close(self) -> None:
        for b in self._batchers.values():
            await b.close()
        self._batchers = {}

    # ------------------------------------------------------------------ one session
    @staticmethod
    def check(
        emu: LoadedEmulator, controls: Sequence[float], forces: Sequence[float], prefix: str = ""
    ) -> CheckedInputs:
        """Controls (U) and forces (F) from JSON, checked against the model and clipped to its range."""
        return emu.inputs.check_lists(controls, forces, f"model {emu.model!r}", prefix)

    @staticmethod
    def refuse_goal(sess: Session, goal: Sequence[float] | None, prefix: str = "") -> None:
        """``BadInput`` for a goal sent to a session without a policy."""
        if goal is not None and sess.policy is None:
            raise BadInput(
                f"session {sess.id} has no policy: create it with a policy to set a goal",
                code="no_policy",
                field=f"{prefix}goal",
                expected="no goal",
                got=list(goal),
            )

    @staticmethod
    def session_inputs(
        sess: Session,
        controls: Sequence[float],
        forces: Sequence[float],
        goal: Sequence[float] | None,
        prefix: str = "",
    ) -> CheckedInputs:
        """The checked inputs of a step request of a session without a driver. A policy-driven one
        takes no controls (its policy sets them in the batcher; neutral values stand in), the client's
        forces, and its new goal (set once the request is known to be good). ``BadInput`` for controls
        sent to a policy-driven session, or a goal sent to a session without a policy."""
        emu, policy = sess.emu, sess.policy
        what = f"model {emu.model!r}"
        if policy is None:
            Stepper.refuse_goal(sess, goal, prefix)
            return emu.inputs.check_lists(controls, forces, what, prefix)
        if controls:
            raise BadInput(
                f"session {sess.id} is driven by policy {policy.name!r}, which sets its controls: send a "
                "goal (and forces), not controls",
                code="policy_sets_controls",
                field=f"{prefix}controls",
                expected=f"no controls (policy {policy.name!r} sets them)",
                got=len(controls),
            )
        new_goal = None if goal is None else policy.check_goal(goal, f"{prefix}goal")
        inputs = emu.inputs.check_lists(emu.inputs.neutral_controls.tolist(), forces, what, prefix)
        if new_goal is not None:
            sess.set_goal(new_goal)
        return inputs

    def check_steps(self, steps: int, frames_per_step: int | None = None) -> None:
        """``BadInput`` beyond MAX_STEPS_PER_REQUEST steps or MAX_FRAMES_PER_REQUEST frames."""
        s = self.settings
        if steps > s.max_steps_per_request:
            raise BadInput(
                f"steps must be at most {s.max_steps_per_request}, got {steps}",
                code="too_many_steps",
                field="steps",
                expected=f"<= {s.max_steps_per_request}",
                got=steps,
            )
        if frames_per_step is not None and steps * frames_per_step > s.max_frames_per_request:
            raise BadInput(
                f"steps × frames_per_step must be at most {s.max_frames_per_request}, got {steps * frames_per_step}",
                code="too_many_frames",
                field="frames_per_step",
                expected=f"<= {s.max_frames_per_request // steps}",
                got=frames_per_step,
            )

    async def step(
        self, sess: Session, inputs: CheckedInputs, steps: int = 1, transport: str = "rest"
    ) -> Stepped:
        """``steps`` super-steps of one session under held inputs, each batched with other requests."""
        self.check_steps(steps)
        start, states, controls = await self.lane(sess.emu, transport).run(sess, inputs.row, steps)
        env = sess.emu.envelope
        outside = [] if env is None else env.groups_outside(states)
        return Stepped(sess, states, inputs, outside, start, controls)

    # ------------------------------------------------------------------ sessions by id, any models
    async def step_items(self, items: Sequence[BatchStepItem]) -> list[Stepped | EmulatorError]:
        """One super-step of each item's session. Request-level problems (size, duplicates, input
        lengths) raise and step nothing; a session that is unknown or diverges is its item's error, as
        are controls sent to a policy-driven session and a goal it cannot take."""
        limit = self.settings.max_batch
        if len(items) > limit:
            raise TooLarge(
                f"a batch may hold at most {limit} items (MAX_BATCH), got {len(items)}",
                field="items",
                expected=f"<= {limit}",
                got=len(items),
            )
        seen: set[str] = set()
        for i, it in enumerate(items):
            if it.session in seen:
                raise BadInput(
                    f"items[{i}].session: session {it.session!r} appears more than once in the batch",
                    code="duplicate_session",
                    field=f"items[{i}].session",
                    expected="each session at most once",
                    got=it.session,
                )
            seen.add(it.session)
        prepared: list[tuple[Session, CheckedInputs] | EmulatorError] = []
        for i, it in enumerate(items):
            try:
                sess = self.store.get(it.session)
            except EmulatorError as exc:
                prepared.append(exc)
                continue
            prefix = f"items[{i}]."
            if sess.policy is not None or it.goal is not None:
                try:  # controls for a policy, or a goal it cannot take: this session's own error
                    inputs = self.session_inputs(sess, it.controls, it.forces, it.goal, prefix)
                except BadInput as exc:
                    prepared.append(exc)
                else:
                    prepared.append((sess, inputs))
                continue
            controls = it.controls if sess.driver is None else sess.driver.act(sess.state).tolist()
            prepared.append((sess, self.check(sess.emu, controls, it.forces, prefix=prefix)))
        t0 = time.perf_counter()

        async def one(p: tuple[Session, CheckedInputs] | EmulatorError) -> Stepped | EmulatorError:
            if isinstance(p, EmulatorError):
                return p
            sess, inputs = p
            try:
                out = await Lane(self.batcher(sess.emu), None).step(sess, inputs.row)
            except EmulatorError as exc:
                return exc
            chosen = None
            if sess.policy is not None:
                chosen = sess.applied_controls[None]
            elif sess.driver is not None:
                chosen = inputs.controls[None]
            return Stepped(sess, out[None], inputs, outside_groups(sess, out), controls=chosen)

        results = await asyncio.gather(*map(one, prepared))
        if items:
            self.metrics.step_latency.labels("batch", "rest-batch").observe(time.perf_counter() - t0)
        return list(results)

    # ------------------------------------------------------------------ a block of one model version
    async def step_block(self, res: Resolved, rows: NDArray[np.float32], label: RowLabel) -> BlockStepped:
        """One super-step of the N sessions ``res`` resolved (one model version; slot -1: unknown)
        under inputs (N, U+F); ``label`` names a row in an error. Returns the (N,) status bytes of the
        binary format (``binary.OK``, ``CLIPPED``, ``DIVERGED``, ``UNKNOWN``), (N, S) states (the new
        state, a diverged session's last finite one, NaN for an unknown session) and (N,) whether
        each new state is outside the training envelope.

        A NaN or Inf input fails the whole block before anything is stepped. The sessions no other
        request is stepping are locked together (no await in between) and stepped as ONE batcher
        entry; one that another request is stepping is stepped after it, alone, holding only its own
        lock. Everything is done with numpy over the block: no Python per session."""
        emu, pool = res.emu, res.pool
        assert emu is not None and pool is not None
        n = len(rows)
        slots, known = res.slots, res.known
        safe = np.where(known, slots, 0)
        driven = np.flatnonzero(known & pool.driven[safe])
        if driven.size:  # a driven session's controls come from its driver, whatever the row says
            rows = rows.copy()
            for i in driven.tolist():
                one = pool.owner[int(res.slots[i])]
                if one is not None and one.driver is not None:
                    rows[i, : emu.num_controls] = one.driver.act(one.state)
        # a policy's session: its policy sets its controls in the batcher; the row's are ignored
        if pool.driving.count:
            policy = known & (pool.driving.index[safe] >= 0)
            if policy.any():
                rows = rows.copy() if not driven.size else rows
                if policy.all():  # (the usual block: a slice, not a mask)
                    rows[:, : emu.num_controls] = emu.inputs.neutral_controls
                else:
                    rows[policy, : emu.num_controls] = emu.inputs.neutral_controls
        inputs, mask = emu.inputs.clip(rows, label)
        status = np.zeros(n, np.uint8)
        if mask is not None:  # (the rows of the clipped values, without a reduction along the short axis)
            status[np.flatnonzero(mask) // rows.shape[1]] = binary.CLIPPED
        states = np.full((n, emu.state_size), np.nan, np.float32)
        outside = np.zeros(n, bool)
        status[~known] = binary.UNKNOWN
        diverged = known & pool.diverged[safe]
        status[diverged] = binary.DIVERGED
        states[diverged] = pool.states[slots[diverged]]
        runnable = known & ~diverged
        busy = runnable & pool.busy[safe]
        free = np.flatnonzero(runnable & ~busy)
        batcher = self.batcher(emu)
        t0 = time.perf_counter()
        if free.size:
            everyone = free.size == n  # the usual request: every session known, none busy or diverged
            mine = slots if everyone else slots[free]
            gens = pool.gen[mine]
            pool.lock_rows(mine)
            try:
                new, outcome, flags = await batcher.step_block(
                    pool, mine, gens, inputs if everyone else inputs[free]
                )
            finally:
                pool.unlock_rows(mine, gens)
            if everyone:
                states = new
            else:
                states[free] = new
            if flags is not None:
                outside[free] = flags
            status[free[outcome == ROW_DIVERGED]] = binary.DIVERGED
            status[free[outcome == ROW_GONE]] = binary.UNKNOWN
        if busy.any():
            lane = Lane(batcher, None)  # (the request's latency is observed below)
            for i in np.flatnonzero(busy).tolist():
                one = pool.owner[int(slots[i])]
                if one is None or pool.gen[slots[i]] != res.gens[i]:
                    status[i] = binary.UNKNOWN
                    continue
                try:
                    states[i] = await lane.step(one, inputs[i])
                    outside[i] = one.outside_envelope
                except EmulatorError as exc:
                    status[i] = binary.DIVERGED if isinstance(exc, Diverged) else binary.UNKNOWN
                    if one.alive:
                        states[i] = one.state
        self.metrics.latency(emu.model, "rest-binary").observe(time.perf_counter() - t0)
        return BlockStepped(status, states, outside)
