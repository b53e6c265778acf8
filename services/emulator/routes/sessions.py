"""Session lifecycle and REST stepping: ``/sessions``, ``/sessions/{id}``, ``/sessions/{id}/step``."""

from __future__ import annotations

import numpy as np
from fastapi import APIRouter, Response

from neuroanimator.contracts.emulator import (
    ErrorBody,
    PolicyStatus,
    SessionCreate,
    SessionInfo,
    StepRequest,
    StepResponse,
)
from neuroanimator.sim.driver import Driver
from services.emulator.deps import ServiceDep
from services.emulator.interpolation import frames
from services.emulator.service import EmulatorService
from services.emulator.sessions import Session
from services.emulator.stepping import Stepped

router = APIRouter(tags=["sessions"])
_ERRORS: dict[int | str, dict[str, object]] = {
    404: {"model": ErrorBody},
    409: {"model": ErrorBody},
    422: {"model": ErrorBody},
    429: {"model": ErrorBody},
}


def session_info(service: EmulatorService, sess: Session) -> SessionInfo:
    return SessionInfo(
        id=sess.id,
        model=sess.emu.model,
        version=sess.emu.version,
        state=sess.state.tolist(),
        t=sess.t,
        steps=sess.steps,
        diverged=sess.diverged,
        seed=sess.seed,
        ttl_s=service.settings.session_ttl_s,
        driver=sess.driver_params,
        policy=policy_status(sess),
    )


def policy_status(sess: Session) -> PolicyStatus | None:
    """The policy driving a session and its goal (None: no policy)."""
    policy = sess.policy
    if policy is None:
        return None
    m, goal = policy.manifest, sess.goal
    return PolicyStatus(
        name=m.name,
        version=m.version,
        emulator_version=m.emulator_version,
        goal_variables=m.goal_variables,
        goal=goal.tolist(),
        goal_low=m.goal_low,
        goal_high=m.goal_high,
        goal_default=m.goal_default,
        goal_outside=policy.goal_outside(goal),
        timed=m.timed,
    )


async def drive_steps(
    service: EmulatorService, sess: Session, driver: Driver, forces: list[float], steps: int
) -> Stepped:
    """``steps`` super-steps of a driven session, the driver setting the controls before each: the
    states of all, the start, and the last step's inputs."""
    runs = []
    for _ in range(steps):
        runs.append(await service.stepper.step(sess, service.driven_inputs(sess, driver, forces), 1))
    outside = sorted({g for r in runs for g in r.outside})
    controls = np.stack([r.inputs.controls for r in runs])
    states = np.concatenate([r.states for r in runs])
    return Stepped(sess, states, runs[-1].inputs, outside, runs[0].start, controls)


@router.post("/sessions", response_model=SessionInfo, status_code=201, responses=_ERRORS)
async def create_session(req: SessionCreate, service: ServiceDep) -> SessionInfo:
    """Start a session of a model (its latest version unless named) at a given or a seeded typical state;
    ``driver`` or ``policy`` make the model's driver or a trained policy set its controls (a policy's
    session runs the emulator version the policy was trained through)."""
    return session_info(service, service.create_session(req))


@router.get("/sessions/{sid}", response_model=SessionInfo, responses=_ERRORS)
async def get_session(sid: str, service: ServiceDep) -> SessionInfo:
    """A session's current state, simulated time, step count and divergence flag."""
    return session_info(service, service.store.get(sid))


@router.delete("/sessions/{sid}", status_code=204, responses=_ERRORS)
async def delete_session(sid: str, service: ServiceDep) -> Response:
    """End a session now (idle sessions also expire after SESSION_TTL_S)."""
    service.delete(sid)
    return Response(status_code=204)


@router.post("/sessions/{sid}/step", response_model=StepResponse, responses=_ERRORS)
async def step_session(sid: str, req: StepRequest, service: ServiceDep) -> StepResponse:
    """Advance a session by ``steps`` super-steps under held controls and forces (clipped to the trained
    range), optionally with interpolated frames between the states. A policy-driven session takes a
    ``goal`` (optional) and no controls: its policy sets them every super-step."""
    stepper = service.stepper
    sess = service.store.get(sid)
    stepper.check_steps(req.steps, req.frames_per_step)
    stepper.refuse_goal(sess, req.goal)
    service.drive(sess, req.driver)
    if sess.driver is None:
        inputs = stepper.session_inputs(sess, req.controls, req.forces, req.goal)
        stepped = await stepper.step(sess, inputs, req.steps)
    else:
        stepped = await drive_steps(service, sess, sess.driver, req.forces, req.steps)
    states, inputs = stepped.states, stepped.inputs
    fr = None
    if req.frames_per_step is not None and stepped.start is not None:
        fr = frames(
            np.concatenate([stepped.start[None], states]),
            req.frames_per_step,
            sess.emu.quaternion_slices,
            sess.emu.emulator.wrap,  # a heading: the shorter arc
        )
    return StepResponse(
        id=sess.id,
        state=states[-1].tolist(),
        states=states.tolist(),
        frames=None if fr is None else fr.tolist(),
        t=sess.t,
        steps=sess.steps,
        clipped=inputs.clipped,
        clipped_controls=inputs.clipped_controls,
        clipped_forces=inputs.clipped_forces,
        outside_envelope=bool(stepped.outside),
        outside_groups=stepped.outside,
        controls=None if stepped.controls is None else stepped.controls.tolist(),
        goal=None if sess.policy is None else sess.goal.tolist(),
        goal_outside=[] if sess.policy is None else sess.policy.goal_outside(sess.goal),
    )
