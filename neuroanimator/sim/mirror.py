"""Left-right mirror symmetry of a model: the map that reflects a state, its controls and its force
inputs across the model's sagittal plane (world y → −y), found from the MJCF.

A figure built symmetric (a left and a right limb that are each other's reflection) moves under the
reflected controls exactly as the reflection of its motion: MuJoCo's step commutes with the mirror.
So every simulated transition gives a second one for free, its mirror image, in which the left leg
does what the right leg did. For an emulator of such a figure that doubles the examples of each limb
without simulating more (``runner_data`` uses it).

How each coordinate reflects (M = diag(1, −1, 1)):
- a free joint's position: (x, −y, z); its quaternion (w, −x, y, −z) (the rotation M R M); its
  linear velocity (world frame) as a vector, M v; its angular velocity (body frame) as a pseudovector,
  −M ω;
- a hinge maps onto its partner (``left_*`` ↔ ``right_*``, else itself), with the sign that makes the
  reflected axis (a pseudovector, −M a) the partner's axis; a slide likewise, its axis a vector (M a);
- an actuator onto its partner's, with its joint's sign;
- a force input onto the one on the partner body with the same component, a force reflected as a
  vector and a torque as a pseudovector.

``mirror_map`` raises ``MirrorError`` where the model is not symmetric: a joint or actuator without a
partner, an axis that does not reflect onto its partner's, partners of different masses.

Shapes: N transitions, S state, U controls, F force inputs.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import mujoco
import numpy as np
from numpy.typing import NDArray

from neuroanimator.core.model_spec import ForceInput
from neuroanimator.core.state import StateLayout
from neuroanimator.sim.model import ModelError, PhysicalModel
from neuroanimator.sim.sampling import Examples

FloatArray = NDArray[np.float64]
_M = np.array([1.0, -1.0, 1.0])  # the reflection y -> -y
_TOL = 1e-6
_COMMUTE_TOL = 1e-6  # of the largest change in the transitions checked


class MirrorError(ModelError):
    """The model is not left-right symmetric: the message says where."""

    def __init__(self, why: str) -> None:
        super().__init__(f"the model is not left-right symmetric, so it has no mirror images: {why}")
        self.why = why

    def __reduce__(self) -> tuple[type[MirrorError], tuple[str]]:
        return type(self), (self.why,)


def partner_name(name: str) -> str:
    """The mirror partner's name: ``left`` and ``right`` swapped (``left_hip`` ↔ ``right_hip``)."""
    if "left" in name:
        return name.replace("left", "right")
    if "right" in name:
        return name.replace("right", "left")
    return name


@dataclass(frozen=True)
class Mirror:
    """Index and sign of each mirrored column: ``mirrored[:, i] = sign[i] * x[:, index[i]]``."""

    state_index: NDArray[np.int64]
    state_sign: FloatArray
    control_index: NDArray[np.int64]
    control_sign: FloatArray
    force_index: NDArray[np.int64]
    force_sign: FloatArray

    def state(self, s: FloatArray) -> FloatArray:
        """(N, S) the mirror images of states (N, S)."""
        return s[..., self.state_index] * self.state_sign

    def controls(self, u: FloatArray) -> FloatArray:
        """(N, U) the mirrored controls."""
        return u[..., self.control_index] * self.control_sign

    def forces(self, f: FloatArray) -> FloatArray:
        """(N, F) the mirrored force inputs."""
        return f[..., self.force_index] * self.force_sign


def _name(m: mujoco.MjModel, kind: mujoco.mjtObj, i: int) -> str:
    return mujoco.mj_id2name(m, kind, i) or ""


def _id(m: mujoco.MjModel, kind: mujoco.mjtObj, name: str, what: str) -> int:
    i = mujoco.mj_name2id(m, kind, name)
    if i < 0:
        raise MirrorError(f"{what} has no mirror partner named {name!r}")
    return int(i)


def _joint_maps(m: mujoco.MjModel) -> tuple[list[int], list[float], list[int], list[float], list[float]]:
    """qpos and qvel (index, sign) of the mirror image, and each joint's sign."""
    d = mujoco.MjData(m)
    mujoco.mj_kinematics(m, d)  # every joint's world axis and anchor at the reference pose
    qpos_i, qpos_s = list(range(m.nq)), [1.0] * m.nq
    qvel_i, qvel_s = list(range(m.nv)), [1.0] * m.nv
    joint_sign = [1.0] * m.njnt
    for j in range(m.njnt):
        kind, pa, va = m.jnt_type[j], m.jnt_qposadr[j], m.jnt_dofadr[j]
        name = _name(m, mujoco.mjtObj.mjOBJ_JOINT, j)
        if kind == mujoco.mjtJoint.mjJNT_FREE:
            if partner_name(name) != name:
                raise MirrorError(f"free joint {name!r} belongs to one side: only a central root is mirrored")
            qpos_s[pa : pa + 7] = [1.0, -1.0, 1.0, 1.0, -1.0, 1.0, -1.0]
            qvel_s[va : va + 6] = [1.0, -1.0, 1.0, -1.0, 1.0, -1.0]
            continue
        if kind == mujoco.mjtJoint.mjJNT_BALL:
            raise MirrorError(f"joint {name!r} is a ball joint: not mirrored")
        p = _id(m, mujoco.mjtObj.mjOBJ_JOINT, partner_name(name), f"joint {name!r}")
        axis, other = d.xaxis[j], d.xaxis[p]
        image = -_M * axis if kind == mujoco.mjtJoint.mjJNT_HINGE else _M * axis
        sign = float(np.dot(image, other))
        if abs(abs(sign) - 1.0) > _TOL:
            raise MirrorError(f"joint {name!r}: its reflected axis is not its partner's (±)")
        mb, pb = m.jnt_bodyid[j], m.jnt_bodyid[p]
        if abs(m.body_mass[mb] - m.body_mass[pb]) > _TOL * max(1.0, m.body_mass[mb]):
            raise MirrorError(f"joint {name!r}: its body and its partner's have different masses")
        if np.abs(_M * d.xanchor[j] - d.xanchor[p]).max() > _TOL:
            raise MirrorError(f"joint {name!r}: its anchor does not reflect onto its partner's")
        joint_sign[j] = float(np.sign(sign))
        qpos_i[m.jnt_qposadr[p]], qpos_s[m.jnt_qposadr[p]] = pa, joint_sign[j]
        qvel_i[m.jnt_dofadr[p]], qvel_s[m.jnt_dofadr[p]] = va, joint_sign[j]
    return qpos_i, qpos_s, qvel_i, qvel_s, joint_sign


