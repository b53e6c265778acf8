"""The binary ``POST /step`` served as plain ASGI, beside FastAPI's routing.

Why: a game server stepping thousands of sessions per request sends them many times a second, and
each request through FastAPI's stack (middleware layers, route matching, dependency resolution, a
``Request`` object, the body gathered through it) costs about 0.3-0.5 ms of a 2-3 ms round trip on
this machine, as measured. This middleware answers exactly ``POST /step`` with ``Content-Type:
application/octet-stream`` by calling the same ``binary_step`` the FastAPI route would; everything
else (the JSON form included) passes through. It sits inside the API-key and CORS middleware, so
authentication and browsers are treated exactly as on the route, and the route stays in the OpenAPI
document. An ``ApiError`` is answered as the app's exception handler would (its JSON ``ErrorBody``).
"""

from __future__ import annotations

from starlette.types import ASGIApp, Message, Receive, Scope, Send

from services.common.errors import ApiError
from services.emulator.binary import MAX_ID_WIDTH, REQUEST_HEADER
from services.emulator.engine import Engine
from services.emulator.routes.step import OCTET, binary_step

MAX_ROW_FLOATS = 256
"""Controls plus forces per session that a binary body may carry (for the body-size cap only)."""


def _content_type(scope: Scope) -> bytes:
    for name, value in scope["headers"]:
        if name == b"content-type":
            ctype: bytes = value.split(b";")[0].strip().lower()
            return ctype
    return b""


class BinaryStepRoute:
    """Pure ASGI middleware: binary ``POST /step`` straight to ``binary_step``."""

    def __init__(self, app: ASGIApp, engine: Engine) -> None:
        self.app = app
        self.engine = engine
        self.octet = OCTET.encode()
        self.max_body = REQUEST_HEADER.size + engine.settings.max_batch * (MAX_ID_WIDTH + 4 * MAX_ROW_FLOATS)

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if (
            scope["type"] != "http"
            or scope["method"] != "POST"
            or scope["path"] != "/step"
            or _content_type(scope) != self.octet
        ):
            await self.app(scope, receive, send)
            return
        try:
            body = await self._body(receive)
            out = await binary_step(self.engine, body)
        except ApiError as exc:
            await _respond(send, exc.status, b"application/json", exc.body.model_dump_json().encode())
            return
        await _respond(send, 200, self.octet, out)

    async def _body(self, receive: Receive) -> bytes:
        chunks: list[bytes] = []
        size = 0
        more = True
        while more:
            message: Message = await receive()
            if message["type"] == "http.disconnect":
                raise ApiError(400, "client_disconnected", "the client went away before sending its body")
            chunk = message.get("body", b"")
            size += len(chunk)
            if size > self.max_body:
                raise ApiError(
                    413,
                    "body_too_large",
                    f"a binary POST /step body may be at most {self.max_body} bytes "
                    f"(MAX_BATCH={self.engine.settings.max_batch} sessions)",
                    field="body",
                    expected=f"<= {self.max_body} bytes",
                    got=f"> {self.max_body} bytes",
                )
            chunks.append(chunk)
            more = message.get("more_body", False)
        return chunks[0] if len(chunks) == 1 else b"".join(chunks)


async def _respond(send: Send, status: int, ctype: bytes, body: bytes) -> None:
    await send(
        {
            "type": "http.response.start",
            "status": status,
            "headers": [(b"content-type", ctype), (b"content-length", str(len(body)).encode())],
        }
    )
    await send({"type": "http.response.body", "body": body})
