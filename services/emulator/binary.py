"""Binary wire formats (little-endian float32), documented in ``proto/frames.md``.

* ``POST /step`` with ``Content-Type: application/octet-stream``: a 16-byte request header (magic
  ``NAST``, version, flags, count N, id width W), N session-id slots of W bytes (ASCII, NUL-padded),
  then N rows of U controls and F forces as float32. Every session of one binary request is of one
  (model, version), so rows have a fixed width. The response: a 16-byte header (magic ``NASR``,
  version, flags, N, S), N status bytes padded to a multiple of 4, N rows of S float32, then (flag
  ``FLAG_ENVELOPE``) N envelope bytes, 1 where the new state is outside the training envelope.
* Websocket frames: a client frame is magic ``NAWC``, u32 seq, then U + F float32; a state frame is
  magic ``NAWS``, u32 seq, u32 steps, u8 status, u8 envelope (1: outside the training envelope), 2 zero
  bytes, then S float32.

Parsing raises ``BadInput`` (or ``TooLarge`` for a batch over MAX_BATCH) naming the problem.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from services.emulator.errors import BadInput, TooLarge

VERSION = 1
MEDIA_TYPE = "application/octet-stream"
REQUEST_MAGIC = b"NAST"
RESPONSE_MAGIC = b"NASR"
WS_CLIENT_MAGIC = b"NAWC"
WS_STATE_MAGIC = b"NAWS"
MAX_ID_WIDTH = 256
NO_SEQ = 0xFFFFFFFF
"""``seq`` of a frame that answers no numbered message."""

REQUEST_HEADER = struct.Struct("<4sHHIHH")  # magic, version, flags, count, id width, reserved
RESPONSE_HEADER = struct.Struct("<4sHHII")  # magic, version, flags, count, state size
WS_CLIENT_HEADER = struct.Struct("<4sI")  # magic, seq
WS_STATE_HEADER = struct.Struct("<4sIIBB2x")  # magic, seq, steps, status, envelope
FLAG_ENVELOPE = 1
"""Response flag: the states are followed by one envelope byte per session."""

# Status byte of each session in a binary response (and of a websocket state frame).
OK = 0
CLIPPED = 1  # stepped; some control or force was outside the trained range and was clipped
DIVERGED = 2  # not stepped: the session diverged (now or earlier); its row is its last finite state
UNKNOWN = 3  # not stepped: no such session (never created, deleted, expired or another key's); NaN row


def _bad(
    error: str, message: str, *, field: str | None = None, expected: Any = None, got: Any = None
) -> BadInput:
    return BadInput(message, code=error, field=field, expected=expected, got=got)


@dataclass
class BatchRequest:
    """A parsed binary batch request: N session-id slots of ``width`` bytes (``id_block``, undecoded:
    the session store resolves them) and the raw (N, U+F) float32 input rows (unchecked width)."""

    count: int
    width: int
    id_block: bytes
    body: memoryview
    offset: int  # where the float32 rows start

    @property
    def ids(self) -> list[str]:
        return decode_ids(self.id_block, self.width)

    def rows(self, width: int, what: str) -> NDArray[np.float32]:
        """(N, width) float32 rows; ``BadInput`` when the body's length does not fit ``width`` per session."""
        n = self.count
        want = self.offset + 4 * n * width
        if len(self.body) != want:
            raise _bad(
                "wrong_length",
                f"binary body is {len(self.body)} bytes; the header says {n} sessions of {what} "
                f"({width} float32 per session), so it must be {want} bytes",
                field="body",
                expected=want,
                got=len(self.body),
            )
        return np.frombuffer(self.body, dtype="<f4", count=n * width, offset=self.offset).reshape(n, width)

    def check_whole_rows(self) -> None:
        """``BadInput`` unless the body's length fits a whole number of float32 per session (checked
        when no session is known, so no model says the width)."""
        n = self.count
        rest = len(self.body) - self.offset
        if n and (rest < 0 or rest % (4 * n)):
            raise _bad(
                "wrong_length",
                f"binary body is {len(self.body)} bytes, which fits no whole number of float32 per session "
                f"for the {n} sessions the header announces",
                field="body",
                got=len(self.body),
            )


