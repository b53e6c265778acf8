"""``/ws/sessions/{id}`` served as plain ASGI: the handshake, a query's ``start``, then the connection."""

from __future__ import annotations

import asyncio
import contextlib
import logging

from starlette.types import ASGIApp, Receive, Scope, Send

from services.emulator.error_mapping import ws_close_code, ws_error
from services.emulator.errors import EmulatorError
from services.emulator.service import EmulatorService
from services.emulator.ws import protocol
from services.emulator.ws.connection import Connection
from services.emulator.ws.transport import AsgiSocket, ClientGone, Disconnected

log = logging.getLogger(__name__)
PATH_PREFIX = "/ws/sessions/"


async def session_socket(socket: AsgiSocket, service: EmulatorService, sid: str) -> None:
    """One websocket client of session ``sid``, from the handshake to the close. An unknown session
    or a bad query gets an error message, then the close code of that error."""
    await socket.accept()
    try:
        conn = Connection(socket, service, service.store.get(sid))
        start = protocol.start_from_query(socket.query)
        started = None if start is None else await conn.start(start)
    except EmulatorError as exc:
        await socket.send(ws_error(exc))
        await socket.close(code=ws_close_code(exc))
        return
    service.connections.add(conn)
    try:
        if started is not None:
            await conn.sender.send(started)
        await conn.run()
    finally:
        await conn.stop_realtime()  # (a client gone before ``started`` leaves no ticker behind)
        service.connections.discard(conn)
        log.info("websocket closed", extra={"session": sid, "dropped_states": conn.queue.dropped})


class SessionSocketRoute:
    """Pure ASGI middleware serving ``/ws/sessions/{id}`` (inside the API-key and CORS middleware).

    The connection runs in a task of its own: every message resumes the connection's coroutine, and
    resuming it under the app's middleware stack would walk a dozen wrapper frames each time."""

    def __init__(self, app: ASGIApp, service: EmulatorService) -> None:
        self.app = app
        self.service = service

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        path: str = scope.get("path", "")
        sid = path[len(PATH_PREFIX) :]
        if scope["type"] != "websocket" or not path.startswith(PATH_PREFIX) or not sid or "/" in sid:
            await self.app(scope, receive, send)
            return
        socket = AsgiSocket(scope, receive, send)
        # (cancelling this coroutine, as a server shutting down does, cancels the task it awaits)
        await asyncio.get_running_loop().create_task(self._serve(socket, sid), name=f"ws-{sid}")

    async def _serve(self, socket: AsgiSocket, sid: str) -> None:
        with contextlib.suppress(Disconnected, ClientGone):
            await session_socket(socket, self.service, sid)
