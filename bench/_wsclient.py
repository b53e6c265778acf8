"""A minimal RFC 6455 websocket client on a raw ``asyncio.Protocol``, for the load benchmarks.

Why it exists: a load generator must not be the bottleneck it measures. ``bench/ws_load.py`` runs a
thousand lock-step clients on the same two cores as the server; with a general-purpose client library
(``websockets``: per-connection reader task, queues, per-frame objects and checks, about 100 µs of CPU
per step) the clients took some 40 % of the machine, so the benchmark measured the clients as much as
the server. This client does the least that is correct: one ``data_received`` parses every complete
frame in the buffer, a message is handed straight to the coroutine awaiting ``recv`` (one future per
wait, no task per message), and a send is one ``transport.write`` of header, mask and masked payload.

What it does:

* the HTTP/1.1 upgrade handshake (``Sec-WebSocket-Key``, ``Sec-WebSocket-Version: 13``), checking the
  101 status, ``Upgrade``/``Connection`` and ``Sec-WebSocket-Accept``; extra request headers (an API
  key) may be given;
* masked client frames (a fresh random 4-byte key per frame, ``os.urandom``), text and binary;
* unmasked server frames with 7-, 16- and 64-bit lengths, split over any number of reads or many in
  one read; fragmented messages (continuation frames) are reassembled;
* ping → pong with the same payload; a close frame is answered with a close frame, pending and later
  ``recv`` calls raise ``ConnectionClosed``; ``close()`` runs the closing handshake;
* protocol violations (masked or reserved-bit server frames, bad control frames, unknown opcodes, a
  message over ``max_size``, invalid UTF-8 in text) fail the connection (close 1002/1007/1009).

What it does not support: ``wss://`` (TLS), extensions (none are requested, so no permessage-deflate;
a server that names one anyway is refused), subprotocols, redirects, proxies, HTTP authentication
challenges, and backpressure on reads (messages queue without bound until ``recv`` takes them; a
lock-step client never has more than one in flight). ``send_*`` never waits; ``await drain()`` waits
while the transport's write buffer is over its high-water mark.
"""

from __future__ import annotations

import asyncio
import base64
import hashlib
import os
import struct
from collections import deque
from collections.abc import Mapping
from typing import cast
from urllib.parse import urlsplit

__all__ = ["ConnectionClosed", "HandshakeError", "WsClient", "accept_key", "mask"]

GUID = b"258EAFA5-E914-47DA-95CA-C5AB0DC85B11"

CONT, TEXT, BINARY, CLOSE, PING, PONG = 0x0, 0x1, 0x2, 0x8, 0x9, 0xA
_DATA = (CONT, TEXT, BINARY)
_CONTROL = (CLOSE, PING, PONG)

_H16 = struct.Struct("!BBH")
_H64 = struct.Struct("!BBQ")
_U16 = struct.Struct("!H")
_U64 = struct.Struct("!Q")

MAX_HEADER_BYTES = 65536


class HandshakeError(Exception):
    """The server did not accept the websocket upgrade (or answered it wrongly)."""


class ConnectionClosed(Exception):
    """The connection is closed; ``code`` and ``reason`` are from the server's close frame (1006, ''
    when there was none)."""

    def __init__(self, code: int, reason: str = "") -> None:
        super().__init__(f"websocket closed: {code} {reason}".rstrip())
        self.code = code
        self.reason = reason


def accept_key(key: bytes) -> bytes:
    """The ``Sec-WebSocket-Accept`` value a server must answer to ``Sec-WebSocket-Key: key``."""
    return base64.b64encode(hashlib.sha1(key + GUID).digest())