def parse_batch_request(body: bytes, max_batch: int) -> BatchRequest:
    """The header of a binary ``POST /step`` body, and where its ids and rows lie."""
    if len(body) < REQUEST_HEADER.size:
        raise _bad(
            "malformed_binary",
            f"binary body is {len(body)} bytes, shorter than the {REQUEST_HEADER.size}-byte header "
            "(see proto/frames.md)",
            field="body",
            expected=f">= {REQUEST_HEADER.size} bytes",
            got=len(body),
        )
    magic, version, _flags, count, width, _ = REQUEST_HEADER.unpack_from(body)
    if magic != REQUEST_MAGIC:
        raise _bad(
            "bad_magic",
            f"binary body starts with {magic!r}, expected the magic {REQUEST_MAGIC!r} (see proto/frames.md)",
            field="magic",
            expected=REQUEST_MAGIC.decode(),
            got=repr(magic),
        )
    if version != VERSION:
        raise _bad(
            "unsupported_version",
            f"binary format version {version} is not supported; this server speaks version {VERSION}",
            field="version",
            expected=VERSION,
            got=version,
        )
    if count > max_batch:
        raise TooLarge(
            f"a batch may hold at most {max_batch} items (MAX_BATCH), got {count}",
            field="count",
            expected=f"<= {max_batch}",
            got=count,
        )
    if not 1 <= width <= MAX_ID_WIDTH:
        raise _bad(
            "bad_id_width",
            f"the session-id width must be 1..{MAX_ID_WIDTH} bytes, got {width}",
            field="id_width",
            expected=f"1..{MAX_ID_WIDTH}",
            got=width,
        )
    end = REQUEST_HEADER.size + count * width
    if len(body) < end:
        raise _bad(
            "wrong_length",
            f"binary body is {len(body)} bytes, too short for the {count} session ids of {width} bytes "
            f"the header announces (at least {end} bytes)",
            field="count",
            expected=f">= {end} bytes",
            got=len(body),
        )
    return BatchRequest(count, width, body[REQUEST_HEADER.size : end], memoryview(body), end)


def encode_batch_request(
    ids: list[str], controls: NDArray[np.floating], forces: NDArray[np.floating] | None = None
) -> bytes:
    """Client side: the binary body for sessions ``ids`` with controls (N, U) and forces (N, F)."""
    n = len(ids)
    raw = [s.encode("ascii") for s in ids]
    width = max((len(r) for r in raw), default=1)
    width = (width + 3) // 4 * 4  # keeps the float32 rows 4-byte aligned
    u = np.asarray(controls, dtype="<f4").reshape(n, -1)
    rows = u if forces is None else np.concatenate([u, np.asarray(forces, "<f4").reshape(n, -1)], axis=1)
    head = REQUEST_HEADER.pack(REQUEST_MAGIC, VERSION, 0, n, width, 0)
    return head + b"".join(r.ljust(width, b"\0") for r in raw) + np.ascontiguousarray(rows, "<f4").tobytes()


def encode_batch_response(
    status: NDArray[np.uint8], states: NDArray[np.float32], outside: NDArray[np.bool_] | None = None
) -> bytes:
    """(N,) status bytes, (N, S) states and (N,) outside the training envelope (all False if None)."""
    n = len(status)
    s = states.shape[1] if states.ndim == 2 else 0
    pad = (-n) % 4
    return b"".join(
        (
            RESPONSE_HEADER.pack(RESPONSE_MAGIC, VERSION, FLAG_ENVELOPE, n, s),
            status.astype(np.uint8).tobytes(),
            b"\0" * pad,
            np.ascontiguousarray(states, "<f4").tobytes(),
            bytes(n) if outside is None else outside.astype(np.uint8).tobytes(),
        )
    )


def decode_batch_response(body: bytes) -> tuple[NDArray[np.uint8], NDArray[np.float32]]:
    """Client side: (N,) status bytes and (N, S) states of a binary ``POST /step`` response."""
    magic, version, _flags, n, s = RESPONSE_HEADER.unpack_from(body)
    if magic != RESPONSE_MAGIC or version != VERSION:
        raise ValueError(f"not a version-{VERSION} binary step response: {body[:8]!r}")
    off = RESPONSE_HEADER.size
    status = np.frombuffer(body, np.uint8, count=n, offset=off)
    off += n + (-n) % 4
    states = np.frombuffer(body, "<f4", count=n * s, offset=off).reshape(n, s)
    return status, states


