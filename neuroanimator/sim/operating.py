"""Where a model operates, read from the model itself: its keyframes, else the controls that hold it
still at ``qpos0``.

Typical motion drawn over every actuator's whole ``ctrlrange`` suits a pendulum; a drone or an arm
works in a narrow band around an operating point (a hovering drone's four thrusts, an arm's torques
against gravity), and uniform controls spin the one up and fling the other about. MuJoCo models
carry what is needed to do better:

- keyframes (``<key qpos qvel ctrl>``): where the model's author says it operates;
- the physics: ``mj_inverse`` gives the generalised force ``τ`` (nv,) that holds a state still
  (zero acceleration), and the actuators map controls to generalised forces, affinely at a fixed
  state: ``f(u) = f(0) + A u``. Controls that hold the model still solve ``f(u) = τ``; they exist when
  the actuators can produce ``τ`` (a drone's thrusters can; a walker's legs cannot hold its free root
  in the air) within their ``ctrlrange``.

``find`` tries them in that order and says which it used and why. Nothing here draws samples: the
sampler centres its starts and controls on what is found.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import mujoco
import numpy as np
from numpy.typing import NDArray

from neuroanimator.sim.errors import ModelError

FloatArray = NDArray[np.float64]

HOLD_RTOL = 1e-3
"""Controls hold the model still when the generalised force they leave unbalanced is at most this share
of the force needed (plus ``HOLD_ATOL``)."""
HOLD_ATOL = 1e-8
NOTHING_TO_HOLD = 1e-9
"""A needed force this small (in the units of the generalised forces) is nothing to hold against: no
gravity load on the actuated joints, as a cart-pole at ``qpos0``."""

Source = Literal["keyframe", "hold", "none"]


@dataclass(frozen=True)
class Keyframe:
    """One operating state: positions (nq,), velocities (nv,) and the controls (nu,) held there."""

    name: str
    qpos: FloatArray
    qvel: FloatArray
    ctrl: FloatArray


@dataclass(frozen=True)
class OperatingPoint:
    """Where a model operates (``points``: every keyframe used, or the one holding state), how it was
    found (``source``) and why, in words for a log, a training's status and the manifest."""

    source: Source
    points: tuple[Keyframe, ...]
    reason: str


def keyframes(m: mujoco.MjModel) -> list[Keyframe]:
    """The model's keyframes, in order; an unnamed one is ``key<i>``."""
    out = []
    for i in range(m.nkey):
        name = mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_KEY, i) or f"key{i}"
        out.append(
            Keyframe(
                name=name,
                qpos=np.array(m.key_qpos[i], dtype=np.float64),
                qvel=np.array(m.key_qvel[i], dtype=np.float64),
                ctrl=np.array(m.key_ctrl[i], dtype=np.float64),
            )
        )
    return out


def _probe_values(m: mujoco.MjModel) -> tuple[FloatArray, FloatArray]:
    """(nu,) two controls per actuator inside its range: probing outside it would read the clamped
    force, not the map."""
    lo = np.where(m.actuator_ctrllimited, m.actuator_ctrlrange[:, 0], -1.0)
    hi = np.where(m.actuator_ctrllimited, m.actuator_ctrlrange[:, 1], 1.0)
    return lo + 0.25 * (hi - lo), lo + 0.75 * (hi - lo)


def _actuator_force(m: mujoco.MjModel, d: mujoco.MjData, ctrl: FloatArray) -> FloatArray:
    """(nv,) the generalised force of the actuators at controls ``ctrl`` (nu,), at ``d``'s state. An
    actuator with its own dynamics is taken at its steady state, its activation equal to its control."""
    d.ctrl[:] = ctrl
    has_act = m.actuator_actadr >= 0
    if np.any(has_act):
        d.act[m.actuator_actadr[has_act]] = ctrl[has_act]
    mujoco.mj_forward(m, d)
    return np.array(d.qfrc_actuator, dtype=np.float64)


def hold_controls(m: mujoco.MjModel, qpos: FloatArray | None = None) -> tuple[FloatArray, float, float]:
    """The controls (nu,) that come nearest to holding the model still at ``qpos`` (default ``qpos0``)
    with zero velocity, within each ``ctrlrange``; with the force they must balance ``|τ|`` and the
    force they leave unbalanced (both the norm over the nv generalised forces)."""
    d = mujoco.MjData(m)
    d.qpos[:] = m.qpos0 if qpos is None else qpos
    d.qvel[:] = 0.0
    mujoco.mj_forward(m, d)
    d.qacc[:] = 0.0
    mujoco.mj_inverse(m, d)
    need = np.array(d.qfrc_inverse, dtype=np.float64)  # (nv,) what actuators and pushes must apply
    a, b = _probe_values(m)
    base = _actuator_force(m, d, a)
    gain = np.zeros((m.nv, m.nu))  # (nv, nu) the force of one unit of each control, about ``a``
    for i in range(m.nu):
        u = a.copy()
        u[i] = b[i]
        gain[:, i] = (_actuator_force(m, d, u) - base) / (b[i] - a[i])
    u = a + np.linalg.lstsq(gain, need - base, rcond=None)[0]
    lo = np.where(m.actuator_ctrllimited, m.actuator_ctrlrange[:, 0], -np.inf)
    hi = np.where(m.actuator_ctrllimited, m.actuator_ctrlrange[:, 1], np.inf)
    u = np.clip(u, lo, hi)
    left = float(np.linalg.norm(_actuator_force(m, d, u) - need))  # measured, not assumed linear
    return u, float(np.linalg.norm(need)), left


def find(m: mujoco.MjModel, keyframe: str | None = None) -> OperatingPoint:
    """Where the model operates: the keyframe named ``keyframe``, else every keyframe, else the controls
    that hold it still at ``qpos0``, else nowhere in particular (``source="none"``: typical controls
    over each control's range). ``ModelError`` names the keyframes when ``keyframe`` is not one."""
    keys = keyframes(m)
    if keyframe is not None:
        chosen = [k for k in keys if k.name == keyframe]
        if not chosen:
            have = [k.name for k in keys]
            raise ModelError(f"the model has no keyframe {keyframe!r}; its keyframes are {have}")
        return OperatingPoint("keyframe", tuple(chosen), f"keyframe {keyframe!r}, as asked")
    if keys:
        names = ", ".join(repr(k.name) for k in keys)
        return OperatingPoint("keyframe", tuple(keys), f"the model's keyframes ({names})")
    if m.nu == 0:
        return OperatingPoint("none", (), "no actuators: nothing to centre controls on")
    u, need, left = hold_controls(m)
    if need <= NOTHING_TO_HOLD:
        return OperatingPoint("none", (), "nothing to hold against at qpos0: controls over their ranges")
    if left > HOLD_RTOL * need + HOLD_ATOL:
        return OperatingPoint(
            "none",
            (),
            f"no controls hold it still at qpos0 (the actuators leave {left:.3g} of the {need:.3g} "
            "generalised force unbalanced): controls over their ranges",
        )
    point = Keyframe("hold", np.array(m.qpos0, dtype=np.float64), np.zeros(m.nv), u)
    held = ", ".join(f"{x:.4g}" for x in u)
    return OperatingPoint("hold", (point,), f"the controls that hold it still at qpos0: [{held}]")
