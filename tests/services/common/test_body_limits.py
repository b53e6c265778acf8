"""``BodyLimitMiddleware``: oversized bodies refused before they are read, streamed ones counted, JSON
that is not UTF-8 or nests too deep refused before any parser sees it; all as the project's JSON error."""

from __future__ import annotations

import json
import socket
import time
from collections.abc import Iterator

import pytest
from fastapi import FastAPI, Request
from fastapi.testclient import TestClient
from pydantic import BaseModel

from services.common.errors import add_error_handlers
from services.common.limits import MAX_JSON_DEPTH, limit_bodies, too_deep
from tests.helpers import uvicorn_serving

KEYS = {"error", "message", "field", "expected", "got"}


class Thing(BaseModel):
    name: str


def _app(max_bytes: int = 1000) -> FastAPI:
    app = FastAPI()
    add_error_handlers(app)

    @app.post("/things")
    async def things(thing: Thing) -> str:
        return thing.name

    @app.post("/raw")
    async def raw(request: Request) -> int:
        return len(await request.body())

    @app.post("/big")
    async def big(request: Request) -> int:
        return len(await request.body())

    limit_bodies(app, max_bytes, per_path=[("/big", 100_000)])
    return app


def _is_error(r: object, status: int, error: str) -> dict[str, object]:
    assert r.status_code == status, r.text  # type: ignore[attr-defined]
    body: dict[str, object] = r.json()  # type: ignore[attr-defined]
    assert set(body) == KEYS
    assert body["error"] == error
    assert body["field"] == "body"
    return body


def test_small_bodies_pass_and_the_limit_is_per_path() -> None:
    client = TestClient(_app())
    assert client.post("/things", json={"name": "a"}).json() == "a"
    assert client.post("/big", content=b"x" * 50_000).json() == 50_000
    _is_error(client.post("/raw", content=b"x" * 1001), 413, "body_too_large")
    _is_error(client.post("/things", content=b'"' + b"x" * 2000 + b'"'), 413, "body_too_large")


def test_a_streamed_body_is_counted() -> None:
    client = TestClient(_app())

    def chunks(n: int) -> Iterator[bytes]:
        for _ in range(n):
            yield b"y" * 300

    assert client.post("/raw", content=chunks(3)).json() == 900
    _is_error(client.post("/raw", content=chunks(10)), 413, "body_too_large")
    _is_error(client.post("/things", content=chunks(10)), 413, "body_too_large")


@pytest.mark.parametrize(
    "body",
    [b'{"name": "\xff"}', b'{"name": "\xc3"}', b"\xfe\xff\x00{"],
    ids=["ff", "truncated", "utf16-bom"],
)
def test_json_that_is_not_utf8_is_the_projects_400(body: bytes) -> None:
    out = _is_error(TestClient(_app()).post("/things", content=body), 400, "invalid_encoding")
    assert "UTF-8" in str(out["message"])


def test_deep_nesting_is_refused_and_the_limit_is_exact() -> None:
    client = TestClient(_app(max_bytes=100_000))
    deep = b"[" * 1000
    _is_error(client.post("/things", content=deep), 400, "too_deep")
    _is_error(client.post("/things", content=b'{"a":' * 40 + b"1" + b"}" * 40), 400, "too_deep")
    at_limit = b"[" * MAX_JSON_DEPTH + b"]" * MAX_JSON_DEPTH
    assert client.post("/things", content=at_limit).status_code == 422  # parsed: not a Thing
    # brackets inside strings are not nesting
    quoted = json.dumps({"name": "[" * 500 + '\\"{' * 100}).encode()
    r = client.post("/things", content=quoted, headers={"content-type": "application/json"})
    assert r.status_code == 200, r.text
    # a non-JSON body is not parsed here, so not checked either
    assert client.post("/raw", content=deep, headers={"content-type": "text/plain"}).json() == 1000


def test_more_than_one_content_type_is_refused() -> None:
    """The check here reads one header, a route another (Starlette's first): a JSON body announced as
    text behind a JSON header would reach the parser unchecked."""
    client = TestClient(_app(max_bytes=100_000))
    for types in (("application/json", "text/plain"), ("text/plain", "application/json")):
        r = client.post("/things", content=b"[" * 1000, headers=[("content-type", t) for t in types])
        assert r.status_code == 400, r.text
        body = r.json()
        assert set(body) == KEYS and body["error"] == "bad_request" and body["field"] == "content-type"
        assert "2 Content-Type headers" in body["message"]
    assert client.post("/things", json={"name": "a"}).json() == "a"


def test_too_deep_against_a_plain_walk() -> None:
    def walk(text: bytes, limit: int) -> bool:
        depth = 0
        for ch in text:
            depth += 1 if ch in b"[{" else -1 if ch in b"]}" else 0
            if depth > limit:
                return True
        return False

    samples = [
        b"[]",
        b"[[[]]]",
        b"[{},{},[[]]]",
        b"]]][[[",
        b"[" * 5 + b"]" * 2 + b"[" * 4,
        b"{" * 3 + b"[" * 3,
        b"[[[]][[[[[]]]]]]",
        b'["[[[[[[[[", [[]]]',
    ]
    for text in samples:
        for limit in range(0, 8):
            plain = walk(text if b'"' not in text else b"[ [[]]]", limit)
            assert too_deep(text, limit) == plain, (text, limit)


@pytest.fixture
def server() -> Iterator[int]:
    """The test app under a real uvicorn on a free port."""
    with uvicorn_serving(_app()) as port:
        yield port


def test_an_oversized_content_length_is_answered_before_the_body_is_sent(server: int) -> None:
    """59 MB announced, not a byte of it sent: the 413 comes at once (the body is never read)."""
    with socket.create_connection(("127.0.0.1", server), timeout=5) as s:
        t0 = time.perf_counter()
        s.sendall(
            b"POST /things HTTP/1.1\r\nHost: x\r\nContent-Type: application/json\r\n"
            b"Content-Length: 59000000\r\n\r\n"
        )
        reply = b""
        while b"\r\n\r\n" not in reply or not reply.rstrip().endswith(b"}"):
            got = s.recv(65536)
            if not got:
                break
            reply += got
        took = time.perf_counter() - t0
    head, _, body = reply.partition(b"\r\n\r\n")
    assert head.startswith(b"HTTP/1.1 413"), reply[:200]
    assert json.loads(body)["error"] == "body_too_large"
    assert took < 1.0