def decode_batch_outside(body: bytes) -> NDArray[np.bool_] | None:
    """Client side: (N,) whether each new state of a binary ``POST /step`` response is outside the
    training envelope (None from a server that does not say)."""
    _, _, flags, n, s = RESPONSE_HEADER.unpack_from(body)
    if not flags & FLAG_ENVELOPE:
        return None
    off = RESPONSE_HEADER.size + n + (-n) % 4 + 4 * n * s
    return np.frombuffer(body, np.uint8, count=n, offset=off).astype(bool)


# ---------------------------------------------------------------- websocket frames
def parse_ws_frame(data: bytes, width: int, what: str) -> tuple[int | None, NDArray[np.float32]]:
    """A client binary frame -> (seq or None, (width,) float32 controls then forces)."""
    want = WS_CLIENT_HEADER.size + 4 * width
    if len(data) < WS_CLIENT_HEADER.size or data[:4] != WS_CLIENT_MAGIC:
        raise _bad(
            "bad_magic",
            f"a binary frame must start with {WS_CLIENT_MAGIC!r} and a u32 seq (see proto/frames.md), "
            f"got {bytes(data[:8])!r}",
            field="magic",
            expected=WS_CLIENT_MAGIC.decode(),
            got=repr(bytes(data[:4])),
        )
    _, seq = WS_CLIENT_HEADER.unpack_from(data)
    if len(data) != want:
        raise _bad(
            "wrong_length",
            f"a binary frame for {what} is {want} bytes (8-byte header + {width} float32), got {len(data)}",
            field="frame",
            expected=want,
            got=len(data),
        )
    values = np.frombuffer(data, "<f4", count=width, offset=WS_CLIENT_HEADER.size)
    return (None if seq == NO_SEQ else int(seq)), values


def encode_ws_frame(seq: int | None, values: NDArray[np.floating]) -> bytes:
    """Client side: a binary frame with controls then forces."""
    s = NO_SEQ if seq is None else seq
    return WS_CLIENT_HEADER.pack(WS_CLIENT_MAGIC, s) + np.ascontiguousarray(values, "<f4").tobytes()


def encode_ws_state(
    seq: int | None, steps: int, status: int, state: NDArray[np.floating], outside: bool = False
) -> bytes:
    s = NO_SEQ if seq is None else seq
    head = WS_STATE_HEADER.pack(WS_STATE_MAGIC, s, steps, status, outside)
    return head + np.ascontiguousarray(state, "<f4").tobytes()


def ws_state_outside(data: bytes) -> bool:
    """Client side: whether the state of a binary state frame is outside the training envelope."""
    return bool(WS_STATE_HEADER.unpack_from(data)[4])


def decode_ws_state(data: bytes) -> tuple[int | None, int, int, NDArray[np.float32]]:
    """Client side: (seq or None, steps, status, (S,) state) of a binary state frame
    (``ws_state_outside``: its envelope byte)."""
    magic, seq, steps, status, _ = WS_STATE_HEADER.unpack_from(data)
    if magic != WS_STATE_MAGIC:
        raise ValueError(f"not a state frame: {bytes(data[:8])!r}")
    state = np.frombuffer(data, "<f4", offset=WS_STATE_HEADER.size)
    return (None if seq == NO_SEQ else int(seq)), int(steps), int(status), state


def decode_ids(block: bytes, width: int) -> list[str]:
    """The ids of a block of NUL-padded ASCII slots of ``width`` bytes; ``BadInput`` naming the first
    slot that is not ASCII."""
    raw = np.frombuffer(block, np.uint8)
    if raw.size and raw.max() >= 0x80:
        i = int(np.flatnonzero(raw >= 0x80)[0]) // width
        slot = block[i * width : (i + 1) * width]
        raise _bad(
            "bad_session_id",
            f"session id slot {i} is not ASCII: {slot!r}",
            field=f"ids[{i}]",
            expected="ASCII, NUL-padded",
            got=repr(slot),
        )
    # numpy's fixed-width bytes drop the trailing NULs of each slot
    return [b.decode("ascii") for b in np.frombuffer(block, f"S{width}").tolist()]
