"""One websocket client of one session: its settings (format, poses, MuJoCo shadow), the lock-step
mode, and the real-time mode (``realtime.py``) when started. Steps go through the stepping core.

A policy-driven session's client sends goals (in ``step`` and ``controls`` messages) and forces; its
control values in binary frames are ignored (the policy sets them in the batcher), controls in JSON
messages are refused. Its JSON state messages carry the controls the policy chose and the goal."""

from __future__ import annotations

import asyncio
import logging

import numpy as np
from numpy.typing import NDArray

from neuroanimator.contracts.emulator import WsControls, WsPing, WsStart
from neuroanimator.sim.driver import load_driver
from services.emulator import binary
from services.emulator.error_mapping import ws_error
from services.emulator.errors import BadInput, EmulatorError, WrongMode
from services.emulator.scene import MujocoShadow
from services.emulator.service import EmulatorService
from services.emulator.sessions import Session
from services.emulator.stepping import Lane, outside_groups
from services.emulator.ws import protocol
from services.emulator.ws.realtime import HeldInputs, Realtime
from services.emulator.ws.transport import AsgiSocket, ClientGone, Disconnected, Frame, LatestQueue, Sender

log = logging.getLogger(__name__)
_NO_CLIP: list[int] = []


class Connection:
    """One websocket client of one session."""

    def __init__(self, socket: AsgiSocket, service: EmulatorService, sess: Session) -> None:
        s = service.settings
        self.socket = socket
        self.service = service
        self.sid = sess.id
        self.emu = sess.emu
        self.format = "json"
        self.poses = False
        self.shadow: MujocoShadow | None = None
        self.period_s = self.emu.super_timestep * s.ws_realtime_scale
        # held until the client sends inputs (a policy's session: in-range stand-ins for its controls)
        controls = (
            self.emu.inputs.neutral_controls.tolist()
            if sess.policy is not None
            else [0.0] * self.emu.num_controls
        )
        self.held = HeldInputs(service.stepper.check(self.emu, controls, [0.0] * self.emu.num_forces))
        self.last_fast: list[float] | None = None  # the inputs of the last fast lock-step frame
        self.sender = Sender(socket, s.ws_send_timeout_s)
        self.queue: LatestQueue[Frame] = LatestQueue(s.ws_queue_size)
        self.realtime: Realtime | None = None
        self.frames = protocol.InputFrames(self.emu)
        self.lane = service.stepper.lane(self.emu, "ws")
        self.policy_driven = sess.policy is not None  # (a session's policy is set when it is created)
        self._main: asyncio.Task[object] | None = None
        self.gone = False

    @property
    def mode(self) -> str:
        return "realtime" if self.realtime is not None and self.realtime.ticking else "lockstep"

    def session(self) -> Session:
        return self.service.store.get(self.sid)

    def check(
        self,
        controls: list[float],
        forces: list[float],
        seq: int | None,
        driver: dict[str, float] | None = None,
        goal: list[float] | None = None,
    ) -> HeldInputs:
        """Inputs from a JSON message (an unknown session is reported before bad inputs). A driven
        session takes new driver parameters from it, and only its forces: the driver sets the controls.
        A policy-driven one takes its new goal and its forces, and refuses controls."""
        sess = self.session()
        stepper = self.service.stepper
        stepper.refuse_goal(sess, goal)
        self.service.drive(sess, driver)
        if sess.driver is None:
            return HeldInputs(stepper.session_inputs(sess, controls, forces, goal), seq)
        if driver and self.shadow is not None and self.shadow.driver is not None:
            self.shadow.driver.configure(sess.driver_params or {})
        controls = [0.0] * self.emu.num_controls  # replaced by the driver's at each step
        return HeldInputs(stepper.check(self.emu, controls, forces), seq)

    # ------------------------------------------------------------------ states out
    def state_frame(self, sess: Session, state: NDArray[np.float32], held: HeldInputs) -> Frame:
        inputs = held.inputs
        if self.format == "binary":
            return protocol.state_binary(state, held.seq, sess.steps, inputs.clipped, sess.outside_envelope)
        drive = None
        if sess.policy is not None:
            goal = sess.goal
            drive = protocol.Drive(sess.applied_controls, goal, tuple(sess.policy.goal_outside(goal)))
        elif sess.driver is not None:
            drive = protocol.Drive(inputs.controls)
        return protocol.state_json(
            state,
            held.seq,
            sess.t,
            sess.steps,
            inputs.clipped_controls,
            inputs.clipped_forces,
            outside_groups(sess, state),
            self.emu.kinematics if self.poses else None,
            self.shadow,
            drive,
        )

    # ------------------------------------------------------------------ lock-step
    async def advance(self, held: HeldInputs, lane: Lane) -> Frame:
        """One super-step of the session (and its shadow) under these inputs: the state frame."""
        sess = self.session()
        if sess.driver is not None:  # the model's controller sets the controls; the client's forces hold
            held = HeldInputs(
                self.service.driven_inputs(sess, sess.driver, held.inputs.forces.tolist()), held.seq
            )
        since_goal = sess.steps - sess.goal_step  # (a policy's twin reads the clock of the session's goal)
        out = await lane.step(sess, held.inputs.row)
        if self.shadow is not None:
            goal = sess.goal if sess.policy is not None else None
            self.shadow.step(held.inputs.controls, held.inputs.forces, goal, since_goal)
        return self.state_frame(sess, out, held)

    async def lockstep(self, held: HeldInputs) -> Frame:
        """A lock-step step: the state frame (or the error) answering it. Its inputs are held: real
        time, started next, goes on with them until a ``controls`` message changes them."""
        self.held, self.last_fast = held, None
        try:
            return await self.advance(held, self.lane)
        except EmulatorError as exc:
            return ws_error(exc, held.seq)

    async def lockstep_fast(self, seq: int | None, values: list[float]) -> Frame:
        """A binary lock-step frame whose inputs are all in range, without a shadow: ``lockstep`` in
        fewer operations (no arrays for one session's inputs)."""
        self.last_fast = values  # made the held inputs only if real time starts next
        try:
            sess = self.service.store.get(self.sid)
            out = await self.lane.step(sess, values)
        except EmulatorError as exc:
            return ws_error(exc, seq)
        if self.format == "binary":
            return binary.encode_ws_state(seq, sess.steps, binary.OK, out, sess.outside_envelope)
        kin = self.emu.kinematics if self.poses else None
        return protocol.state_json(
            out, seq, sess.t, sess.steps, _NO_CLIP, _NO_CLIP, outside_groups(sess, out), kin
        )

    # ------------------------------------------------------------------ messages in
    async def on_text(self, text: str) -> Frame | None:
        seq, msg = protocol.read_text(text)
        try:
            if isinstance(msg, EmulatorError):
                raise msg
            if isinstance(msg, WsPing):
                return protocol.pong(msg.seq)
            if isinstance(msg, WsStart):
                return await self.start(msg)
            if isinstance(msg, WsControls):
                self.held = self.check(msg.controls, msg.forces, msg.seq, msg.driver, msg.goal)
                return None
            if self.mode == "realtime":
                raise WrongMode(
                    "step messages are for lock-step mode; in real-time mode send controls messages "
                    '(or {"type": "start", "mode": "lockstep"} first)',
                    field="type",
                    expected="controls",
                    got="step",
                )
            held = self.check(msg.controls, msg.forces, msg.seq, msg.driver, msg.goal)
        except EmulatorError as exc:
            return ws_error(exc, seq)
        return await self.lockstep(held)

    async def on_binary(self, data: bytes) -> Frame | None:
        realtime = self.realtime
        plain = self.shadow is None and not self.emu.manifest.spec.driver and not self.policy_driven
        if plain and (realtime is None or not realtime.ticking):  # lock-step, no shadow, no driver
            fast = self.frames.unpack(data)
            # NaN fails the range check too, so it takes the general path below and is named there
            if fast is not None and self.emu.inputs.fits(fast[1]):
                return await self.lockstep_fast(*fast)
        seq = None
        try:
            seq, values = self.frames.parse(data)
            self.session()  # an unknown session is reported before bad inputs
            if self.policy_driven:  # its policy sets the controls: the frame's are ignored
                values = values.copy()
                values[: self.emu.num_controls] = self.emu.inputs.neutral_controls
            held = HeldInputs(self.emu.inputs.check_row(values), seq)
        except EmulatorError as exc:
            return ws_error(exc, seq)
        if self.mode == "realtime":
            self.held = held
            return None
        return await self.lockstep(held)

    # ------------------------------------------------------------------ settings and modes
    async def start(self, msg: WsStart) -> str:
        """Apply a ``start`` (its settings, then its mode): the ``started`` message."""
        want_poses = self.poses if msg.poses is None else msg.poses
        want_shadow = (self.shadow is not None) if msg.shadow is None else msg.shadow
        if (msg.format or self.format) == "binary" and (want_poses or want_shadow):
            raise BadInput(
                "poses and shadow come in JSON state messages only; ask for format json "
                "(or leave poses and shadow off for binary frames)",
                code="needs_json",
                field="format",
                expected="json",
                got="binary",
            )
        if msg.format is not None:
            self.format = msg.format
        self.poses = want_poses
        if msg.shadow is True:  # (re)start the shadow from the session's current state
            sess = self.session()
            driver = None
            if sess.driver is not None and sess.emu.manifest.spec.driver is not None:  # its own controller
                spec = sess.emu.manifest.spec.driver
                driver = load_driver(spec, sess.emu.physical, sess.emu.substeps, sess.driver_params or {})
            self.shadow = MujocoShadow(sess.emu.physical, sess.emu.substeps, sess.state, driver, sess.policy)
        elif msg.shadow is False:
            self.shadow = None
        if msg.mode == "realtime":
            if self.last_fast is not None:  # the last lock-step inputs, held on into real time
                row = np.asarray(self.last_fast, dtype=np.float32)
                self.held, self.last_fast = HeldInputs(self.emu.inputs.check_row(row)), None
            if self.realtime is None:
                self.realtime = Realtime(self)
            self.realtime.start()
        else:
            await self.stop_realtime()
        return protocol.started(
            self.emu,
            msg.seq,
            self.mode == "realtime",
            self.format,
            self.period_s,
            self.poses,
            self.shadow is not None,
        )

    async def stop_realtime(self) -> None:
        if self.realtime is not None:
            await self.realtime.stop()
            self.realtime = None
        self.queue.clear()

    def end(self) -> None:
        """The client is gone (noticed by a send of the real-time pusher): end the connection."""
        self.gone = True
        if self._main is not None:
            self._main.cancel()

    # ------------------------------------------------------------------ the connection
    async def run(self) -> None:
        """Answer the client's messages until it disconnects."""
        self._main = asyncio.current_task()
        try:
            while True:
                msg = await self.socket.receive()
                if msg["type"] == "websocket.disconnect":
                    break
                data = msg.get("bytes")
                reply = await (
                    self.on_binary(data) if data is not None else self.on_text(msg.get("text") or "")
                )
                if reply is not None:
                    await self.sender.reply(reply)
        except (Disconnected, ClientGone):
            pass
        except asyncio.CancelledError:
            if not self.gone:
                raise
        finally:
            self._main = None
            await self.stop_realtime()
