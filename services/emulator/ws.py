"""``/ws/sessions/{id}``: lock-step and real-time modes, JSON and binary frames.

Lock-step (the default): ``{"type": "step", "controls": [...], "forces": [...], "seq": n}`` (or a
binary frame, proto/frames.md) → the next state. Real-time (``{"type": "start", "mode": "realtime"}``
or ``?mode=realtime``): the server advances the session every Δt of wall time (the model's super
timestep × ``WS_REALTIME_SCALE``) with the latest inputs the client sent (``{"type": "controls", ...}``
or binary frames) and pushes each new state. ``format=binary`` (in ``start`` or the query) sends
states as binary frames; errors are always JSON text. ``{"type": "ping"}`` → ``pong``.

For drawing (JSON format only): ``poses: true`` (in ``start`` or the query) adds every body's world
pose to each state; ``shadow: true`` runs a MuJoCo twin of the session, stepped with the same held
inputs, whose state (and poses) come along in each state message (``scene.Twin``).

A client's outgoing states go through its own latest-state-wins queue of ``WS_QUEUE_SIZE`` (1–2)
frames, drained by its own task, so a slow reader only loses intermediate states: the ticker, the
batcher and every other client keep going. Every send has a timeout (``WS_SEND_TIMEOUT_S``); a send
that times out ends the connection, as does the server's websocket ping going unanswered (uvicorn's
``--ws-ping-interval`` / ``--ws-ping-timeout``, 20 s each by default), so a client that vanishes
without closing is noticed. The session itself is kept until its TTL.

A malformed message gets ``{"type": "error", ...}`` (the connection stays open); an unknown session
gets an error and close code 4404; a bad ``mode``/``format`` query gets an error and close code 4422.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import struct
import time
from collections import deque
from collections.abc import Coroutine, Sequence
from dataclasses import dataclass, field
from typing import Generic, TypeVar
from urllib.parse import parse_qsl

import numpy as np
from numpy.typing import NDArray
from pydantic import TypeAdapter, ValidationError
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from neuroanimator.emulator_schemas import (
    ClientMessage,
    ShadowState,
    WsControls,
    WsError,
    WsPing,
    WsPong,
    WsStart,
    WsStarted,
    WsState,
)
from services.common.errors import ApiError, from_validation
from services.emulator import binary
from services.emulator.engine import Engine
from services.emulator.scene import Twin
from services.emulator.sessions import Session

log = logging.getLogger(__name__)
PATH_PREFIX = "/ws/sessions/"
_CLIENT: TypeAdapter[ClientMessage] = TypeAdapter(ClientMessage)
T = TypeVar("T")
Frame = str | bytes


def _error(exc: ApiError, seq: int | None = None) -> str:
    return WsError(**exc.body.model_dump(), seq=seq).model_dump_json()


class LatestQueue(Generic[T]):
    """A bounded queue whose ``put`` never waits: when full, the oldest item is dropped."""

    def __init__(self, size: int = 1) -> None:
        self._items: deque[T] = deque(maxlen=size)
        self._event = asyncio.Event()
        self.dropped = 0

    def __len__(self) -> int:
        return len(self._items)

    def put(self, item: T) -> None:
        if len(self._items) == self._items.maxlen:
            self.dropped += 1
        self._items.append(item)
        self._event.set()

    async def get(self) -> T:
        while not self._items:
            self._event.clear()
            await self._event.wait()
        return self._items.popleft()

    def clear(self) -> None:
        self._items.clear()


class ClientGone(Exception):
    """A send timed out: the client stopped reading or vanished."""


class Disconnected(Exception):
    """The client closed (or dropped) the connection."""


class AsgiSocket:
    """The server side of one websocket, straight on the ASGI ``receive``/``send`` of the server.

    Why not Starlette's ``WebSocket``: at thousands of messages a second, its per-message state checks
    and the exception-handling wrappers every ``send`` passes through are a measurable share of the
    CPU time of a step. A send after the client has gone raises ``Disconnected``."""

    def __init__(self, scope: Scope, receive: Receive, send: Send) -> None:
        self.scope = scope
        self.receive = receive  # the server's own: one coroutine layer less per message
        self._send = send
        self.query: dict[str, str] = dict(parse_qsl(scope.get("query_string", b"").decode("latin-1")))

    async def accept(self) -> None:
        msg = await self.receive()
        if msg["type"] != "websocket.connect":
            raise Disconnected(f"expected websocket.connect, got {msg['type']}")
        await self._send({"type": "websocket.accept"})

    def send(self, frame: Frame) -> Coroutine[None, None, None]:
        """Send a binary (``bytes``) or text (``str``) message (a plain function returning the send's
        coroutine: one coroutine layer less per message)."""
        if isinstance(frame, bytes):
            return self._raw({"type": "websocket.send", "bytes": frame})
        return self._raw({"type": "websocket.send", "text": frame})

    async def close(self, code: int = 1000, reason: str = "") -> None:
        await self._raw({"type": "websocket.close", "code": code, "reason": reason})

    async def _raw(self, message: Message) -> None:
        try:
            await self._send(message)
        except (OSError, RuntimeError) as exc:  # uvicorn: ClientDisconnected; others: a closed socket
            raise Disconnected(str(exc)) from exc


@dataclass
class Held:
    """The inputs real-time mode steps with: validated, clipped, and the ``seq`` they came with."""

    controls: NDArray[np.float32]
    forces: NDArray[np.float32]
    seq: int | None = None
    clipped_controls: list[int] = field(default_factory=list)
    clipped_forces: list[int] = field(default_factory=list)


class Connection:
    """One websocket client of one session."""

    def __init__(self, websocket: AsgiSocket, engine: Engine, sess: Session) -> None:
        s = engine.settings
        self.ws = websocket
        self.engine = engine
        self.sid = sess.id
        self.emu = sess.emu
        self.mode = "lockstep"
        self.format = "json"
        self.poses = False
        self.twin: Twin | None = None
        self.period = self.emu.super_timestep * s.ws_realtime_scale
        self.timeout = s.ws_send_timeout_s
        u, cu, f, cf = engine.inputs(sess, [0.0] * self.emu.num_controls, [0.0] * self.emu.num_forces)
        self.held = Held(u, f, None, cu, cf)
        self.queue: LatestQueue[Frame] = LatestQueue(s.ws_queue_size)
        self.pushed = 0
        self._send_lock = asyncio.Lock()
        self._ticker: asyncio.Task[None] | None = None
        self._pusher: asyncio.Task[None] | None = None
        self._main: asyncio.Task[object] | None = None
        self.gone = False
        # for binary lock-step frames, the hot path: their layout and the inputs' range as Python values
        width = self.emu.num_controls + self.emu.num_forces
        self._frame = struct.Struct(f"<4sI{width}f")
        self._bounds = list(zip(self.emu.input_low.tolist(), self.emu.input_high.tolist(), strict=True))
        self._batcher = engine.batcher(self.emu)
        self._latency = engine.metrics.latency(self.emu.model, "ws")

    # ------------------------------------------------------------------ sending
    async def reply(self, frame: Frame) -> None:
        """A lock-step reply. No timeout here (a timer per message is measurable at 10,000 steps/s):
        a client that stops reading blocks only its own connection, whose session then expires."""
        if self._pusher is None:  # no real-time pusher: this task is the only one sending
            await self.ws.send(frame)
            return
        async with self._send_lock:
            await self.ws.send(frame)

    async def send(self, frame: Frame) -> None:
        async with self._send_lock:
            try:
                # asyncio.timeout, unlike wait_for, starts no task per message (this is the hot path)
                async with asyncio.timeout(self.timeout):
                    await self.ws.send(frame)
            except TimeoutError as exc:
                raise ClientGone(f"a send took longer than {self.timeout} s") from exc

    async def _push(self) -> None:
        """Drains the latest-state-wins queue; a send timeout ends the whole connection."""
        try:
            while True:
                frame = await self.queue.get()
                await self.send(frame)
                self.pushed += 1
        except ClientGone:
            log.info("websocket client gone (send timeout)", extra={"session": self.sid})
        except Disconnected:
            log.info("websocket closed while pushing", extra={"session": self.sid})
        self.gone = True
        if self._main is not None:
            self._main.cancel()

    # ------------------------------------------------------------------ stepping
    async def _step(
        self, sess: Session, u: NDArray[np.float32], f: NDArray[np.float32], transport: str
    ) -> NDArray[np.float32]:
        t0 = time.perf_counter()
        async with sess.lock:
            out = await self.engine.batcher(sess.emu).step(sess, u, f)
        self.engine.metrics.latency(sess.emu.model, transport).observe(time.perf_counter() - t0)
        return out

    def _state(
        self, sess: Session, state: NDArray[np.float32], seq: int | None, cu: list[int], cf: list[int]
    ) -> Frame:
        clipped = bool(cu or cf)
        if self.format == "binary":
            return binary.encode_ws_state(seq, sess.steps, binary.CLIPPED if clipped else binary.OK, state)
        kin = self.emu.kinematics if self.poses else None
        shadow = None
        if self.twin is not None:
            twin = self.twin.state
            shadow = ShadowState(
                state=twin.tolist(),
                poses=None if kin is None else kin.poses(twin[None])[0].tolist(),
                diverged=self.twin.diverged,
            )
        msg = WsState(
            seq=seq,
            state=state.tolist(),
            t=sess.t,
            steps=sess.steps,
            clipped=clipped,
            clipped_controls=cu,
            clipped_forces=cf,
            poses=None if kin is None else kin.poses(state[None])[0].tolist(),
            shadow=shadow,
        )
        return msg.model_dump_json(exclude={k for k in ("poses", "shadow") if getattr(msg, k) is None})

    async def _tick(self) -> None:
        """Real-time mode: one super-step every ``period`` of wall time with the latest inputs. A tick
        that falls more than a period behind is skipped (never a burst of catch-up steps)."""
        loop = asyncio.get_running_loop()
        nxt = loop.time() + self.period
        while True:
            delay = nxt - loop.time()
            if delay > 0:
                await asyncio.sleep(delay)
            nxt += self.period
            now = loop.time()
            if now - nxt > self.period:
                nxt = now + self.period
            held = self.held
            try:
                sess = self.engine.store.get(self.sid)
                out = await self._step(sess, held.controls, held.forces, "ws-realtime")
                if self.twin is not None:
                    self.twin.step(held.controls, held.forces)
            except ApiError as exc:  # diverged, expired or deleted: say so and stop ticking
                self.queue.put(_error(exc, held.seq))
                self.mode = "lockstep"
                return
            self.queue.put(self._state(sess, out, held.seq, held.clipped_controls, held.clipped_forces))

    def _inputs(self, controls: Sequence[float], forces: Sequence[float], seq: int | None) -> Held:
        sess = self.engine.store.get(self.sid)
        u, cu, f, cf = self.engine.inputs(sess, controls, forces)
        return Held(u, f, seq, cu, cf)

    # ------------------------------------------------------------------ modes
    async def start(
        self,
        mode: str,
        fmt: str | None,
        seq: int | None = None,
        poses: bool | None = None,
        shadow: bool | None = None,
    ) -> str:
        want_poses = self.poses if poses is None else poses
        want_shadow = (self.twin is not None) if shadow is None else shadow
        if (fmt or self.format) == "binary" and (want_poses or want_shadow):
            raise ApiError(
                422,
                "needs_json",
                "poses and shadow come in JSON state messages only; ask for format json "
                "(or leave poses and shadow off for binary frames)",
                field="format",
                expected="json",
                got="binary",
            )
        if fmt is not None:
            self.format = fmt
        self.poses = want_poses
        if shadow is True:  # (re)start the twin from the session's current state
            sess = self.engine.store.get(self.sid)
            self.twin = Twin(sess.emu.physical, sess.emu.substeps, sess.state)
        elif shadow is False:
            self.twin = None
        if mode == "realtime" and self._ticker is None:
            self._pusher = asyncio.create_task(self._push(), name=f"ws-push-{self.sid}")
            self._ticker = asyncio.create_task(self._tick(), name=f"ws-tick-{self.sid}")
        elif mode == "lockstep":
            await self._stop_realtime()
        self.mode = mode
        e = self.emu
        return WsStarted(
            seq=seq,
            mode="realtime" if mode == "realtime" else "lockstep",
            format="binary" if self.format == "binary" else "json",
            super_timestep=e.super_timestep,
            period_s=self.period,
            state_size=e.state_size,
            num_controls=e.num_controls,
            num_forces=e.num_forces,
            poses=self.poses,
            shadow=self.twin is not None,
        ).model_dump_json()

    async def _stop_realtime(self) -> None:
        for task in (self._ticker, self._pusher):
            if task is not None and task is not asyncio.current_task():
                task.cancel()
                with contextlib.suppress(asyncio.CancelledError):
                    await task
        self._ticker = self._pusher = None
        self.queue.clear()

    # ------------------------------------------------------------------ messages
    async def on_text(self, text: str) -> Frame | None:
        seq = None
        try:
            try:
                raw = json.loads(text)
            except json.JSONDecodeError as exc:
                raise ApiError(
                    422, "malformed_json", f"the message is not JSON: {exc}", got=text[:200]
                ) from exc
            if isinstance(raw, dict) and isinstance(raw.get("seq"), int):
                seq = raw["seq"]
            try:
                msg = _CLIENT.validate_python(raw)
            except ValidationError as exc:
                raise from_validation([dict(e) for e in exc.errors()]) from exc
            if isinstance(msg, WsPing):
                return WsPong(seq=msg.seq).model_dump_json()
            if isinstance(msg, WsStart):
                return await self.start(msg.mode, msg.format, msg.seq, msg.poses, msg.shadow)
            if isinstance(msg, WsControls):
                self.held = self._inputs(msg.controls, msg.forces, msg.seq)
                return None
            if self.mode == "realtime":
                raise ApiError(
                    409,
                    "wrong_mode",
                    "step messages are for lock-step mode; in real-time mode send controls messages "
                    '(or {"type": "start", "mode": "lockstep"} first)',
                    field="type",
                    expected="controls",
                    got="step",
                )
            return await self.lockstep(msg.controls, msg.forces, msg.seq)
        except ApiError as exc:
            return _error(exc, seq)

    async def on_binary(self, data: bytes) -> Frame | None:
        if len(data) == self._frame.size and self.mode == "lockstep" and self.twin is None:
            magic, number, *given = self._frame.unpack(data)
            # NaN fails both comparisons, so it takes the general path below and is named there
            if magic == binary.WS_CLIENT_MAGIC and all(
                lo <= v <= hi for (lo, hi), v in zip(self._bounds, given, strict=True)
            ):
                return await self._lockstep_fast(None if number == binary.NO_SEQ else number, tuple(given))
        e = self.emu
        seq = None
        try:
            seq, values = binary.parse_ws_frame(
                data,
                e.num_controls + e.num_forces,
                f"model {e.model!r} ({e.num_controls} controls, {e.num_forces} forces)",
            )
            sess = self.engine.store.get(self.sid)
            u, cu, f, cf = self.engine.inputs_array(sess, values)
            held = Held(u, f, seq, cu, cf)
            if self.mode == "realtime":
                self.held = held
                return None
            return await self._lockstep(sess, held)
        except ApiError as exc:
            return _error(exc, seq)

    async def _lockstep_fast(self, seq: int | None, values: tuple[float, ...]) -> Frame:
        """A binary lock-step frame whose inputs are all in range: ``_lockstep`` in fewer operations
        (no arrays for one session's inputs, the batcher and latency series looked up once)."""
        try:
            sess = self.engine.store.get(self.sid)
            t0 = time.perf_counter()
            if not sess.try_lock():
                await sess.lock.acquire()
            try:
                out = await self._batcher.step_row(sess, values)
            finally:
                sess.unlock()
            self._latency.observe(time.perf_counter() - t0)
        except ApiError as exc:
            return _error(exc, seq)
        if self.format == "binary":
            return binary.encode_ws_state(seq, sess.steps, binary.OK, out)
        return self._state(sess, out, seq, [], [])

    async def lockstep(self, controls: Sequence[float], forces: Sequence[float], seq: int | None) -> Frame:
        sess = self.engine.store.get(self.sid)
        u, cu, f, cf = self.engine.inputs(sess, controls, forces)
        return await self._lockstep(sess, Held(u, f, seq, cu, cf))

    async def _lockstep(self, sess: Session, held: Held) -> Frame:
        out = await self._step(sess, held.controls, held.forces, "ws")
        if self.twin is not None:
            self.twin.step(held.controls, held.forces)
        return self._state(sess, out, held.seq, held.clipped_controls, held.clipped_forces)

    # ------------------------------------------------------------------ the connection
    async def run(self) -> None:
        self._main = asyncio.current_task()
        try:
            while True:
                msg = await self.ws.receive()
                if msg["type"] == "websocket.disconnect":
                    break
                data = msg.get("bytes")
                reply = await (
                    self.on_binary(data) if data is not None else self.on_text(msg.get("text") or "")
                )
                if reply is not None:
                    await self.reply(reply)
        except (Disconnected, ClientGone):
            pass
        except asyncio.CancelledError:
            if not self.gone:
                raise
        finally:
            self._main = None
            await self._stop_realtime()


async def session_socket(ws: AsgiSocket, engine: Engine, sid: str) -> None:
    """One websocket client of session ``sid``, from the handshake to the close."""
    await ws.accept()
    try:
        sess = engine.store.get(sid)
    except ApiError as exc:
        await ws.send(_error(exc))
        await ws.close(code=4404)
        return
    conn = Connection(ws, engine, sess)
    q = ws.query
    started: str | None = None
    if {"mode", "format", "poses", "shadow"} & set(q):
        try:
            start = WsStart.model_validate(
                {
                    "type": "start",
                    "mode": q.get("mode", "lockstep"),
                    "format": q.get("format"),
                    "poses": q.get("poses"),
                    "shadow": q.get("shadow"),
                }
            )
            started = await conn.start(start.mode, start.format, None, start.poses, start.shadow)
        except ValidationError as exc:
            await ws.send(_error(from_validation([dict(e) for e in exc.errors()])))
            await ws.close(code=4422)
            return
        except ApiError as exc:
            await ws.send(_error(exc))
            await ws.close(code=4422)
            return
    engine.connections.add(conn)
    try:
        if started is not None:
            await conn.send(started)
        await conn.run()
    finally:
        await conn._stop_realtime()  # (a client gone before ``started`` leaves no ticker behind)
        engine.connections.discard(conn)
        log.info("websocket closed", extra={"session": sid, "dropped_states": conn.queue.dropped})


class SessionSocketRoute:
    """Pure ASGI middleware serving ``/ws/sessions/{id}`` (inside the API-key and CORS middleware).

    The connection runs in a task of its own: every message resumes the connection's coroutine, and
    resuming it under the app's middleware stack would walk a dozen wrapper frames each time."""

    def __init__(self, app: ASGIApp, engine: Engine) -> None:
        self.app = app
        self.engine = engine

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        path: str = scope.get("path", "")
        sid = path[len(PATH_PREFIX) :]
        if scope["type"] != "websocket" or not path.startswith(PATH_PREFIX) or not sid or "/" in sid:
            await self.app(scope, receive, send)
            return
        ws = AsgiSocket(scope, receive, send)
        # (cancelling this coroutine, as a server shutting down does, cancels the task it awaits)
        await asyncio.get_running_loop().create_task(self._serve(ws, sid), name=f"ws-{sid}")

    async def _serve(self, ws: AsgiSocket, sid: str) -> None:
        with contextlib.suppress(Disconnected, ClientGone):
            await session_socket(ws, self.engine, sid)