def mirror_map(m: mujoco.MjModel, layout: StateLayout, forces: Sequence[ForceInput] = ()) -> Mirror:
    """The mirror of a model whose state ``layout`` reads its qpos and qvel, with these force inputs;
    raises ``MirrorError`` when the model is not left-right symmetric."""
    qpos_i, qpos_s, qvel_i, qvel_s, joint_sign = _joint_maps(m)
    s_index, s_sign = np.arange(layout.size), np.ones(layout.size)
    column = {}  # (source, address) -> state column
    for g, sl in layout.group_slices():
        for k in range(g.size):
            column[(g.source, g.address + k)] = sl.start + k
    for (source, address), col in column.items():
        index, sign = (qpos_i, qpos_s) if source == "qpos" else (qvel_i, qvel_s)
        src = (source, index[address])
        if src not in column:
            raise MirrorError(f"state column {col} mirrors {source}[{index[address]}], which the state lacks")
        s_index[col], s_sign[col] = column[src], sign[address]
    u_index, u_sign = np.arange(m.nu), np.ones(m.nu)
    for a in range(m.nu):
        if m.actuator_trntype[a] != mujoco.mjtTrn.mjTRN_JOINT:
            raise MirrorError(
                f"actuator {_name(m, mujoco.mjtObj.mjOBJ_ACTUATOR, a)!r} does not act on a joint"
            )
        name = _name(m, mujoco.mjtObj.mjOBJ_ACTUATOR, a)
        p = _id(m, mujoco.mjtObj.mjOBJ_ACTUATOR, partner_name(name), f"actuator {name!r}")
        joint, other = (_name(m, mujoco.mjtObj.mjOBJ_JOINT, m.actuator_trnid[k, 0]) for k in (a, p))
        if partner_name(joint) != other:
            raise MirrorError(f"actuator {name!r} drives {joint!r}, its partner {other!r}: not mirror images")
        u_index[p], u_sign[p] = a, joint_sign[m.actuator_trnid[a, 0]]
    f_index, f_sign = np.arange(len(forces)), np.ones(len(forces))
    where = {(f.body, f.component): i for i, f in enumerate(forces)}
    for i, f in enumerate(forces):
        image = where.get((partner_name(f.body), f.component))
        if image is None:
            raise MirrorError(f"force input {f.name!r} has no partner on body {partner_name(f.body)!r}")
        axis = f.component % 3
        f_index[image] = i
        f_sign[image] = _M[axis] if f.component < 3 else -_M[axis]
    return Mirror(s_index, s_sign, u_index, u_sign, f_index, f_sign)


def with_mirror_images(mirror: Mirror, data: Examples) -> Examples:
    """(2N) rows: each transition of ``data`` followed by its mirror image. Pairs stay adjacent, so a
    split into leading validation rows and training rows keeps a transition and its image together."""

    def interleave(a: FloatArray, image: FloatArray) -> FloatArray:
        return np.stack([a, image], axis=1).reshape(2 * a.shape[0], *a.shape[1:])

    return Examples(
        interleave(data.states, mirror.state(data.states)),
        interleave(data.controls, mirror.controls(data.controls)),
        interleave(data.forces, mirror.forces(data.forces)),
        interleave(data.next_states, mirror.state(data.next_states)),
    )


def check_mirror(mirror: Mirror, model: PhysicalModel, data: Examples, substeps: int, rows: int = 64) -> None:
    """Step the mirror images of the first ``rows`` transitions with MuJoCo and compare them with the
    mirrored next states: the names and masses ``mirror_map`` checks do not cover every asymmetry (a
    geom's shape, a joint's damping, a friction), and MuJoCo's step commutes with the mirror of a
    symmetric figure to rounding. Raises ``MirrorError`` naming the state column that differs most."""
    part = data.subset(slice(0, rows))
    stepped = model.step_held(
        mirror.state(part.states), mirror.controls(part.controls), mirror.forces(part.forces), substeps
    )
    err = np.abs(stepped - mirror.state(part.next_states)).max(axis=0)
    scale = np.abs(part.next_states - part.states).max()
    if err.max() > _COMMUTE_TOL * max(scale, 1e-9):
        col = int(err.argmax())
        raise MirrorError(
            f"the mirror image of a transition is not what MuJoCo does from the mirrored state: "
            f"{model.layout.labels()[col]} differs by {err[col]:.3g}"
        )
