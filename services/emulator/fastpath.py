"""The binary ``POST /step`` (proto/frames.md): a thin transport over ``Stepper.step_block``, served
as plain ASGI beside FastAPI's routing.

Why plain ASGI: a game server stepping thousands of sessions per request sends them many times a
second, and each request through FastAPI's stack (middleware layers, route matching, dependency
resolution, a ``Request`` object, the body gathered through it) costs about 0.3-0.5 ms of a 2-3 ms
round trip on this machine, as measured. This middleware answers exactly ``POST /step`` with
``Content-Type: application/octet-stream`` by calling the same ``binary_step`` the FastAPI route would;
everything else (the JSON form included) passes through. It sits inside the API-key and CORS
middleware, so authentication and browsers are treated exactly as on the route, and the route stays
in the OpenAPI document. Errors are answered as the app's handlers would (``error_mapping.py``).
"""

from __future__ import annotations

import numpy as np
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from services.emulator import binary
from services.emulator.error_mapping import http_json
from services.emulator.errors import ClientDisconnected, EmulatorError, TooLarge
from services.emulator.service import EmulatorService

MAX_ROW_FLOATS = 256
"""Controls plus forces per session that a binary body may carry (for the body-size cap only)."""


async def binary_step(service: EmulatorService, body: bytes) -> bytes:
    """Parse a binary batch, step it (``Stepper.step_block``: the whole request fails on a problem and
    steps nothing) and encode the answer."""
    parsed = binary.parse_batch_request(body, service.settings.max_batch)
    n = parsed.count
    res = service.store.resolve_block(parsed.id_block, parsed.width)
    emu = res.emu
    if emu is None:  # no known session: nothing to step, every status says so
        parsed.check_whole_rows()
        return binary.encode_batch_response(
            np.full(n, binary.UNKNOWN, np.uint8), np.zeros((n, 0), np.float32)
        )
    nu, nf = emu.num_controls, emu.num_forces
    rows = parsed.rows(nu + nf, f"model {emu.model!r} ({nu} controls, {nf} forces)")

    def label(i: int) -> tuple[str, str]:
        return f"items[{i}].", f" of session {parsed.ids[i]!r}"

    out = await service.stepper.step_block(res, rows, label)
    return binary.encode_batch_response(out.status, out.states, out.outside)


def _content_type(scope: Scope) -> bytes:
    for name, value in scope["headers"]:
        if name == b"content-type":
            ctype: bytes = value.split(b";")[0].strip().lower()
            return ctype
    return b""


class BinaryStepRoute:
    """Pure ASGI middleware: binary ``POST /step`` straight to ``binary_step``."""

    def __init__(self, app: ASGIApp, service: EmulatorService) -> None:
        self.app = app
        self.service = service
        self.octet = binary.MEDIA_TYPE.encode()
        max_batch = service.settings.max_batch
        self.max_body = binary.REQUEST_HEADER.size + max_batch * (binary.MAX_ID_WIDTH + 4 * MAX_ROW_FLOATS)

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
            out = await binary_step(self.service, body)
        except EmulatorError as exc:
            status, err = http_json(exc)
            await _respond(send, status, b"application/json", err)
            return
        await _respond(send, 200, self.octet, out)

    async def _body(self, receive: Receive) -> bytes:
        chunks: list[bytes] = []
        size = 0
        more = True
        while more:
            message: Message = await receive()
            if message["type"] == "http.disconnect":
                raise ClientDisconnected("the client went away before sending its body")
            chunk = message.get("body", b"")
            size += len(chunk)
            if size > self.max_body:
                raise TooLarge(
                    f"a binary POST /step body may be at most {self.max_body} bytes "
                    f"(MAX_BATCH={self.service.settings.max_batch} sessions)",
                    code="body_too_large",
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
