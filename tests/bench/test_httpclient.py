"""bench/_httpclient.py: responses cut into pieces, chunked, closing the connection or malformed (from a
scripted socket server), and binary batch steps against the real emulator service, as httpx sees them."""

from __future__ import annotations

import socket
import sys
import threading
from collections.abc import Iterator
from pathlib import Path

import httpx
import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[2]
sys.path.append(str(REPO / "bench"))  # its _server and _httpclient (bench/ is no package)

from _httpclient import Client, HttpError  # noqa: E402
from _server import serve  # noqa: E402

from services.emulator import binary  # noqa: E402

OCTET = {"content-type": "application/octet-stream"}


class Scripted:
    """A one-thread TCP server: for each request it reads, it sends the next scripted response, one
    byte-slice at a time; ``None`` in the script closes the connection instead. Records the requests."""

    def __init__(self, script: list[list[bytes] | None]) -> None:
        self.script = script
        self.requests: list[bytes] = []
        self.connections = 0
        self.sock = socket.create_server(("127.0.0.1", 0))
        self.url = f"http://127.0.0.1:{self.sock.getsockname()[1]}"
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self) -> None:
        while self.script:
            conn, _ = self.sock.accept()
            self.connections += 1
            with conn:
                while self.script:
                    data = b""
                    while b"\r\n\r\n" not in data:
                        chunk = conn.recv(65536)
                        if not chunk:
                            break
                        data += chunk
                    if not data:
                        break
                    head, _, body = data.partition(b"\r\n\r\n")
                    length = next(
                        (
                            int(h.split(b":")[1])
                            for h in head.split(b"\r\n")
                            if h.lower().startswith(b"content-length")
                        ),
                        0,
                    )
                    while len(body) < length:
                        body += conn.recv(65536)
                    self.requests.append(head + b"\r\n\r\n" + body)
                    step = self.script.pop(0)
                    if step is None:
                        break
                    for piece in step:
                        conn.sendall(piece)


def test_pieces_chunked_and_reconnect_after_close() -> None:
    body = b"x" * 70_000
    whole = b"HTTP/1.1 200 OK\r\ncontent-length: 70000\r\n\r\n" + body
    pieces = [whole[i : i + 997] for i in range(0, len(whole), 997)]
    chunked = [
        b"HTTP/1.1 201 Created\r\nTransfer-Encoding: chunked\r\n\r\n",
        b"5\r\nhello\r\n",
        b"6;x=1\r\n world\r\n0\r\n\r\n",
    ]
    closing = [b"HTTP/1.1 204 No Content\r\nconnection: close\r\ncontent-length: 0\r\n\r\n"]
    srv = Scripted([pieces, chunked, closing, [b"HTTP/1.1 404 Not Found\r\ncontent-length: 2\r\n\r\nno"]])
    with Client(srv.url) as c:
        r = c.post("/a", content=b"abc", headers={"content-type": "text/plain"})
        assert (r.status_code, r.content) == (200, body)
        r = c.get("/b")
        assert (r.status_code, r.content) == (201, b"hello world")
        assert c.post("/c").status_code == 204
        r = c.get("/d")  # a new connection: the server closed the first one
        assert r.status_code == 404 and r.content == b"no"
        with pytest.raises(HttpError, match="HTTP 404"):
            r.raise_for_status()
    assert srv.connections == 2
    first = srv.requests[0]
    assert (
        first.startswith(b"POST /a HTTP/1.1\r\n")
        and b"content-length: 3\r\n" in first
        and first.endswith(b"abc")
    )


@pytest.mark.parametrize(
    ("reply", "needle"),
    [
        ([b"SPDY/3 200 OK\r\n\r\n"], "not an HTTP/1.x status line"),
        ([b"HTTP/1.1 200 OK\r\nno colon here\r\n\r\n"], "malformed header line"),
        ([b"HTTP/1.1 200 OK\r\n\r\n"], "without Content-Length"),
        (None, "closed the connection"),
    ],
)
def test_malformed_or_cut_responses_raise(reply: list[bytes] | None, needle: str) -> None:
    srv = Scripted([reply])
    with Client(srv.url) as c, pytest.raises(HttpError, match=needle):
        c.get("/")


@pytest.fixture(scope="module")
def service(service_root: Path) -> Iterator[str]:
    with serve(str(service_root)) as (url, _pid):
        yield url


def test_binary_batch_step_matches_httpx(service: str) -> None:
    ids = [
        httpx.post(f"{service}/sessions", json={"model": "pendulum-active", "seed": i}).json()["id"]
        for i in range(6)
    ]
    twins = [
        httpx.post(f"{service}/sessions", json={"model": "pendulum-active", "seed": i}).json()["id"]
        for i in range(6)
    ]
    u = np.random.default_rng(0).uniform(-1, 1, (6, 3)).astype(np.float32)
    with Client(service) as c, httpx.Client(base_url=service) as h:
        for _ in range(3):
            lean = c.post(
                "/step", content=binary.encode_batch_request(ids, u), headers=OCTET
            ).raise_for_status()
            ref = h.post(
                "/step", content=binary.encode_batch_request(twins, u), headers=OCTET
            ).raise_for_status()
            assert lean.headers["content-type"] == "application/octet-stream"
            (s1, x1), (s2, x2) = (
                binary.decode_batch_response(lean.content),
                binary.decode_batch_response(ref.content),
            )
            assert s1.tolist() == s2.tolist() == [binary.OK] * 6
            np.testing.assert_array_equal(x1, x2)
        bad = c.post("/step", content=b"NAST", headers=OCTET)
        assert bad.status_code == 422 and b"malformed_binary" in bad.content
