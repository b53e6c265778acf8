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

from neuroanimator.core.model_spec import ModelSpec
from neuroanimator.core.operating_spec import OperatingRecord, OperatingSpec, StartSpread
from neuroanimator.sim.errors import ModelError
from neuroanimator.sim.model import PhysicalModel

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


# ---------------------------------------------------------------------------- typical motion

POSITION_SPREAD = 0.3
"""Default half-width of a start's joint positions (rad or m) and velocities around the operating state."""
VELOCITY_SPREAD = 0.3
TILT = 0.3
"""Default largest tilt of a free root's start, rad."""
CONTROL_SPREAD_AT_POINT = 0.05
"""Default half-width of the controls around an operating point found (a keyframe's, a hold's), as a share
of each ``ctrlrange``: a hovering drone's thrusts within ±5 % of their range of the hover thrust."""
HELD_SHARE_AT_POINT = 0.2
"""Default share of runs whose controls stay at an operating point found: holding still is what a user
asks of a hovering drone or a standing arm first, and an emulator that never saw it drifts there."""
AT_POINT_SHARE = 1 / 3
"""Around an operating point found, starts spread a third as far (±0.1 rad or m on joints, ±0.1 on
velocities, a tilt of 0.1 rad): a drone hovering 1 m over its floor and tilted 0.3 rad reaches the floor
within a second (the reinmav-gym quadrotor), and its crashes were most of its emulator's error."""
RUN_S = 20.0
"""Default seconds of a training run before it restarts from a typical start."""


class OperatingSpecError(ModelError):
    """An operating spec that does not fit the model; ``field`` names the spec's field (dotted)."""

    def __init__(self, field: str, message: str) -> None:
        super().__init__(f"operating spec, {field}: {message}")
        self.field = field
        self.reason = message  # the problem, without the field


def _names(m: mujoco.MjModel, kind: mujoco.mjtObj, count: int, prefix: str) -> list[str]:
    return [mujoco.mj_id2name(m, kind, i) or f"{prefix}{i}" for i in range(count)]


def _state_of(model: PhysicalModel, point: Keyframe) -> FloatArray:
    """(S,) the emulator's state at a keyframe (its activations at its controls, as held there)."""
    m = model.mj_model
    d = mujoco.MjData(m)
    d.qpos[:], d.qvel[:] = point.qpos, point.qvel
    if m.na:
        has_act = m.actuator_actadr >= 0
        d.act[m.actuator_actadr[has_act]] = point.ctrl[has_act]
    full = np.empty(mujoco.mj_stateSize(m, mujoco.mjtState.mjSTATE_FULLPHYSICS))
    mujoco.mj_getState(m, d, full, mujoco.mjtState.mjSTATE_FULLPHYSICS)
    return np.asarray(model.from_physics(full[None, :])[0], dtype=np.float64)


def _start_spread(model: PhysicalModel, start: StartSpread, found: bool) -> tuple[FloatArray, float]:
    """(S,) half-width of each state value at a start, and the free root's largest tilt: the spec's,
    else the defaults, narrower around an operating point ``found``."""
    m = model.mj_model
    joints = _names(m, mujoco.mjtObj.mjOBJ_JOINT, m.njnt, "joint")
    near = AT_POINT_SHARE if found else 1.0
    position = near * POSITION_SPREAD if start.position_spread is None else start.position_spread
    velocity = near * VELOCITY_SPREAD if start.velocity_spread is None else start.velocity_spread
    speed = velocity if start.speed is None else start.speed
    half = np.zeros(model.state_size)
    for g, sl in model.layout.group_slices():
        if g.source == "act":  # an activation: anywhere its control can drive it (the band decides)
            continue
        if g.kind in ("angle", "scalar") and g.source == "qpos":  # a free root's place: translations
            half[sl] = position
        elif g.source == "qvel":
            half[sl] = speed if g.kind == "world_vector" else velocity
    for name, spread in start.joints.items():
        if name not in joints:
            raise OperatingSpecError(
                f"start.joints.{name}", f"the model has no joint {name!r}; its joints are {joints}"
            )
        j = joints.index(name)
        if int(m.jnt_type[j]) not in (int(mujoco.mjtJoint.mjJNT_HINGE), int(mujoco.mjtJoint.mjJNT_SLIDE)):
            raise OperatingSpecError(
                f"start.joints.{name}",
                "a spread per joint is for hinge and slide joints; a free root's is tilt/speed",
            )
        if spread < 0:
            raise OperatingSpecError(f"start.joints.{name}", f"a spread must be 0 or more, got {spread:g}")
        group = next(g for g in model.layout if g.source == "qpos" and g.address == int(m.jnt_qposadr[j]))
        half[model.layout.slice_of(group.name)] = spread
    return half, near * TILT if start.tilt is None else start.tilt


