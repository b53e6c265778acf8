"""bench/_wsclient.py: the frame parser on its own (fed byte by byte), and the client against the real
emulator service (a uvicorn subprocess over loopback), as bench/ws_load.py uses it."""

from __future__ import annotations

import asyncio
import json
import os
import struct
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[2]
sys.path.append(str(REPO / "bench"))  # its _server and _wsclient (bench/ is no package)

from _server import serve  # noqa: E402
from _wsclient import ConnectionClosed, HandshakeError, WsClient, accept_key, mask  # noqa: E402

from services.emulator import binary  # noqa: E402


# ---------------------------------------------------------------- helpers
def server_frame(opcode: int, payload: bytes, fin: bool = True, masked: bool = False) -> bytes:
    """A frame as a server sends it (unmasked unless asked), with the shortest length form."""
    b0 = (0x80 if fin else 0) | opcode
    n = len(payload)
    m = 0x80 if masked else 0
    if n < 126:
        head = bytes((b0, m | n))
    elif n < 65536:
        head = struct.pack("!BBH", b0, m | 126, n)
    else:
        head = struct.pack("!BBQ", b0, m | 127, n)
    return head + (b"\0\0\0\0" + payload if masked else payload)


def client_frames(data: bytes) -> list[tuple[int, bytes]]:
    """(opcode, unmasked payload) of every frame the client wrote; each must be final and masked."""
    out = []
    pos = 0
    while pos < len(data):
        b0, b1 = data[pos], data[pos + 1]
        assert b0 & 0x80 and not b0 & 0x70, "client frames are final, no reserved bits"
        assert b1 & 0x80, "client frames must be masked"
        n, pos = b1 & 0x7F, pos + 2
        if n == 126:
            n, pos = struct.unpack_from("!H", data, pos)[0], pos + 2
        elif n == 127:
            n, pos = struct.unpack_from("!Q", data, pos)[0], pos + 8
        key, pos = data[pos : pos + 4], pos + 4
        out.append((b0 & 0x0F, bytes(c ^ key[i % 4] for i, c in enumerate(data[pos : pos + n]))))
        pos += n
    return out


class FakeTransport(asyncio.Transport):
    """Collects what the client writes; closing reports the connection lost on the next loop turn."""

    def __init__(self, proto: asyncio.Protocol) -> None:
        super().__init__()
        self.proto = proto
        self.written = bytearray()
        self.closing = False

    def write(self, data: bytes | bytearray | memoryview) -> None:
        self.written += data

    def is_closing(self) -> bool:
        return self.closing

    def close(self) -> None:
        if not self.closing:
            self.closing = True
            asyncio.get_running_loop().call_soon(self.proto.connection_lost, None)

    def abort(self) -> None:
        self.close()


def opened(accept: bytes | None = None) -> tuple[WsClient, FakeTransport, bytes]:
    """A client on a fake transport, and the 101 response the server would answer (split at will)."""
    proto = WsClient("example:80", "/ws/sessions/x?format=binary")
    transport = FakeTransport(proto)
    proto.connection_made(transport)
    response = (
        "HTTP/1.1 101 Switching Protocols\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
        f"Sec-WebSocket-Accept: {(accept or accept_key(proto._key)).decode()}\r\n\r\n"
    ).encode()
    return proto, transport, response


# ---------------------------------------------------------------- pure unit tests
def test_accept_key_and_mask() -> None:
    assert accept_key(b"dGhlIHNhbXBsZSBub25jZQ==") == b"s3pPLMBiTxaQ9kYGzzhZRbK+xOo="  # RFC 6455 §1.3
    rng = np.random.default_rng(0)
    for n in (0, 1, 3, 4, 5, 17, 126, 70_001):
        payload, key = rng.bytes(n), rng.bytes(4)
        masked = mask(payload, key)
        assert masked == bytes(c ^ key[i % 4] for i, c in enumerate(payload))
        assert mask(masked, key) == payload


