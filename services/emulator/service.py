"""``EmulatorService``: everything one service process holds, shared by every transport.

The artifact registry (loaded emulators), the policies (``policies.py``), the session store, the
stepping core (``stepping.py``), metrics and the open websocket connections; sessions are created and
deleted here, and given the model's driver or a policy. Transports reach it as
``request.app.state.service`` (``deps.ServiceDep``).
"""

from __future__ import annotations

import asyncio
import logging
import secrets
from collections.abc import Mapping, Sequence
from typing import Protocol

import numpy as np
from numpy.typing import NDArray

from neuroanimator.contracts.emulator import PolicyDrive, SessionCreate
from neuroanimator.sim.driver import Driver, DriverError, check_params, load_driver
from services.common.auth import CALLER
from services.emulator.errors import BadInput, UnknownSession
from services.emulator.inputs import CheckedInputs, check_vector
from services.emulator.metrics import Metrics
from services.emulator.policies import LoadedPolicy, PolicyRegistry, check_drive
from services.emulator.registry import LoadedEmulator, Registry
from services.emulator.sessions import Session, SessionStore
from services.emulator.settings import Settings
from services.emulator.stepping import Stepper

log = logging.getLogger(__name__)


class OpenSocket(Protocol):
    """An open websocket connection, as the service keeps count of them (``ws.connection``)."""

    sid: str


class EmulatorService:
    """The emulators, sessions, stepping core and metrics of one service process."""

    def __init__(self, settings: Settings) -> None:
        self.settings = settings
        self.registry = Registry(settings.roots(), settings.ort_threads, settings.registry_poll_s)
        self.policies = PolicyRegistry(settings.roots(), settings.ort_threads)
        self.store = SessionStore(
            settings.replica_id, settings.session_ttl_s, settings.max_sessions, settings.max_sessions_per_key
        )
        self.metrics = Metrics()
        self.stepper = Stepper(settings, self.store, self.metrics)
        self.connections: set[OpenSocket] = set()  # open websocket connections (services/emulator/ws/)
        self.registry.refresh()

    async def close(self) -> None:
        await self.stepper.close()

    async def sweep_forever(self) -> None:
        while True:
            await asyncio.sleep(self.settings.sweep_interval_s)
            self.store.expire()
            self.update_gauges()

    def update_gauges(self) -> None:
        for (model, version), n in self.store.count_by_model().items():
            self.metrics.sessions.labels(model, version).set(n)

    # ------------------------------------------------------------------ sessions
    def create_session(self, req: SessionCreate) -> Session:
        """A session at the given state (checked; quaternion groups normalised) or at a typical start
        drawn from the seed (one of its policy's own starts when it has them), owned by the caller's
        API key; driven by the model's driver or by a policy (of the emulator version it was trained
        through: the session's) when asked."""
        policy, goal = None, None
        if req.policy is not None:
            if req.driver is not None:
                raise BadInput(
                    "a session is driven by the model's driver or by a policy, not both",
                    code="driver_and_policy",
                    field="policy",
                    expected="driver or policy",
                    got="both",
                )
            policy = self.policies.get(req.model, req.policy.name, req.policy.version)
        # a policy drives the emulator version it was trained through: the session's, unless named
        version = (
            req.version if req.version is not None or policy is None else policy.manifest.emulator_version
        )
        emu = self.registry.get(req.model, version)
        if policy is not None:
            assert req.policy is not None
            goal = self.policy_goal(emu, policy, req.policy)
        seed = None
        if req.state is not None:
            state = check_vector("state", req.state, emu.state_size, f"model {emu.model!r}").copy()
            for sl in emu.quaternion_slices:
                norm = float(np.linalg.norm(state[sl]))
                if not norm > 1e-6:
                    raise BadInput(
                        f"state[{sl.start}:{sl.stop}] is a quaternion and must not be zero",
                        code="bad_quaternion",
                        field=f"state[{sl.start}:{sl.stop}]",
                        expected="a nonzero quaternion [w, x, y, z]",
                        got=[float(v) for v in state[sl]],
                    )
                state[sl] /= norm
        else:
            seed = req.seed if req.seed is not None else secrets.randbits(63)
            starts = policy.manifest.starts if policy is not None else []
            # a policy starts where its task's runs start (a running stride, not a standing pose)
            state = np.asarray(starts[seed % len(starts)], np.float32) if starts else emu.initial_state(seed)
        driver = None
        if req.driver is not None:
            params = self.driver_params(emu, req.driver)
            spec = emu.manifest.spec.driver
            assert spec is not None  # driver_params refuses a model without one
            driver = load_driver(spec, emu.physical, emu.substeps, params)
            if req.state is None:  # where the driven motion starts; no random draw
                state, seed = driver.start().astype(np.float32), None
        sess = self.store.create(emu, state, seed, owner=CALLER.get())
        if driver is not None:
            sess.attach_driver(driver, params)
        if policy is not None and goal is not None:
            sess.attach_policy(policy, goal)
        self.update_gauges()
        log.info("session created", extra={"session": sess.id, "model": emu.model, "version": emu.version})
        return sess

    # ------------------------------------------------------------------ policies
    @staticmethod
    def policy_goal(emu: LoadedEmulator, policy: LoadedPolicy, req: PolicyDrive) -> NDArray[np.float32]:
        """The (G,) goal a new session of ``emu`` starts with under ``policy`` (its default when not
        given); ``PolicyMismatch`` for another emulator version, ``BadInput`` for a bad goal."""
        policy.check_emulator(emu.model, emu.version)
        check_drive(policy, emu.state_size, emu.num_controls)
        if req.goal is None:
            return policy.default_goal.copy()
        return policy.check_goal(req.goal, "policy.goal")

    # ------------------------------------------------------------------ drivers
    @staticmethod
    def driver_params(emu: LoadedEmulator, given: Mapping[str, float]) -> dict[str, float]:
        """The model's driver's parameters, ``given`` over its defaults; ``BadInput`` naming the problem."""
        try:
            return check_params(emu.manifest.spec.driver, emu.model, given)
        except DriverError as exc:
            raise BadInput(str(exc), code="bad_driver", field="driver", got=dict(given)) from None

    def drive(self, sess: Session, params: Mapping[str, float] | None) -> None:
        """New parameters for a driven session's driver (``None``: unchanged); ``BadInput`` for a session
        without a driver."""
        if params is None:
            return
        if sess.driver is None:
            raise BadInput(
                f"session {sess.id} has no driver: create it with a driver to set driver parameters",
                code="no_driver",
                field="driver",
                got=dict(params),
            )
        full = self.driver_params(sess.emu, {**(sess.driver_params or {}), **params})
        sess.driver.configure(full)
        sess.driver_params = full

    def driven_inputs(self, sess: Session, driver: Driver, forces: Sequence[float]) -> CheckedInputs:
        """The inputs of a driven session's next super-step: the driver's controls for its current
        state, and the client's (checked) forces."""
        controls = driver.act(sess.state)
        return self.stepper.check(sess.emu, controls.tolist(), list(forces))

    def delete(self, sid: str) -> None:
        """``UnknownSession`` unless it exists and the caller's key (if any) owns it."""
        self.store.get(sid)
        if not self.store.delete(sid):
            raise UnknownSession.named(sid)
        self.update_gauges()
