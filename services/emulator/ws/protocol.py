"""The websocket protocol: client messages parsed, server messages encoded (JSON text or the binary
frames of proto/frames.md); the wire models are ``neuroanimator.contracts.emulator``'s ``Ws*``."""

from __future__ import annotations

import json
import struct
from collections.abc import Mapping
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray
from pydantic import TypeAdapter, ValidationError

from neuroanimator.contracts.emulator import ClientMessage, ShadowState, WsPong, WsStart, WsStarted, WsState
from services.common.errors import json_error
from services.emulator import binary
from services.emulator.error_mapping import invalid
from services.emulator.errors import BadInput, EmulatorError
from services.emulator.registry import LoadedEmulator
from services.emulator.scene import Kinematics, MujocoShadow

_CLIENT: TypeAdapter[ClientMessage] = TypeAdapter(ClientMessage)
QUERY_KEYS = ("mode", "format", "poses", "shadow")
"""Query parameters that start a connection as a ``start`` message would."""


# ---------------------------------------------------------------- client -> server
def read_text(text: str) -> tuple[int | None, ClientMessage | EmulatorError]:
    """A text message: its ``seq`` (when it has an integer one, even if the rest is invalid, so that
    the error echoes it) and the message, or the error saying why it is not one."""
    try:
        raw = json.loads(text)
    except (ValueError, RecursionError) as exc:  # syntax, a huge integer, too deep
        return None, BadInput(
            f"the message is not JSON: {json_error(exc)}", code="malformed_json", got=text[:200]
        )
    seq = raw.get("seq") if isinstance(raw, dict) else None
    seq = seq if isinstance(seq, int) else None
    try:
        return seq, _CLIENT.validate_python(raw)
    except ValidationError as exc:
        return seq, invalid(exc)


def start_from_query(query: Mapping[str, str]) -> WsStart | None:
    """The ``start`` that query parameters ask for (``?mode=realtime&format=binary``), if any."""
    if not set(QUERY_KEYS) & set(query):
        return None
    try:
        return WsStart.model_validate(
            {
                "type": "start",
                "mode": query.get("mode", "lockstep"),
                "format": query.get("format"),
                "poses": query.get("poses"),
                "shadow": query.get("shadow"),
            }
        )
    except ValidationError as exc:
        raise invalid(exc) from exc


class InputFrames:
    """Binary input frames of one model (``NAWC``, seq, U+F float32)."""

    def __init__(self, emu: LoadedEmulator) -> None:
        self.emu = emu
        self.width = emu.num_controls + emu.num_forces
        self._struct = struct.Struct(f"<4sI{self.width}f")
        self.size = self._struct.size

    def unpack(self, data: bytes) -> tuple[int | None, list[float]] | None:
        """Seq and inputs as Python floats of a well-formed frame, else None (``parse`` says why). The
        hot path of binary lock-step: one ``struct`` call, no arrays for a few values."""
        if len(data) != self.size:
            return None
        magic, number, *values = self._struct.unpack(data)
        if magic != binary.WS_CLIENT_MAGIC:
            return None
        return (None if number == binary.NO_SEQ else number), values

    def parse(self, data: bytes) -> tuple[int | None, NDArray[np.float32]]:
        """Seq and (U+F,) float32 inputs of a frame; ``BadInput`` naming what is wrong with it."""
        e = self.emu
        return binary.parse_ws_frame(
            data, self.width, f"model {e.model!r} ({e.num_controls} controls, {e.num_forces} forces)"
        )


# ---------------------------------------------------------------- server -> client
def pong(seq: int | None) -> str:
    return WsPong(seq=seq).model_dump_json()


def started(
    emu: LoadedEmulator, seq: int | None, realtime: bool, fmt: str, period_s: float, poses: bool, shadow: bool
) -> str:
    return WsStarted(
        seq=seq,
        mode="realtime" if realtime else "lockstep",
        format="binary" if fmt == "binary" else "json",
        super_timestep=emu.super_timestep,
        period_s=period_s,
        state_size=emu.state_size,
        num_controls=emu.num_controls,
        num_forces=emu.num_forces,
        poses=poses,
        shadow=shadow,
    ).model_dump_json()


class Drive(NamedTuple):
    """What a driven session's state message adds: the (U,) controls its driver or policy chose, and
    a policy's (G,) goal with the goal variables outside the goals it was trained for."""

    controls: NDArray[np.float32]
    goal: NDArray[np.float32] | None = None
    goal_outside: tuple[str, ...] = ()


def state_json(
    state: NDArray[np.float32],
    seq: int | None,
    t: float,
    steps: int,
    clipped_controls: list[int],
    clipped_forces: list[int],
    outside_groups: list[str],
    kinematics: Kinematics | None = None,
    shadow: MujocoShadow | None = None,
    drive: Drive | None = None,
) -> str:
    """A JSON state message (``outside_groups``: the state's groups outside the training envelope);
    ``kinematics`` adds body poses (of the shadow's state too), ``shadow`` the MuJoCo shadow's state,
    ``drive`` a driven session's controls and goal. Fields not asked for are left out."""
    kin = kinematics
    twin = None
    if shadow is not None:
        twin = ShadowState(
            state=shadow.state.tolist(),
            poses=None if kin is None else kin.poses(shadow.state[None])[0].tolist(),
            diverged=shadow.diverged,
            controls=None if shadow.controls is None else shadow.controls.tolist(),
        )
    msg = WsState(
        seq=seq,
        state=state.tolist(),
        t=t,
        steps=steps,
        clipped=bool(clipped_controls or clipped_forces),
        clipped_controls=clipped_controls,
        clipped_forces=clipped_forces,
        outside_envelope=bool(outside_groups),
        outside_groups=outside_groups,
        poses=None if kin is None else kin.poses(state[None])[0].tolist(),
        shadow=twin,
        controls=None if drive is None else drive.controls.tolist(),
        goal=None if drive is None or drive.goal is None else drive.goal.tolist(),
        goal_outside=[] if drive is None else list(drive.goal_outside),
    )
    unasked = {k for k in ("poses", "shadow", "controls", "goal") if getattr(msg, k) is None}
    if msg.goal is None:
        unasked.add("goal_outside")
    return msg.model_dump_json(exclude=unasked)


def state_binary(
    state: NDArray[np.float32], seq: int | None, steps: int, clipped: bool, outside: bool
) -> bytes:
    return binary.encode_ws_state(seq, steps, binary.CLIPPED if clipped else binary.OK, state, outside)
