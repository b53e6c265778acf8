"""A minimal blocking HTTP/1.1 keep-alive client, for the batch-stepping benchmark.

Why it exists: ``bench/batch_api.py`` measures how many session-steps per second the service gives a
game server that steps thousands of sessions per request. Each request carries about 100 KB each way;
a general-purpose client (``httpx``: URL parsing, header validation, h11 state machine, response
objects) spends about 0.6 ms of CPU per such request on this machine, as much as a third of the whole
round trip, so the benchmark would measure the client as much as the server. This client does the
least that is correct for one origin server: one persistent TCP connection (``TCP_NODELAY``), the
request head and body in one ``sendall``, and the response read into one buffer.

What it does: ``POST`` and ``GET`` with extra headers; responses with ``Content-Length`` or chunked
transfer encoding; ``Connection: close`` from the server (the next request reconnects); a status
line, headers and body returned as ``Response``.

What it does not do: TLS, redirects, proxies, ``Expect: 100-continue``, HTTP/1.0 servers without a
length, compressed bodies (none are asked for), or pipelining (one request in flight at a time).
"""

from __future__ import annotations

import socket
from dataclasses import dataclass
from urllib.parse import urlsplit

READ_SIZE = 1 << 20


class HttpError(RuntimeError):
    """A response that is not valid HTTP/1.1, or a closed connection mid-response."""


@dataclass
class Response:
    """What callers of ``httpx`` read: ``status_code``, ``headers``, ``content``, ``raise_for_status()``."""

    status_code: int
    headers: dict[str, str]  # lower-case names
    content: bytes

    def raise_for_status(self) -> Response:
        if self.status_code >= 400:
            raise HttpError(f"HTTP {self.status_code}: {self.content[:200]!r}")
        return self


class Client:
    """``Client("http://127.0.0.1:8000").post("/step", content=body, headers={...})``, as with httpx."""

    def __init__(self, base_url: str, timeout: float = 60.0) -> None:
        parts = urlsplit(base_url)
        if parts.scheme != "http" or parts.hostname is None:
            raise ValueError(f"only http://host[:port] URLs are supported, got {base_url!r}")
        self.host, self.port = parts.hostname, parts.port or 80
        self.timeout = timeout
        self._sock: socket.socket | None = None
        self._buf = bytearray()

    def __enter__(self) -> Client:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        if self._sock is not None:
            self._sock.close()
            self._sock = None
        self._buf.clear()

    def get(self, path: str, headers: dict[str, str] | None = None) -> Response:
        return self.request("GET", path, b"", headers)

    def post(self, path: str, content: bytes = b"", headers: dict[str, str] | None = None) -> Response:
        return self.request("POST", path, content, headers)

    def request(self, method: str, path: str, body: bytes, headers: dict[str, str] | None = None) -> Response:
        head = [f"{method} {path} HTTP/1.1", f"host: {self.host}:{self.port}"]
        head += [f"{k}: {v}" for k, v in (headers or {}).items()]
        if body or method == "POST":
            head.append(f"content-length: {len(body)}")
        data = ("\r\n".join(head) + "\r\n\r\n").encode("latin-1") + body
        sock = self._connect()
        try:
            sock.sendall(data)
            resp = self._read_response()
        except (OSError, HttpError):
            self.close()
            raise
        if resp.headers.get("connection", "").lower() == "close":
            self.close()
        return resp

    def _connect(self) -> socket.socket:
        if self._sock is None:
            self._sock = socket.create_connection((self.host, self.port), timeout=self.timeout)
            self._sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        return self._sock

    def _fill(self) -> None:
        assert self._sock is not None
        chunk = self._sock.recv(READ_SIZE)
        if not chunk:
            raise HttpError("the server closed the connection mid-response")
        self._buf += chunk

    def _take(self, n: int) -> bytes:
        while len(self._buf) < n:
            self._fill()
        out = bytes(self._buf[:n])
        del self._buf[:n]
        return out

    def _line(self) -> bytes:
        while (end := self._buf.find(b"\r\n")) < 0:
            self._fill()
        out = bytes(self._buf[:end])
        del self._buf[: end + 2]
        return out

    def _read_response(self) -> Response:
        while (end := self._buf.find(b"\r\n\r\n")) < 0:
            self._fill()
        lines = bytes(self._buf[:end]).decode("latin-1").split("\r\n")
        del self._buf[: end + 4]
        version, _, rest = lines[0].partition(" ")
        if not version.startswith("HTTP/1.") or not rest[:3].isdigit():
            raise HttpError(f"not an HTTP/1.x status line: {lines[0]!r}")
        headers: dict[str, str] = {}
        for line in lines[1:]:
            name, sep, value = line.partition(":")
            if not sep:
                raise HttpError(f"malformed header line: {line!r}")
            headers[name.strip().lower()] = value.strip()
        if "chunked" in headers.get("transfer-encoding", "").lower():
            parts = []
            while size := int(self._line().split(b";")[0], 16):
                parts.append(self._take(size))
                self._take(2)
            while self._line():  # trailers, then the blank line
                pass
            content = b"".join(parts)
        elif "content-length" in headers:
            content = self._take(int(headers["content-length"]))
        else:
            raise HttpError("a response without Content-Length or chunked encoding")
        return Response(int(rest[:3]), headers, content)