def test_parser_byte_by_byte() -> None:
    """The handshake response and every kind of frame arrive one byte per read, then all in one read."""

    async def main() -> None:
        proto, transport, response = opened()
        request = bytes(transport.written).decode()
        assert request.startswith("GET /ws/sessions/x?format=binary HTTP/1.1\r\n")
        assert "Sec-WebSocket-Version: 13\r\n" in request and "Extensions" not in request
        transport.written.clear()
        big = os.urandom(70_000)
        text = json.dumps({"type": "error", "message": "é" * 200})
        frames = (
            server_frame(0x2, b"\x01\x02")  # 7-bit length
            + server_frame(0x1, text.encode())  # 16-bit length, multi-byte UTF-8
            + server_frame(0x2, big)  # 64-bit length
            + server_frame(0x1, b"frag", fin=False)
            + server_frame(0x9, b"are you there")  # a control frame between fragments
            + server_frame(0x0, b"men", fin=False)
            + server_frame(0x0, b"ted")
            + server_frame(0x2, b"")
        )
        expected: list[bytes | str] = [b"\x01\x02", text, big, "fragmented", b""]
        for i in range(len(response)):
            proto.data_received(response[i : i + 1])
        assert proto._open and not proto._messages
        reader = asyncio.ensure_future(proto.recv())  # waiting before the first frame comes
        await asyncio.sleep(0)
        for i in range(len(frames)):
            proto.data_received(frames[i : i + 1])
        got = [await reader] + [await proto.recv() for _ in range(len(expected) - 1)]
        assert got == expected
        assert client_frames(bytes(transport.written)) == [(0xA, b"are you there")]  # the pong
        transport.written.clear()

        proto.data_received(frames + server_frame(0x8, struct.pack("!H", 1001) + b"going away"))
        assert [await proto.recv() for _ in expected] == expected
        with pytest.raises(ConnectionClosed) as closed:
            await proto.recv()
        assert (closed.value.code, closed.value.reason) == (1001, "going away")
        assert client_frames(bytes(transport.written)) == [
            (0xA, b"are you there"),
            (0x8, struct.pack("!H", 1001)),  # the close, echoed
        ]
        with pytest.raises(ConnectionClosed):
            proto.send_binary(b"late")

    asyncio.run(main())


def test_handshake_with_the_first_frames_in_the_same_read() -> None:
    async def main() -> None:
        proto, _, response = opened()
        proto.data_received(response + server_frame(0x1, b'{"type":"started"}') + server_frame(0x2, b"x")[:1])
        assert await proto.recv() == '{"type":"started"}'
        proto.data_received(server_frame(0x2, b"x")[1:])
        assert await proto.recv() == b"x"

    asyncio.run(main())


def test_a_wrong_accept_key_fails_the_handshake() -> None:
    async def main() -> None:
        proto, transport, response = opened(accept=accept_key(b"another key"))
        proto.data_received(response)
        with pytest.raises(HandshakeError, match="Sec-WebSocket-Accept"):
            await proto._handshake
        assert transport.closing

    asyncio.run(main())


@pytest.mark.parametrize(
    ("frame", "code"),
    [
        (server_frame(0x2, b"hidden", masked=True), 1002),  # servers never mask
        (bytes((0xC2, 1)) + b"x", 1002),  # RSV1 without a negotiated extension
        (server_frame(0x9, b"p" * 126), 1002),  # a control frame longer than 125 bytes
        (server_frame(0x0, b"orphan"), 1002),  # a continuation with nothing to continue
        (server_frame(0x3, b""), 1002),  # a reserved opcode
        (server_frame(0x1, b"\xff\xfe"), 1007),  # not UTF-8
    ],
)
def test_protocol_violations_fail_the_connection(frame: bytes, code: int) -> None:
    async def main() -> None:
        proto, transport, response = opened()
        proto.data_received(response)
        transport.written.clear()
        pending = asyncio.ensure_future(proto.recv())
        await asyncio.sleep(0)
        proto.data_received(frame)
        with pytest.raises(ConnectionClosed) as closed:
            await pending
        assert closed.value.code == code and transport.closing
        [(opcode, payload)] = client_frames(bytes(transport.written))
        assert opcode == 0x8 and struct.unpack_from("!H", payload)[0] == code

    asyncio.run(main())


# ---------------------------------------------------------------- against the real service
@pytest.fixture(scope="module")
def service(service_root: Path) -> Iterator[str]:
    with serve(str(service_root)) as (url, _pid):
        yield url