def _control_bands(
    model: PhysicalModel, spec: OperatingSpec, centres: FloatArray, found: bool
) -> tuple[FloatArray, FloatArray]:
    """(K, U) control centres and (U,) half-widths from the spec over the operating point's centres (K, U):
    a control the spec names takes its band; the others keep their centre, with ``control_spread`` of
    their range around it (by default ``CONTROL_SPREAD_AT_POINT`` around a point ``found``, else half
    the range: all of it)."""
    m = model.mj_model
    names = list(model.control_names)
    limits = control_ranges(model)
    width = limits[:, 1] - limits[:, 0]
    default = CONTROL_SPREAD_AT_POINT if found else 0.5
    share = spec.control_spread if spec.control_spread is not None else default
    spread = share * width
    centres = centres.copy()
    for name, band in spec.controls.items():
        if name not in names:
            everyone = _names(m, mujoco.mjtObj.mjOBJ_ACTUATOR, m.nu, "actuator")
            raise OperatingSpecError(
                f"controls.{name}",
                f"the model has no actuator {name!r}; its controls are {names or everyone}",
            )
        k = names.index(name)
        lo, hi = limits[k]
        if band.range is not None:
            centres[:, k], spread[k] = (
                (band.range[0] + band.range[1]) / 2,
                (band.range[1] - band.range[0]) / 2,
            )
        else:
            if band.centre is not None:
                centres[:, k] = band.centre
            if band.spread is not None:
                spread[k] = band.spread
        low, high = centres[:, k].min() - spread[k], centres[:, k].max() + spread[k]
        if low < lo - 1e-9 or high > hi + 1e-9:
            raise OperatingSpecError(
                f"controls.{name}",
                f"[{low:g}, {high:g}] lies outside the actuator's ctrlrange [{lo:g}, {hi:g}]",
            )
    return centres, spread


def _actuator_of(m: mujoco.MjModel, address: int) -> int:
    """The actuator whose activation sits at ``act[address]``."""
    return int(np.flatnonzero(m.actuator_actadr == address)[0])


def control_envelope(
    centres: FloatArray, spread: FloatArray, ranges: FloatArray
) -> tuple[list[float], list[float]]:
    """(U,) low and high of every band around the centres (K, U), half-widths ``spread`` (U,), within
    ``ranges`` (U, 2): the controls an emulator is trained on (``ModelSpec.control_low``/``high``)."""
    low = np.clip(centres.min(axis=0) - spread, ranges[:, 0], ranges[:, 1])
    high = np.clip(centres.max(axis=0) + spread, ranges[:, 0], ranges[:, 1])
    return low.tolist(), high.tolist()


def control_ranges(model: PhysicalModel) -> FloatArray:
    """(U, 2) each control's ctrlrange, ±1 where unlimited (not ``control_range``: the spec's envelope)."""
    lim = model.control_limits.copy()
    lim[~np.isfinite(lim[:, 0]), 0] = -1.0
    lim[~np.isfinite(lim[:, 1]), 1] = 1.0
    return lim


def typical_motion(
    model: PhysicalModel, spec: OperatingSpec | None = None, keyframe: str | None = None
) -> ModelSpec:
    """The model's spec with its typical motion set around its operating point (``find``) and the
    user's ``spec``: starts spread around the operating states, controls centred on theirs, the
    controls' time scale and the run length; the record of it in ``ModelSpec.operating``.

    Raises ``OperatingSpecError`` (naming the field) for a spec that does not fit the model."""
    spec = spec or OperatingSpec()
    if keyframe is not None and spec.keyframe is not None and keyframe != spec.keyframe:
        raise OperatingSpecError(
            "keyframe", f"--keyframe {keyframe!r} and the spec's {spec.keyframe!r} differ"
        )
    named = keyframe or spec.keyframe
    try:
        point = find(model.mj_model, named)
    except ModelError as exc:
        raise OperatingSpecError("keyframe", str(exc)) from exc
    limits = control_ranges(model)
    if point.points:
        centres = np.stack([k.ctrl[model.control_ids] for k in point.points])
        starts = [_state_of(model, k).tolist() for k in point.points]
    else:
        centres, starts = limits.mean(axis=1)[None, :], []
    centres = np.clip(centres, limits[:, 0], limits[:, 1])
    centres, spread = _control_bands(model, spec, centres, bool(point.points))
    half, tilt = _start_spread(model, spec.start, bool(point.points))
    given = spec != OperatingSpec()
    source = point.source if point.source != "none" or not given else "spec"
    reason = point.reason if source != "spec" else f"the operating spec given ({point.reason})"
    record = OperatingRecord(
        source=source,
        reason=reason,
        keyframes=[k.name for k in point.points],
        # none found and nothing declared: controls over their whole range, as drawn without a point
        control_centres=centres.tolist() if point.points or given else [],
        control_spread=spread.tolist() if point.points or given else [],
        held_share=(
            spec.held_share if spec.held_share is not None else HELD_SHARE_AT_POINT if point.points else 0.0
        ),
        spec=spec if given else None,
    )
    low = -half
    if not point.points and not given:  # today's starts: an activation anywhere in its control's range
        for g, sl in model.layout.group_slices():
            if g.source == "act":
                k = int(np.flatnonzero(model.control_ids == _actuator_of(model.mj_model, g.address))[0])
                low[sl], half[sl] = limits[k]
    else:  # around the operating state's activation (its control there), as far as the control's band
        for g, sl in model.layout.group_slices():
            if g.source == "act":
                k = int(np.flatnonzero(model.control_ids == _actuator_of(model.mj_model, g.address))[0])
                low[sl], half[sl] = -spread[k], spread[k]
    initial = model.spec.initial.model_copy(
        update={
            "low": low.tolist(),
            "high": half.tolist(),
            "centres": starts,
            "max_tilt": tilt,
            "random_yaw": True,
        }
    )
    update: dict[str, object] = {"initial": initial, "operating": record}
    if point.points or given:
        update["control_low"], update["control_high"] = control_envelope(centres, spread, limits)
    if spec.time_scale_s is not None:
        update["control_spacing_s"] = spec.time_scale_s
    update["episode_s"] = spec.run_s if spec.run_s is not None else RUN_S
    return model.spec.model_copy(update=update)
