"""``BodyLimitMiddleware``: every request body is bounded and checked before anything parses it.

A pure ASGI middleware, outside the API-key check and the routes, so one rule covers every endpoint of
a service (its fast paths included):

- a ``Content-Length`` above the path's limit is answered 413 at once, without reading a byte;
- a body sent without one (chunked) is counted as it streams and refused with 413 the moment it
  passes the limit;
- a JSON body (``application/json``, ``+json``, or no content type) is read whole (it is bounded)
  and refused with 400 when it is not UTF-8 or nests arrays and objects deeper than ``max_depth``
  (Python's parser would recurse once per level: 1,000 ``[`` raise RecursionError), so that what
  reaches a route is text a parser can read in bounded time and stack;
- a body sent with more than one ``Content-Type`` is refused with 400: what is checked here (the
  last header) and what a route parses by (Starlette reads the first) must be the same body type.

Errors are the project's JSON error (``{"error", "message", "field", "expected", "got"}``), written here
without the wire types so that the dashboard's server can use this module too.
"""

from __future__ import annotations

import json
import re
from collections.abc import Sequence
from typing import Any

from starlette.applications import Starlette
from starlette.exceptions import HTTPException
from starlette.types import ASGIApp, Message, Receive, Scope, Send

MAX_JSON_DEPTH = 32
"""Deepest nesting of arrays and objects in a JSON body (the services' own requests nest 5 deep)."""
_STRING = re.compile(rb'"[^"\\]*(?:\\.[^"\\]*)*"')
_NOT_BRACKETS = bytes(b for b in range(256) if b not in b"[]{}")
_SQUARE = bytes.maketrans(b"{}", b"[]")
_OPEN = ord("[")


class BodyTooLarge(HTTPException):
    """A body that passed its limit while streaming; raised out of ``receive`` into whatever reads it
    (an ``HTTPException``, so that FastAPI's body reading passes it on as it is), answered 413."""

    error = "body_too_large"

    def __init__(self, limit: int, path: str) -> None:
        super().__init__(413, too_large_message(limit, path))
        self.limit = limit


def too_large_message(limit: int, path: str) -> str:
    return f"the body of a request to {path} may be at most {limit} bytes"


def error_json(
    status: int, error: str, message: str, expected: Any = None, got: Any = None, field: str = "body"
) -> bytes:
    """The project's JSON error about the body (``ErrorBody``'s fields)."""
    body = {"error": error, "message": message, "field": field, "expected": expected, "got": got}
    return json.dumps(body, separators=(",", ":")).encode()


async def respond(send: Send, status: int, body: bytes, headers: Sequence[tuple[bytes, bytes]] = ()) -> None:
    """A complete response of JSON ``body``; the connection is closed after it (the rest of a refused
    body is not read)."""
    await send(
        {
            "type": "http.response.start",
            "status": status,
            "headers": [
                (b"content-type", b"application/json"),
                (b"content-length", str(len(body)).encode()),
                (b"connection", b"close"),
                *headers,
            ],
        }
    )
    await send({"type": "http.response.body", "body": body})


def too_deep(body: bytes, limit: int) -> bool:
    """Whether a JSON text nests arrays and objects more than ``limit`` deep (strings ignored).

    Done at C speed for ordinary bodies: fewer brackets than the limit cannot be too deep; else the
    strings are cut out, every byte but brackets dropped, ``{}`` made ``[]``, and innermost pairs
    removed, one level per pass: a balanced text gone within ``limit`` passes is not too deep. What
    is left after that (too deep, or unbalanced: the parser's concern) is walked bracket by bracket,
    stopping at the first level past the limit.
    """
    if body.count(b"[") + body.count(b"{") <= limit:
        return False
    # without escaped quotes, the strings are every other piece between quotes (faster than the regex)
    bare = b"".join(body.split(b'"')[::2]) if b"\\" not in body else _STRING.sub(b"", body)
    brackets = bare.translate(_SQUARE, _NOT_BRACKETS)
    rest = brackets
    for _ in range(limit):
        fewer = rest.replace(b"[]", b"")
        if not fewer:
            return False
        if len(fewer) == len(rest):
            break  # no pair left to remove: unbalanced
        rest = fewer
    depth = 0
    for b in brackets:
        depth = depth + 1 if b == _OPEN else depth - 1
        if depth > limit:
            return True
    return False


def body_problem(body: bytes, max_depth: int) -> tuple[str, str, str] | None:
    """(error, message, expected) of a JSON body that no parser should be handed, else None."""
    if not body.isascii():
        try:
            body.decode("utf-8")
        except UnicodeDecodeError as exc:
            return (
                "invalid_encoding",
                f"the body is not UTF-8 text: byte {exc.start} is {body[exc.start : exc.start + 1]!r}; "
                "JSON must be sent as UTF-8",
                "UTF-8 JSON text",
            )
    if too_deep(body, max_depth):
        return (
            "too_deep",
            f"the JSON body nests arrays and objects more than {max_depth} levels deep",
            f"at most {max_depth} levels of nesting",
        )
    return None


def _is_json(ctype: bytes | None) -> bool:
    if ctype is None:
        return True
    main = ctype.split(b";")[0].strip().lower()
    return main == b"application/json" or main.endswith(b"+json")


