"""The service's core, shared by REST and websockets: registry, sessions, batchers and metrics.

Inputs are validated here against the session's model (lengths, float32 range, control ranges), so
every transport answers the same errors; the hot path then calls the batcher with clean arrays.
"""

from __future__ import annotations

import asyncio
import logging
import secrets
import time
from collections.abc import Sequence
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from neuroanimator.emulator_schemas import (
    BatchStepRequest,
    BatchStepResponse,
    BatchStepResult,
    SessionCreate,
    SessionInfo,
    StepResponse,
)
from services.common.auth import CALLER
from services.common.errors import ApiError
from services.emulator.batcher import Batcher
from services.emulator.interpolation import frames
from services.emulator.metrics import Metrics
from services.emulator.registry import Loaded, Registry
from services.emulator.sessions import Session, SessionStore
from services.emulator.settings import Settings

if TYPE_CHECKING:
    from services.emulator.ws import Connection

log = logging.getLogger(__name__)

_F32_MAX = float(np.finfo(np.float32).max)
_EMPTY = np.zeros(0, np.float32)
_EMPTY.flags.writeable = False  # shared by every model without controls or forces


def check_vector(
    field: str, values: Sequence[float], width: int, what: str, rng: NDArray[np.float64] | None = None
) -> tuple[NDArray[np.float32], list[int]]:
    """A (width,) float32 vector from finite JSON numbers, clipped to ``rng`` (width, 2) if given.

    Returns the vector and the indices that were clipped; 422 on a wrong length or a value beyond
    float32's range.
    """
    if len(values) != width:
        raise ApiError(
            422,
            "wrong_length",
            f"{field} must have {width} values for {what}, got {len(values)}",
            field=field,
            expected=width,
            got=len(values),
        )
    if width == 0:
        return _EMPTY, []
    arr = np.asarray(values, dtype=np.float64)
    # beyond float32's range (JSON allows it) or NaN/Inf (binary frames can carry them): 422
    bad = np.flatnonzero(~(np.abs(arr) <= _F32_MAX))
    if bad.size:
        i = int(bad[0])
        raise ApiError(
            422,
            "not_finite",
            f"{field}[{i}] = {values[i]!r} is beyond the float32 range",
            field=f"{field}[{i}]",
            expected="a finite float32",
            got=values[i],
        )
    out = arr.astype(np.float32)
    return clip_to(out, rng) if rng is not None else (out, [])


def clip_to(values: NDArray[np.float32], rng: NDArray[np.float64]) -> tuple[NDArray[np.float32], list[int]]:
    """Finite float32 ``values`` (W,) clipped to ``rng`` (W, 2): the vector and the clipped indices."""
    if values.size == 0:
        return _EMPTY, []
    lo, hi = rng[:, 0], rng[:, 1]
    mask = (values < lo) | (values > hi)
    if not mask.any():
        return values, []
    return np.clip(values, lo, hi).astype(np.float32), np.flatnonzero(mask).tolist()


