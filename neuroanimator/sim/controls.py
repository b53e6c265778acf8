"""What each control of a model means (``ControlInfo``): the spec's words, else derived from the MJCF.

An actuator's transmission, gear and gain say what a control value applies: a torque on a hinge, a
force on a slide joint or along a tendon, a force and torque at a site, or (a servo, whose bias
cancels its gain) a target angle or position. ``describe_actuator`` turns that into a unit, a gain
(what ``u = 1`` applies) and the sign convention in words; ``control_info`` lays a model's
``ModelSpec.control_info`` over it, field by field.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import mujoco
import numpy as np

from neuroanimator.core.model_spec import ControlInfo

_TRN = mujoco.mjtTrn
_JOINTS = (int(_TRN.mjTRN_JOINT), int(_TRN.mjTRN_JOINTINPARENT))
_ROTATING = (int(mujoco.mjtJoint.mjJNT_HINGE), int(mujoco.mjtJoint.mjJNT_BALL))
_AXES = ("x", "y", "z")


def _name(m: mujoco.MjModel, kind: mujoco.mjtObj, i: int, fallback: str) -> str:
    return mujoco.mj_id2name(m, kind, i) or f"{fallback}{i}"


def _number(x: float) -> str:
    return f"{x:.6g}"


def _direction(v: np.ndarray) -> str:
    """A unit direction in words: '+z', '−x', or '(0.6, 0, 0.8)'."""
    n = v / np.linalg.norm(v)
    big = np.flatnonzero(np.abs(n) > 1e-9)
    if len(big) == 1:
        return ("+" if n[big[0]] > 0 else "−") + _AXES[big[0]]
    return "(" + ", ".join(_number(float(c)) for c in n) + ")"


def describe_actuator(m: mujoco.MjModel, i: int) -> ControlInfo:
    """Unit, gain and sign convention of actuator ``i``, from its MJCF alone."""
    name = _name(m, mujoco.mjtObj.mjOBJ_ACTUATOR, i, "actuator")
    gain = float(m.actuator_gainprm[i, 0])
    bias = m.actuator_biasprm[i]
    gear = np.asarray(m.actuator_gear[i], dtype=np.float64)
    affine = int(m.actuator_biastype[i]) == int(mujoco.mjtBias.mjBIAS_AFFINE)
    position_servo = affine and gain != 0 and np.isclose(bias[1], -gain) and bias[2] <= 0
    velocity_servo = affine and gain != 0 and bias[1] == 0 and np.isclose(bias[2], -gain)
    trn, target = int(m.actuator_trntype[i]), int(m.actuator_trnid[i, 0])
    if trn in _JOINTS:
        joint = _name(m, mujoco.mjtObj.mjOBJ_JOINT, target, "joint")
        hinge = int(m.jnt_type[target]) in _ROTATING
        axis = np.asarray(m.jnt_axis[target], dtype=np.float64)

        def about(direction: np.ndarray) -> str:
            where = f"{_direction(direction)} (in its body's frame"
            return f"about {where}, right-hand rule)" if hinge else f"along {where})"

        if position_servo or velocity_servo:
            what = ("angle" if hinge else "position") if position_servo else ("rate" if hinge else "speed")
            return ControlInfo(
                label=f"{joint} target {what}",
                unit=("rad" if hinge else "m") + ("" if position_servo else "/s"),
                gain=1.0,
                sign=f"a servo drives joint {joint} towards this {what}; positive is {about(axis)}",
            )
        effect = gain * float(gear[0])
        return ControlInfo(
            label=f"{'torque' if hinge else 'force'} on {joint}",
            unit="N·m" if hinge else "N",
            gain=abs(effect),
            sign=f"positive {'turns' if hinge else 'pushes'} joint {joint} {about(np.sign(effect or 1.0) * axis)}",
        )
    if trn == int(_TRN.mjTRN_TENDON):
        tendon = _name(m, mujoco.mjtObj.mjOBJ_TENDON, target, "tendon")
        effect = gain * float(gear[0])
        return ControlInfo(
            label=f"force along tendon {tendon}",
            unit="N",
            gain=abs(effect),
            sign=f"positive {'lengthens' if effect >= 0 else 'contracts'} tendon {tendon}",
        )
    if trn == int(_TRN.mjTRN_SITE):
        site = _name(m, mujoco.mjtObj.mjOBJ_SITE, target, "site")
        force, torque = gain * gear[:3], gain * gear[3:]
        parts = []
        if np.linalg.norm(force) > 0:
            parts.append(f"a force along the site's {_direction(force)} axis")
        if np.linalg.norm(torque) > 0:
            per = "" if not parts else f" of {_number(float(np.linalg.norm(torque)))} N·m per unit"
            parts.append(f"a torque{per} about its {_direction(torque)} axis (right-hand rule)")
        main = force if np.linalg.norm(force) > 0 else torque
        return ControlInfo(
            label=f"{name} at site {site}",
            unit="N" if main is force else "N·m",
            gain=float(np.linalg.norm(main)),
            sign=f"positive applies {' and '.join(parts) or 'nothing'}, in the frame of site {site}",
        )
    return ControlInfo(label=name)


def control_info(
    m: mujoco.MjModel, controls: Sequence[tuple[str, int]], given_info: Mapping[str, ControlInfo]
) -> list[ControlInfo]:
    """Per control (its name and actuator index, in order): the spec's words (``given_info``, by
    name) over what the MJCF says, field by field."""
    out = []
    for name, i in controls:
        derived = describe_actuator(m, int(i))
        given = given_info.get(name)
        if given is not None:
            derived = derived.model_copy(update=given.model_dump(exclude_none=True))
        out.append(derived)
    return out