class BodyLimitMiddleware:
    """Bounds every request body (``max_bytes``, or the first of ``per_path``'s (path regex, limit)
    that matches) and refuses JSON that is not UTF-8 or nests too deep; see the module's text."""

    def __init__(
        self,
        app: ASGIApp,
        max_bytes: int,
        per_path: Sequence[tuple[str, int]] = (),
        max_depth: int = MAX_JSON_DEPTH,
        json_per_path: Sequence[tuple[str, int, str]] = (),
    ) -> None:
        self.app = app
        self.max_bytes = max_bytes
        self.per_path = [(re.compile(p), n) for p, n in per_path]
        self.max_depth = max_depth
        self.json_per_path = [(re.compile(p), n, why) for p, n, why in json_per_path]

    def limit(self, path: str) -> int:
        for pattern, n in self.per_path:
            if pattern.fullmatch(path):
                return n
        return self.max_bytes

    def json_limit(self, path: str) -> tuple[int, str] | None:
        """A smaller limit for JSON bodies of ``path`` (a path with a binary form for large bodies), and
        what to say when it is passed."""
        for pattern, n, why in self.json_per_path:
            if pattern.fullmatch(path):
                return n, why
        return None

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        length: bytes | None = None
        ctype: bytes | None = None
        ctypes = 0
        chunked = False
        for name, value in scope["headers"]:
            if name == b"content-length":
                length = value
            elif name == b"content-type":
                ctype = value
                ctypes += 1
            elif name == b"transfer-encoding":
                chunked = True
        if length is None and not chunked:  # HTTP/1.1: no body at all
            await self.app(scope, receive, send)
            return
        path: str = scope["path"]
        limit = self.limit(path)
        if length is not None and length.isdigit() and int(length) > limit:
            await self._too_large(send, limit, path, got=f"Content-Length: {int(length)}")
            return
        smaller = self.json_limit(path) if _is_json(ctype) else None
        if smaller is not None:  # checked before a byte is read: parsing a large JSON body costs seconds
            limit = min(limit, smaller[0])
            if length is not None and length.isdigit() and int(length) > limit:
                body = error_json(
                    413, "body_too_large", smaller[1], f"<= {limit} bytes", f"Content-Length: {int(length)}"
                )
                await respond(send, 413, body)
                return
        if ctypes > 1:
            msg = f"the request has {ctypes} Content-Type headers; send one, naming the body's type"
            body = error_json(400, "bad_request", msg, "one Content-Type header", ctypes, "content-type")
            await respond(send, 400, body)
            return
        if _is_json(ctype):
            await self._json(scope, receive, send, limit)
        else:
            await self._streamed(scope, receive, send, limit)

    async def _too_large(self, send: Send, limit: int, path: str, got: str) -> None:
        body = error_json(413, "body_too_large", too_large_message(limit, path), f"<= {limit} bytes", got)
        await respond(send, 413, body)

    async def _json(self, scope: Scope, receive: Receive, send: Send, limit: int) -> None:
        """Read the whole (bounded) body, check it, and hand it on as one message."""
        chunks: list[bytes] = []
        size = 0
        while True:
            message = await receive()
            if message["type"] == "http.disconnect":
                return  # the client is gone: nobody to answer
            chunk: bytes = message.get("body", b"")
            size += len(chunk)
            if size > limit:
                await self._too_large(send, limit, scope["path"], got=f"more than {limit} bytes")
                return
            chunks.append(chunk)
            if not message.get("more_body", False):
                break
        body = b"".join(chunks)
        problem = body_problem(body, self.max_depth)
        if problem is not None:
            error, msg, expected = problem
            await respond(send, 400, error_json(400, error, msg, expected, f"{len(body)} bytes"))
            return
        replayed = False

        async def replay() -> Message:
            nonlocal replayed
            if not replayed:
                replayed = True
                return {"type": "http.request", "body": body, "more_body": False}
            return await receive()  # after the body: http.disconnect, as the app expects

        await self.app(scope, replay, send)

    async def _streamed(self, scope: Scope, receive: Receive, send: Send, limit: int) -> None:
        """Pass the body on as it streams, counting; past the limit, ``BodyTooLarge`` is raised out of
        ``receive`` and answered here unless the app already started its response."""
        size = 0
        started = False

        async def counted() -> Message:
            nonlocal size
            message = await receive()
            if message["type"] == "http.request":
                size += len(message.get("body", b""))
                if size > limit:
                    raise BodyTooLarge(limit, scope["path"])
            return message

        async def watched(message: Message) -> None:
            nonlocal started
            if message["type"] == "http.response.start":
                started = True
            await send(message)

        try:
            await self.app(scope, counted, watched)
        except BodyTooLarge as exc:
            if started:
                raise
            await self._too_large(send, exc.limit, scope["path"], got=f"more than {exc.limit} bytes")


def limit_bodies(
    app: Starlette,
    max_bytes: int,
    per_path: Sequence[tuple[str, int]] = (),
    json_per_path: Sequence[tuple[str, int, str]] = (),
) -> None:
    """Add ``BodyLimitMiddleware`` to ``app`` (outside every middleware added before this call);
    ``json_per_path``: (path regex, limit, message) for JSON bodies smaller than the path's others."""
    app.add_middleware(
        BodyLimitMiddleware, max_bytes=max_bytes, per_path=per_path, json_per_path=json_per_path
    )
