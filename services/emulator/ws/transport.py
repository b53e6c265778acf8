"""The websocket transport: the server side of a socket on raw ASGI, and how frames go out on it.

Why not Starlette's ``WebSocket``: at thousands of messages a second, its per-message state checks
and the exception-handling wrappers every ``send`` passes through are a measurable share of the CPU
time of a step.
"""

from __future__ import annotations

import asyncio
from collections import deque
from collections.abc import Coroutine
from typing import Generic, TypeVar
from urllib.parse import parse_qsl

from starlette.types import Message, Receive, Scope, Send

T = TypeVar("T")
Frame = str | bytes
"""A websocket message: text (JSON) or binary."""


class ClientGone(Exception):
    """A send timed out: the client stopped reading or vanished."""


class Disconnected(Exception):
    """The client closed (or dropped) the connection."""


class AsgiSocket:
    """The server side of one websocket, straight on the ASGI ``receive``/``send`` of the server. A
    send after the client has gone raises ``Disconnected``."""

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


class Sender:
    """How frames go out on one socket: replies to the client's messages, and frames pushed by a task
    of the server's own (real-time states), which set ``shared`` while they may send."""

    def __init__(self, socket: AsgiSocket, timeout_s: float) -> None:
        self.socket = socket
        self.timeout_s = timeout_s
        self.shared = False
        self._lock = asyncio.Lock()

    async def reply(self, frame: Frame) -> None:
        """A reply. No timeout here (a timer per message is measurable at 10,000 steps/s): a client
        that stops reading blocks only its own connection, whose session then expires."""
        if not self.shared:  # this task is the only one sending
            await self.socket.send(frame)
            return
        async with self._lock:
            await self.socket.send(frame)

    async def send(self, frame: Frame) -> None:
        """A pushed frame; ``ClientGone`` when the send takes longer than the timeout."""
        async with self._lock:
            try:
                # asyncio.timeout, unlike wait_for, starts no task per message (this is the hot path)
                async with asyncio.timeout(self.timeout_s):
                    await self.socket.send(frame)
            except TimeoutError as exc:
                raise ClientGone(f"a send took longer than {self.timeout_s} s") from exc


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