def mask(payload: bytes, key: bytes) -> bytes:
    """``payload`` XOR the 4-byte ``key`` repeated (RFC 6455 §5.3), as one big-integer XOR."""
    n = len(payload)
    if not n:
        return b""
    keys = (key * ((n + 3) // 4))[:n]
    return (int.from_bytes(payload, "little") ^ int.from_bytes(keys, "little")).to_bytes(n, "little")


def _header(opcode: int, n: int, fin: bool = True) -> bytes:
    b0 = (0x80 if fin else 0) | opcode
    if n < 126:
        return bytes((b0, 0x80 | n))
    if n < 65536:
        return _H16.pack(b0, 0x80 | 126, n)
    return _H64.pack(b0, 0x80 | 127, n)


class WsClient(asyncio.Protocol):
    """One client connection. Create it with ``await WsClient.connect(url)``; then ``send_binary``,
    ``send_text``, ``await recv()`` (``bytes`` for binary messages, ``str`` for text) and
    ``await close()``."""

    def __init__(
        self, host_header: str, path: str, headers: Mapping[str, str] | None = None, max_size: int = 1 << 24
    ) -> None:
        self.max_size = max_size
        self._key = base64.b64encode(os.urandom(16))
        lines = [
            f"GET {path} HTTP/1.1",
            f"Host: {host_header}",
            "Upgrade: websocket",
            "Connection: Upgrade",
            f"Sec-WebSocket-Key: {self._key.decode()}",
            "Sec-WebSocket-Version: 13",
            *(f"{k}: {v}" for k, v in (headers or {}).items()),
        ]
        self._request = ("\r\n".join(lines) + "\r\n\r\n").encode("latin-1")
        self._loop = asyncio.get_running_loop()
        self._transport: asyncio.Transport | None = None
        self._open = False  # the handshake has completed
        self._buf = bytearray()
        self._handshake: asyncio.Future[None] = self._loop.create_future()
        self._lost: asyncio.Future[None] = self._loop.create_future()
        self._messages: deque[bytes | str] = deque()
        self._waiter: asyncio.Future[bytes | str] | None = None
        self._frag_opcode = -1  # opcode of the fragmented message being reassembled, -1 if none
        self._frag: list[bytes] = []
        self._frag_size = 0
        self._close_sent = False
        self._closed: ConnectionClosed | None = None  # set once closed (close frame in, or lost)
        self._paused = False
        self._drain: asyncio.Future[None] | None = None
        self.response_headers: dict[str, str] = {}

    # ------------------------------------------------------------------ connecting
    @classmethod
    async def connect(
        cls,
        url: str,
        timeout: float = 30.0,
        headers: Mapping[str, str] | None = None,
        max_size: int = 1 << 24,
    ) -> WsClient:
        """Open ``ws://host[:port]/path[?query]`` and complete the handshake within ``timeout`` s."""
        parts = urlsplit(url)
        if parts.scheme != "ws":
            raise ValueError(f"only ws:// URLs are supported, got {url!r}")
        host = parts.hostname or ""
        port = parts.port or 80
        path = (parts.path or "/") + (f"?{parts.query}" if parts.query else "")
        host_header = parts.netloc.rsplit("@", 1)[-1]
        loop = asyncio.get_running_loop()
        proto = cls(host_header, path, headers, max_size)
        try:
            async with asyncio.timeout(timeout):
                await loop.create_connection(lambda: proto, host, port)
                await proto._handshake
        except BaseException:
            proto.abort()
            raise
        return proto

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        # a cast, not an isinstance check: uvloop's transports are no asyncio.Transport subclasses
        self._transport = cast(asyncio.Transport, transport)
        self._transport.write(self._request)

    def _finish_handshake(self) -> None:
        end = self._buf.find(b"\r\n\r\n")
        if end < 0:
            if len(self._buf) > MAX_HEADER_BYTES:
                self._fail_handshake("the handshake response headers are too long")
            return
        head = bytes(self._buf[:end]).decode("latin-1")
        del self._buf[: end + 4]
        status_line, *lines = head.split("\r\n")
        parts = status_line.split(" ", 2)
        if len(parts) < 2 or not parts[0].startswith("HTTP/1.") or parts[1] != "101":
            self._fail_handshake(f"the server refused the upgrade: {status_line!r}")
            return
        hdrs: dict[str, str] = {}
        for line in lines:
            name, sep, value = line.partition(":")
            if not sep:
                self._fail_handshake(f"malformed response header {line!r}")
                return
            name = name.strip().lower()
            value = value.strip()
            hdrs[name] = f"{hdrs[name]}, {value}" if name in hdrs else value
        self.response_headers = hdrs
        connection = {t.strip().lower() for t in hdrs.get("connection", "").split(",")}
        if hdrs.get("upgrade", "").lower() != "websocket" or "upgrade" not in connection:
            self._fail_handshake("the response lacks Upgrade: websocket / Connection: Upgrade")
        elif hdrs.get("sec-websocket-accept", "").encode() != accept_key(self._key):
            self._fail_handshake("wrong Sec-WebSocket-Accept")
        elif hdrs.get("sec-websocket-extensions"):
            self._fail_handshake(
                f"the server chose extensions none were asked for: {hdrs['sec-websocket-extensions']}"
            )
        elif hdrs.get("sec-websocket-protocol"):
            self._fail_handshake("the server chose a subprotocol none was asked for")
        else:
            self._open = True
            if not self._handshake.done():
                self._handshake.set_result(None)

    def _fail_handshake(self, why: str) -> None:
        if not self._handshake.done():
            self._handshake.set_exception(HandshakeError(why))
        self.abort()

    # ------------------------------------------------------------------ receiving
    def data_received(self, data: bytes) -> None:
        if self._open:
            buf = self._buf
            if buf:
                buf += data
                used = self._parse(buf)
                if self._buf is buf:  # (a failure may have replaced the buffer)
                    del buf[:used]
            else:  # the common case: whole frames, no copy into the buffer
                used = self._parse(data)
                if used < len(data) and self._closed is None:
                    self._buf += data[used:]
            return
        self._buf += data
        self._finish_handshake()
        if self._open and self._buf:
            rest = bytes(self._buf)
            self._buf = bytearray()
            self.data_received(rest)

    def _parse(self, data: bytes | bytearray) -> int:
        """Handles every complete frame of ``data``; returns how many bytes they took."""
        pos = 0
        end = len(data)
        while end - pos >= 2 and self._closed is None:
            b0 = data[pos]
            b1 = data[pos + 1]
            n = b1 & 0x7F
            at = pos + 2
            if n == 126:
                if end - at < 2:
                    break
                n = _U16.unpack_from(data, at)[0]
                at += 2
            elif n == 127:
                if end - at < 8:
                    break
                n = _U64.unpack_from(data, at)[0]
                at += 8
            if b1 & 0x80:
                self._fail(1002, "a server frame is masked")
                break
            if n > self.max_size:
                self._fail(1009, "frame too big")
                break
            if end - at < n:
                break
            payload = bytes(data[at : at + n])
            pos = at + n
            opcode = b0 & 0x0F
            if b0 & 0x70:
                self._fail(1002, "reserved bits set")
                break
            if opcode == BINARY and b0 & 0x80 and self._frag_opcode < 0:  # the hot path
                self._deliver(payload)
            elif opcode == TEXT and b0 & 0x80 and self._frag_opcode < 0:
                self._deliver_text(payload)
            else:
                self._frame(b0 & 0x80 != 0, opcode, payload)
        return pos

    def _deliver(self, msg: bytes | str) -> None:
        w = self._waiter
        if w is not None and not w.done():
            w.set_result(msg)
            self._waiter = None
        else:
            self._messages.append(msg)

    def _deliver_text(self, payload: bytes) -> None:
        try:
            text = payload.decode("utf-8")
        except UnicodeDecodeError:
            self._fail(1007, "invalid UTF-8 in a text message")
            return
        self._deliver(text)

    def _frame(self, fin: bool, opcode: int, payload: bytes) -> None:
        """Every frame but a whole unfragmented data message."""
        if opcode in _CONTROL:
            if not fin or len(payload) > 125:
                self._fail(1002, "a fragmented or long control frame")
            elif opcode == PING:
                self._send(PONG, payload)
            elif opcode == CLOSE:
                self._on_close(payload)
            return  # (a pong needs nothing)
        if opcode not in _DATA:
            self._fail(1002, f"unknown opcode {opcode}")
            return
        if opcode == CONT:
            if self._frag_opcode < 0:
                self._fail(1002, "a continuation frame with no message to continue")
                return
        elif self._frag_opcode >= 0:
            self._fail(1002, "a new message inside a fragmented one")
            return
        else:
            self._frag_opcode = opcode
        self._frag.append(payload)
        self._frag_size += len(payload)
        if self._frag_size > self.max_size:
            self._fail(1009, "message too big")
            return
        if fin:
            whole = b"".join(self._frag)
            first = self._frag_opcode
            self._frag_opcode, self._frag, self._frag_size = -1, [], 0
            if first == TEXT:
                self._deliver_text(whole)
            else:
                self._deliver(whole)

    def _on_close(self, payload: bytes) -> None:
        if len(payload) == 1:
            self._fail(1002, "a one-byte close payload")
            return
        code = _U16.unpack_from(payload)[0] if payload else 1005
        try:
            reason = payload[2:].decode("utf-8")
        except UnicodeDecodeError:
            self._fail(1007, "invalid UTF-8 in a close reason")
            return
        if not self._close_sent:  # echo the code (RFC 6455 §5.5.1); the server then closes TCP
            self._send(CLOSE, payload[:2])
            self._close_sent = True
        self._set_closed(ConnectionClosed(code, reason))

    def _set_closed(self, exc: ConnectionClosed) -> None:
        if self._closed is None:
            self._closed = exc
        w = self._waiter
        if w is not None and not w.done():
            w.set_exception(self._closed)
        self._waiter = None

    def _fail(self, code: int, why: str) -> None:
        """Fails the connection: a close frame with ``code``, then the TCP connection is dropped."""
        if not self._close_sent and self._transport is not None:
            self._send(CLOSE, _U16.pack(code) + why.encode()[:120])
            self._close_sent = True
        self._set_closed(ConnectionClosed(code, why))
        self._buf = bytearray()
        if self._transport is not None:
            self._transport.close()

    def connection_lost(self, exc: Exception | None) -> None:
        self._open = False
        if not self._handshake.done():
            self._handshake.set_exception(
                HandshakeError(f"the connection closed during the handshake: {exc or 'EOF'}")
            )
        self._set_closed(ConnectionClosed(1006, str(exc or "")))
        if not self._lost.done():
            self._lost.set_result(None)
        if self._drain is not None and not self._drain.done():
            self._drain.set_result(None)

    # ------------------------------------------------------------------ sending
    def _send(self, opcode: int, payload: bytes) -> None:
        key = os.urandom(4)
        assert self._transport is not None
        self._transport.write(_header(opcode, len(payload)) + key + mask(payload, key))

    def send_binary(self, data: bytes) -> None:
        """Sends one binary message (one frame). Raises ``ConnectionClosed`` once closed."""
        if self._closed is not None or self._close_sent:
            raise self._closed or ConnectionClosed(1006, "closing")
        key = os.urandom(4)
        n = len(data)
        hdr = bytes((0x82, 0x80 | n)) if n < 126 else _header(BINARY, n)
        assert self._transport is not None
        self._transport.write(hdr + key + mask(data, key))

    def send_text(self, text: str) -> None:
        """Sends one text message (one frame). Raises ``ConnectionClosed`` once closed."""
        if self._closed is not None or self._close_sent:
            raise self._closed or ConnectionClosed(1006, "closing")
        self._send(TEXT, text.encode("utf-8"))

    def send_ping(self, payload: bytes = b"") -> None:
        if len(payload) > 125:
            raise ValueError("a ping payload is at most 125 bytes")
        if self._closed is None and not self._close_sent:
            self._send(PING, payload)

    async def drain(self) -> None:
        """Waits while the transport's write buffer is over its high-water mark."""
        if self._paused and self._closed is None:
            self._drain = self._loop.create_future()
            await self._drain

    def pause_writing(self) -> None:
        self._paused = True

    def resume_writing(self) -> None:
        self._paused = False
        if self._drain is not None and not self._drain.done():
            self._drain.set_result(None)

    async def recv(self) -> bytes | str:
        """The next message: ``bytes`` (binary) or ``str`` (text). Raises ``ConnectionClosed`` once the
        connection is closed and every message received before has been taken."""
        if self._messages:
            return self._messages.popleft()
        if self._closed is not None:
            raise self._closed
        if self._waiter is not None and not self._waiter.done():
            raise RuntimeError("recv is already being awaited")
        fut: asyncio.Future[bytes | str] = self._loop.create_future()
        self._waiter = fut
        return await fut

    # ------------------------------------------------------------------ closing
    @property
    def closed(self) -> bool:
        return self._closed is not None

    async def close(self, code: int = 1000, reason: str = "", timeout: float = 5.0) -> None:
        """The closing handshake: send close, wait (at most ``timeout`` s) for the server's close frame
        and for it to drop the TCP connection, then drop it ourselves if it has not."""
        if self._transport is None:
            return
        if not self._close_sent and not self._lost.done():
            self._send(CLOSE, _U16.pack(code) + reason.encode("utf-8")[:123])
            self._close_sent = True
        try:
            async with asyncio.timeout(timeout):
                await asyncio.shield(self._lost)
        except TimeoutError:
            self.abort()
        else:
            self._transport.close()
        self._set_closed(self._closed or ConnectionClosed(1006, "closed"))

    def abort(self) -> None:
        """Drops the TCP connection at once (no closing handshake)."""
        if self._transport is not None:
            self._transport.abort()