def new_session(url: str, model: str = "pendulum-active") -> str:
    r = httpx.post(f"{url}/sessions", json={"model": model, "seed": 1}, timeout=30)
    r.raise_for_status()
    sid: str = r.json()["id"]
    return sid


def ws_url(url: str, sid: str, query: str = "") -> str:
    return url.replace("http://", "ws://") + f"/ws/sessions/{sid}" + query


def test_binary_steps(service: str) -> None:
    async def main() -> None:
        ws = await WsClient.connect(ws_url(service, new_session(service), "?format=binary"), timeout=10)
        assert "sec-websocket-extensions" not in ws.response_headers
        started = await ws.recv()
        assert isinstance(started, str) and len(started) > 125  # a 16-bit length frame
        info = json.loads(started)
        assert (info["type"], info["format"]) == ("started", "binary")
        u = np.zeros(info["num_controls"], np.float32)
        for k in range(5):
            ws.send_binary(binary.encode_ws_frame(k, u))
            reply = await ws.recv()
            assert isinstance(reply, bytes)
            seq, steps, status, state = binary.decode_ws_state(reply)
            assert (seq, steps, status) == (k, k + 1, binary.OK)
            assert state.shape == (info["state_size"],) and np.isfinite(state).all()
        await ws.close()
        assert ws.closed

    asyncio.run(main())


def test_json_round_trips_and_long_frames(service: str) -> None:
    async def main() -> None:
        ws = await WsClient.connect(ws_url(service, new_session(service)), timeout=10)
        ws.send_text(json.dumps({"type": "ping", "seq": 7}))
        assert json.loads(await ws.recv()) == {"type": "pong", "seq": 7}
        ws.send_text(json.dumps({"type": "step", "controls": [0.1, 0.0, -0.1], "seq": 8}))
        state = json.loads(await ws.recv())
        assert (state["type"], state["seq"], state["steps"]) == ("state", 8, 1)
        # an extra field is refused with an error that quotes it, cut short (a reply of a 16-bit length)
        for pad in (300, 70_000):
            ws.send_text(json.dumps({"type": "ping", "seq": pad, "pad": "x" * pad}))
            reply = await ws.recv()
            assert isinstance(reply, str) and 125 < len(reply) < 2000
            err = json.loads(reply)
            assert (err["type"], err["error"], err["seq"]) == ("error", "invalid_request", pad)
        ws.send_text(json.dumps({"type": "ping", "seq": 9}))  # the connection is still in step
        assert json.loads(await ws.recv()) == {"type": "pong", "seq": 9}
        await ws.close()
        with pytest.raises(ConnectionClosed):
            await ws.recv()
        with pytest.raises(ConnectionClosed):
            ws.send_text("{}")

    asyncio.run(main())


def test_server_close_and_refused_upgrade(service: str) -> None:
    async def main() -> None:
        ws = await WsClient.connect(ws_url(service, "no-such-session"), timeout=10)
        err = json.loads(await ws.recv())
        assert err["error"] == "unknown_session"
        with pytest.raises(ConnectionClosed) as closed:
            await ws.recv()
        assert closed.value.code == 4404
        await ws.close(timeout=5)
        with pytest.raises(HandshakeError, match="403"):
            await WsClient.connect(service.replace("http://", "ws://") + "/not-a-socket", timeout=10)

    asyncio.run(main())


def test_ws_load_at_a_fixed_rate(service: str) -> None:
    """bench/ws_load.py on WsClient: every client steps at about --rate Hz, with no errors."""
    args = ["--url", service, "--clients", "6", "--duration", "1", "--rate", "20", "--binary", "--json"]
    out = subprocess.run(
        [sys.executable, "bench/ws_load.py", *args],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=60,
        check=True,
    ).stdout
    r: dict[str, Any] = json.loads(out.strip().splitlines()[-1])
    assert r["errors"] == 0 and r["connected"] == 6 and r["target_steps_per_s"] == 120
    assert 80 <= r["steps_per_s"] <= 130 and r["p99_ms"] is not None
    assert "20 Hz" in r["mode"] and "20 Hz" in out.splitlines()[0]