class Engine:
    """Everything one service process holds; routes reach it as ``request.app.state.engine``."""

    def __init__(self, settings: Settings) -> None:
        self.settings = settings
        self.registry = Registry(settings.artifacts_dir, settings.ort_threads, settings.registry_poll_s)
        self.store = SessionStore(
            settings.replica_id, settings.session_ttl_s, settings.max_sessions, settings.max_sessions_per_key
        )
        self.metrics = Metrics()
        self._batchers: dict[tuple[str, str], Batcher] = {}
        self.connections: set[Connection] = set()  # open websocket connections (services/emulator/ws.py)
        self._loop: asyncio.AbstractEventLoop | None = None
        self.registry.refresh()

    # ------------------------------------------------------------------ batching
    def batcher(self, emu: Loaded) -> Batcher:
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

    @property
    def ort_calls(self) -> int:
        """ORT calls made by the batchers of the current loop (tests compare it with request counts)."""
        return sum(b.ort_calls for b in self._batchers.values())

    async def close(self) -> None:
        for b in self._batchers.values():
            await b.close()
        self._batchers = {}

    async def sweep_forever(self) -> None:
        while True:
            await asyncio.sleep(self.settings.sweep_interval_s)
            self.store.expire()
            self.update_gauges()

    def update_gauges(self) -> None:
        for (model, version), n in self.store.count_by_model().items():
            self.metrics.sessions.labels(model, version).set(n)

    # ------------------------------------------------------------------ sessions
    def create_session(self, req: SessionCreate) -> Session:
        emu = self.registry.get(req.model, req.version)
        seed = None
        if req.state is not None:
            state, _ = check_vector("state", req.state, emu.state_size, f"model {emu.model!r}")
            for sl in emu.quaternion_slices:
                norm = float(np.linalg.norm(state[sl]))
                if not norm > 1e-6:
                    raise ApiError(
                        422,
                        "bad_quaternion",
                        f"state[{sl.start}:{sl.stop}] is a quaternion and must not be zero",
                        field=f"state[{sl.start}:{sl.stop}]",
                        expected="a nonzero quaternion [w, x, y, z]",
                        got=[float(v) for v in state[sl]],
                    )
                state[sl] /= norm
        else:
            seed = req.seed if req.seed is not None else secrets.randbits(63)
            state = emu.initial_state(seed)
        sess = self.store.create(emu, state, seed, owner=CALLER.get())
        self.update_gauges()
        log.info("session created", extra={"session": sess.id, "model": emu.model, "version": emu.version})
        return sess

    def info(self, sess: Session) -> SessionInfo:
        return SessionInfo(
            id=sess.id,
            model=sess.emu.model,
            version=sess.emu.version,
            state=sess.state.tolist(),
            t=sess.t,
            steps=sess.steps,
            diverged=sess.diverged,
            seed=sess.seed,
            ttl_s=self.settings.session_ttl_s,
        )

    def delete(self, sid: str) -> None:
        self.store.get(sid)  # 404 unless it exists and the caller's key (if any) owns it
        if not self.store.delete(sid):
            raise ApiError(404, "unknown_session", f"no session {sid!r} (never created, deleted or expired)")
        self.update_gauges()

    def inputs(
        self, sess: Session, controls: Sequence[float], forces: Sequence[float], prefix: str = ""
    ) -> tuple[NDArray[np.float32], list[int], NDArray[np.float32], list[int]]:
        """Validated, clipped (U,) controls and (F,) forces for this session's model."""
        emu = sess.emu
        what = f"model {emu.model!r}"
        u, cu = check_vector(f"{prefix}controls", controls, emu.num_controls, what, emu.control_range)
        f, cf = check_vector(f"{prefix}forces", forces, emu.num_forces, what, emu.force_range)
        return u, cu, f, cf

    def inputs_array(
        self, sess: Session, values: NDArray[np.float32]
    ) -> tuple[NDArray[np.float32], list[int], NDArray[np.float32], list[int]]:
        """``inputs`` for (U+F,) float32 values of a binary frame (its length already checked)."""
        emu = sess.emu
        # the common case first, in two comparisons: every value finite and in range (NaN fails both)
        if (values >= emu.input_low).all() and (values <= emu.input_high).all():
            return values[: emu.num_controls], [], values[emu.num_controls :], []
        bad = np.flatnonzero(~np.isfinite(values))
        if bad.size:
            j = int(bad[0])
            name = f"controls[{j}]" if j < emu.num_controls else f"forces[{j - emu.num_controls}]"
            raise ApiError(
                422,
                "not_finite",
                f"{name} is {float(values[j])!r}; inputs must be finite float32",
                field=name,
                expected="a finite float32",
                got=float(values[j]),
            )
        u, cu = clip_to(values[: emu.num_controls], emu.control_range)
        f, cf = clip_to(values[emu.num_controls :], emu.force_range)
        return u, cu, f, cf

    # ------------------------------------------------------------------ stepping
    async def step(
        self,
        sess: Session,
        controls: Sequence[float],
        forces: Sequence[float],
        steps: int = 1,
        frames_per_step: int | None = None,
        transport: str = "rest",
    ) -> StepResponse:
        """``steps`` super-steps of one session under held inputs, each batched with other requests."""
        s = self.settings
        if steps > s.max_steps_per_request:
            raise ApiError(
                422,
                "too_many_steps",
                f"steps must be at most {s.max_steps_per_request}, got {steps}",
                field="steps",
                expected=f"<= {s.max_steps_per_request}",
                got=steps,
            )
        if frames_per_step is not None and steps * frames_per_step > s.max_frames_per_request:
            raise ApiError(
                422,
                "too_many_frames",
                f"steps × frames_per_step must be at most {s.max_frames_per_request}, got {steps * frames_per_step}",
                field="frames_per_step",
                expected=f"<= {s.max_frames_per_request // steps}",
                got=frames_per_step,
            )
        u, cu, f, cf = self.inputs(sess, controls, forces)
        batcher = self.batcher(sess.emu)
        t0 = time.perf_counter()
        async with sess.lock:
            start = sess.state
            out = [await batcher.step(sess, u, f) for _ in range(steps)]
        self.metrics.latency(sess.emu.model, transport).observe((time.perf_counter() - t0) / steps)
        states = np.stack(out)
        fr = None
        if frames_per_step is not None:
            fr = frames(
                np.concatenate([start[None], states]),
                frames_per_step,
                sess.emu.quaternion_slices,
                sess.emu.emulator.wrap,  # a heading: the shorter arc
            )
        return StepResponse(
            id=sess.id,
            state=states[-1].tolist(),
            states=states.tolist(),
            frames=None if fr is None else fr.tolist(),
            t=sess.t,
            steps=sess.steps,
            clipped=bool(cu or cf),
            clipped_controls=cu,
            clipped_forces=cf,
        )

    async def batch_step(self, req: BatchStepRequest) -> BatchStepResponse:
        """One super-step of many sessions. Request-level problems (size, lengths) fail the whole
        request and step nothing; a session that is unknown or diverged gets its own error."""
        items = req.items
        if len(items) > self.settings.max_batch:
            raise ApiError(
                413,
                "batch_too_large",
                f"a batch may hold at most {self.settings.max_batch} items (MAX_BATCH), got {len(items)}",
                field="items",
                expected=f"<= {self.settings.max_batch}",
                got=len(items),
            )
        seen: set[str] = set()
        for i, it in enumerate(items):
            if it.session in seen:
                raise ApiError(
                    422,
                    "duplicate_session",
                    f"items[{i}].session: session {it.session!r} appears more than once in the batch",
                    field=f"items[{i}].session",
                    expected="each session at most once",
                    got=it.session,
                )
            seen.add(it.session)
        prepared: list[
            tuple[Session, NDArray[np.float32], NDArray[np.float32], list[int], list[int]] | ApiError
        ] = []
        for i, it in enumerate(items):
            try:
                sess = self.store.get(it.session)
            except ApiError as exc:
                prepared.append(exc)
                continue
            u, cu, f, cf = self.inputs(sess, it.controls, it.forces, prefix=f"items[{i}].")
            prepared.append((sess, u, f, cu, cf))
        t0 = time.perf_counter()

        async def one(
            sid: str,
            p: tuple[Session, NDArray[np.float32], NDArray[np.float32], list[int], list[int]] | ApiError,
        ) -> BatchStepResult:
            if isinstance(p, ApiError):
                return BatchStepResult(session=sid, error=p.body)
            sess, u, f, cu, cf = p
            try:
                async with sess.lock:
                    new = await self.batcher(sess.emu).step(sess, u, f)
            except ApiError as exc:
                return BatchStepResult(session=sid, error=exc.body)
            return BatchStepResult(
                session=sid,
                state=new.tolist(),
                t=sess.t,
                clipped=bool(cu or cf),
                clipped_controls=cu,
                clipped_forces=cf,
            )

        results = await asyncio.gather(*(one(it.session, p) for it, p in zip(items, prepared, strict=True)))
        if items:
            self.metrics.step_latency.labels("batch", "rest-batch").observe(time.perf_counter() - t0)
        return BatchStepResponse(results=list(results))
