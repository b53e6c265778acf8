"""Real-time mode of a websocket connection.

The ticker advances the session every period of wall time (the model's Δt × ``WS_REALTIME_SCALE``)
with the latest inputs the client sent, and puts each state frame on the connection's own
latest-state-wins queue (``WS_QUEUE_SIZE`` frames); the pusher drains that queue to the socket. A slow
reader thus only loses intermediate states: the ticker, the batcher and every other client keep going.
A push that times out (``WS_SEND_TIMEOUT_S``) ends the connection.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
from dataclasses import dataclass
from typing import Protocol

from services.emulator.error_mapping import ws_error
from services.emulator.errors import EmulatorError
from services.emulator.inputs import CheckedInputs
from services.emulator.registry import LoadedEmulator
from services.emulator.service import EmulatorService
from services.emulator.stepping import Lane
from services.emulator.ws.transport import ClientGone, Disconnected, Frame, LatestQueue, Sender

log = logging.getLogger(__name__)


@dataclass(slots=True)
class HeldInputs:
    """Checked inputs and the ``seq`` of the message they came with (real-time mode steps with the
    latest of them; its state messages echo that ``seq``)."""

    inputs: CheckedInputs
    seq: int | None = None


class Host(Protocol):
    """What real-time mode uses of its connection (``ws.connection.Connection``)."""

    service: EmulatorService
    emu: LoadedEmulator
    sid: str
    sender: Sender
    queue: LatestQueue[Frame]
    period_s: float
    held: HeldInputs

    async def advance(self, held: HeldInputs, lane: Lane) -> Frame: ...

    def end(self) -> None: ...


class Realtime:
    """The ticker and pusher tasks of one connection in real-time mode."""

    def __init__(self, conn: Host) -> None:
        self.conn = conn
        self.lane = conn.service.stepper.lane(conn.emu, "ws-realtime")
        self._ticker: asyncio.Task[None] | None = None
        self._pusher: asyncio.Task[None] | None = None

    @property
    def ticking(self) -> bool:
        """False once the ticker stopped on an error (diverged, expired or deleted session)."""
        return self._ticker is not None and not self._ticker.done()

    def start(self) -> None:
        sid = self.conn.sid
        if self._pusher is None:
            self.conn.sender.shared = True
            self._pusher = asyncio.create_task(self._push(), name=f"ws-push-{sid}")
        if not self.ticking:
            self._ticker = asyncio.create_task(self._tick(), name=f"ws-tick-{sid}")

    async def stop(self) -> None:
        for task in (self._ticker, self._pusher):
            if task is not None and task is not asyncio.current_task():
                task.cancel()
                with contextlib.suppress(asyncio.CancelledError):
                    await task
        self._ticker = self._pusher = None
        self.conn.sender.shared = False

    async def _tick(self) -> None:
        """One super-step every period with the latest inputs. A tick that falls more than a period
        behind is skipped (never a burst of catch-up steps); an error is sent and stops the ticking."""
        conn = self.conn
        period = conn.period_s
        loop = asyncio.get_running_loop()
        nxt = loop.time() + period
        while True:
            delay = nxt - loop.time()
            if delay > 0:
                await asyncio.sleep(delay)
            nxt += period
            now = loop.time()
            if now - nxt > period:
                nxt = now + period
            held = conn.held
            try:
                frame = await conn.advance(held, self.lane)
            except EmulatorError as exc:
                conn.queue.put(ws_error(exc, held.seq))
                return
            conn.queue.put(frame)

    async def _push(self) -> None:
        """Drains the latest-state-wins queue; a send timeout ends the whole connection."""
        conn = self.conn
        try:
            while True:
                frame = await conn.queue.get()
                await conn.sender.send(frame)
        except ClientGone:
            log.info("websocket client gone (send timeout)", extra={"session": conn.sid})
        except Disconnected:
            log.info("websocket closed while pushing", extra={"session": conn.sid})
        conn.end()
