"""``PhysicalModel``: one MuJoCo system behind the contract every other part reads.

It gives the MJCF, the physical timestep δt, the state layout, the control and external-force
inputs with their ranges, samplers of typical initial states and controls, and batched simulation
through ``mujoco.rollout`` (C threads, no Python in the inner step). Forces that depend on the state
(friction, drag) are expressed in the MJCF itself: joint damping, or affine-bias actuators placed in
the spec's *passive* actuator group, which are not controls.

Shapes: B = batch, T = time steps, S = state size, U = controls, F = external forces.
"""

from __future__ import annotations

import hashlib
import logging
import os
import re
import threading
import time
import xml.etree.ElementTree as ET
from collections.abc import Callable, Iterator, Mapping
from contextlib import contextmanager
from dataclasses import dataclass
from functools import cached_property

import mujoco
import numpy as np
from mujoco import rollout
from numpy.typing import NDArray

from neuroanimator.core import catmull_rom
from neuroanimator.core import quaternion as quat
from neuroanimator.core.model_spec import ControlInfo, ModelSpec
from neuroanimator.core.state import GroupKind, StateGroup, StateLayout, StateSource
from neuroanimator.sim import separation
from neuroanimator.sim.controls import control_info
from neuroanimator.sim.errors import ModelError
from neuroanimator.sim.waves import mix_waves

log = logging.getLogger(__name__)
FloatArray = NDArray[np.float64]
_BAD_QACC = int(mujoco.mjtWarning.mjWARN_BADQACC)
_PHYSICS = mujoco.mjtState.mjSTATE_FULLPHYSICS
_CONTROL_SPEC = mujoco.mjtState.mjSTATE_CTRL | mujoco.mjtState.mjSTATE_XFRC_APPLIED


class SimulationDiverged(ModelError):
    """MuJoCo found NaN, Inf or huge accelerations while simulating; the message says when and where."""


MAX_DIVERGED = 0.05
"""The largest share of sampled runs that may diverge: they are dropped and counted; beyond it, the
typical motion itself is what MuJoCo cannot simulate, and sampling stops (``SimulationDiverged``)."""


_quiet_warnings = 0  # > 0 inside ``mujoco_warnings_as_debug``


@contextmanager
def mujoco_warnings_as_debug() -> Iterator[None]:
    """MuJoCo's warnings are logged at DEBUG inside the block: for probes that expect instability and
    report what they found themselves (they may come from rollout's worker threads, hence a module
    counter rather than a thread-local flag)."""
    global _quiet_warnings
    _quiet_warnings += 1
    try:
        yield
    finally:
        _quiet_warnings -= 1


_BAD_DOF = re.compile(r"QACC at DOF (\d+)")
_last_bad_dof = -1  # the degree of freedom of MuJoCo's latest instability warning (-1: none yet)
_arena_full = 0  # MuJoCo's warnings that its arena could not hold a step's contacts or constraints


def _log_mujoco_warning(text: str) -> None:
    # MuJoCo's default prints to stderr and appends to MUJOCO_LOG.TXT in the working directory
    global _last_bad_dof, _arena_full
    log.log(logging.DEBUG if _quiet_warnings else logging.WARNING, "MuJoCo: %s", text.strip())
    if found := _BAD_DOF.search(text):
        _last_bad_dof = int(found.group(1))
    if "arena memory" in text:
        _arena_full += 1


mujoco.set_mju_user_warning(_log_mujoco_warning)


@dataclass(frozen=True)
class Frame:
    """Which symmetries the emulator may use: translation of the root position, rotation about z."""

    translate: tuple[bool, ...]  # one flag per dimension of the root position group
    rotate: bool
    # scalar groups of root slide joints the physics is translation-invariant along (a planar
    # body's ``rootx``: the emulator does not read how far it has gone, as for a free root's x and y)
    slides: tuple[str, ...] = ()


def _descends(m: mujoco.MjModel, body: int, ancestor: int) -> bool:
    """Whether ``body`` is ``ancestor`` or in its subtree."""
    while body != ancestor and body != 0:
        body = int(m.body_parentid[body])
    return body == ancestor


def _group(
    name: str,
    kind: GroupKind,
    size: int,
    source: StateSource,
    address: int,
    labels: tuple[str, ...] = (),
) -> StateGroup:
    return StateGroup(name=name, kind=kind, size=size, source=source, address=address, labels=labels)


def derive_layout(m: mujoco.MjModel) -> StateLayout:
    """State groups from the joints: free → position, quaternion, velocity, angular velocity;
    ball → local quaternion and angular velocity; hinge → angle and rate; slide → scalars; and one
    scalar per activation of an actuator with its own dynamics (a filter, a muscle: ``<name>.act``),
    without which the next state would not follow from the state and the controls.

    The first free joint is the root (its position and orientation define the local frame);
    further free joints are treated as plain numbers, without symmetry.
    """
    pos_groups: list[StateGroup] = []
    vel_groups: list[StateGroup] = []
    root_taken = False
    for j in range(m.njnt):
        name = mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_JOINT, j) or f"joint{j}"
        qa, va = int(m.jnt_qposadr[j]), int(m.jnt_dofadr[j])
        jt = m.jnt_type[j]
        if jt == mujoco.mjtJoint.mjJNT_FREE:
            root = not root_taken
            root_taken = True
            xyz = ("x", "y", "z")
            pos_groups.append(_group(f"{name}.pos", "position" if root else "scalar", 3, "qpos", qa, xyz))
            pos_groups.append(
                _group(
                    f"{name}.quat",
                    "quaternion" if root else "local_quaternion",
                    4,
                    "qpos",
                    qa + 3,
                    ("w", "x", "y", "z"),
                )
            )
            vel_groups.append(_group(f"{name}.vel", "world_vector" if root else "scalar", 3, "qvel", va, xyz))
            vel_groups.append(_group(f"{name}.angvel", "local_vector", 3, "qvel", va + 3, xyz))
        elif jt == mujoco.mjtJoint.mjJNT_BALL:
            pos_groups.append(_group(f"{name}.quat", "local_quaternion", 4, "qpos", qa, ("w", "x", "y", "z")))
            vel_groups.append(_group(f"{name}.angvel", "local_vector", 3, "qvel", va, ("x", "y", "z")))
        elif jt == mujoco.mjtJoint.mjJNT_HINGE:
            pos_groups.append(_group(f"{name}.angle", "angle", 1, "qpos", qa))
            vel_groups.append(_group(f"{name}.rate", "scalar", 1, "qvel", va))
        else:  # slide
            pos_groups.append(_group(f"{name}.pos", "scalar", 1, "qpos", qa))
            vel_groups.append(_group(f"{name}.vel", "scalar", 1, "qvel", va))
    if not pos_groups:
        raise ModelError("the MJCF has no joints: there is no state to emulate")
    act_groups = [
        _group(
            f"{mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_ACTUATOR, a) or f'actuator{a}'}.act",
            "scalar",
            1,
            "act",
            adr,
        )
        for a in range(m.nu)
        if (adr := int(m.actuator_actadr[a])) >= 0 and int(m.actuator_actnum[a]) == 1
    ]
    if len(act_groups) != m.na:
        raise ModelError(
            f"the MJCF's actuators hold {m.na} activations, of which {m.na - len(act_groups)} in actuators with "
            "more than one (a user-defined dynamics): such a state cannot be emulated yet"
        )
    return StateLayout(tuple(pos_groups + vel_groups + act_groups))


class PhysicalModel:
    """A MuJoCo model plus its ``ModelSpec``; see the module docstring for the contract."""

    def __init__(
        self,
        xml: str,
        spec: ModelSpec,
        assets: Mapping[str, bytes] | None = None,
        sources: Mapping[str, str] | None = None,
        compiled: mujoco.MjModel | None = None,
    ) -> None:
        """``assets``: the files the MJCF names (meshes, textures, ...), by the names it uses
        (MuJoCo's virtual file system); a model read from files has them by content (``bundle``), and
        ``sources`` says where each was found (for people). ``compiled``: the MJCF already compiled,
        in the sandbox (``sim.sandbox``), for a model that did not come with the code; without it the
        MJCF is compiled here, which only the catalog's own models may be."""
        self.xml = xml
        self.assets = dict(assets or {})
        self.asset_sources = dict(sources or {})
        self.spec = spec
        self.name = spec.name
        try:
            self.mj_model = compiled or mujoco.MjModel.from_xml_string(xml, self.assets or None)
        except Exception as exc:  # MuJoCo raises ValueError with the parser's message
            raise ModelError(f"malformed MJCF for model {spec.name!r}: {exc}") from exc
        m = self.mj_model
        try:
            self.layout = StateLayout.of(spec.layout) if spec.layout is not None else derive_layout(m)
        except (ValueError, KeyError) as exc:
            raise ModelError(f"model {spec.name}: bad state layout: {exc}") from exc
        self._check_layout()
        self.dt = float(m.opt.timestep)
        self._passive = np.array(
            [m.actuator_group[i] == spec.passive_actuator_group for i in range(m.nu)], bool
        )
        self._control_ids = np.flatnonzero(~self._passive)
        self.control_names = [
            mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_ACTUATOR, int(i)) or f"actuator{i}"
            for i in self._control_ids
        ]
        unknown = sorted(set(spec.control_info) - set(self.control_names))
        if unknown:
            raise ModelError(
                f"model {spec.name}: control_info names {unknown}, which are not controls ({self.control_names})"
            )
        self.force_names = [f.name for f in spec.forces]
        self._force_index = self._resolve_forces()
        self._threads = max(1, min(2, os.cpu_count() or 1))
        self._local = threading.local()
        self._separator_lock = threading.Lock()
        # physical steps simulated on all threads, and the seconds they took (``step_rate``)
        self._steps_simulated = 0
        self._seconds_simulating = 0.0
        self._probe_state_offsets()

    # ------------------------------------------------------------------ description
    @property
    def spec(self) -> ModelSpec:
        """What the MJCF does not say (``ModelSpec``); setting it (a super-step chosen, typical motion
        narrowed) drops what was derived from the previous one."""
        return self._spec

    @spec.setter
    def spec(self, spec: ModelSpec) -> None:
        self._spec = spec
        for derived in ("control_range", "control_info"):
            self.__dict__.pop(derived, None)

    @property
    def state_size(self) -> int:
        return self.layout.size

    @property
    def num_controls(self) -> int:
        return len(self.control_names)

    @property
    def num_forces(self) -> int:
        return len(self.spec.forces)

    @property
    def control_ids(self) -> NDArray[np.intp]:
        """(U,) the MuJoCo actuator index of each control."""
        return self._control_ids

    @cached_property
    def control_info(self) -> list[ControlInfo]:
        """(U,) what each control means: unit, gain, sign convention (``physics.controls``)."""
        controls = list(zip(self.control_names, self.control_ids.tolist(), strict=True))
        return control_info(self.mj_model, controls, self.spec.control_info)

    @cached_property
    def control_limits(self) -> FloatArray:
        """(U, 2) hard limits from the actuators' ctrlrange (±inf where unlimited)."""
        m = self.mj_model
        out = np.full((self.num_controls, 2), [-np.inf, np.inf])
        for k, i in enumerate(self._control_ids):
            if m.actuator_ctrllimited[i]:
                out[k] = m.actuator_ctrlrange[i]
        return out

    @cached_property
    def control_range(self) -> FloatArray:
        """(U, 2) useful range that typical controls are drawn from (spec, else ctrlrange, else ±1)."""
        if self.spec.control_low is not None and self.spec.control_high is not None:
            rng = np.stack([self.spec.control_low, self.spec.control_high], axis=1).astype(np.float64)
            if rng.shape != (self.num_controls, 2):
                raise ModelError(
                    f"model {self.name}: control_low/high must have {self.num_controls} values, got {rng.shape[0]}"
                )
            return rng
        lim = self.control_limits.copy()
        lim[~np.isfinite(lim[:, 0]), 0] = -1.0
        lim[~np.isfinite(lim[:, 1]), 1] = 1.0
        return lim

    @cached_property
    def force_range(self) -> FloatArray:
        return np.array([[f.low, f.high] for f in self.spec.forces], dtype=np.float64).reshape(-1, 2)

    @cached_property
    def frame(self) -> Frame:
        """The symmetries that are true for this model (thesis 4.3.3, corrected for gravity).

        Translation: every root-position axis, except the vertical one when the world has colliding
        geoms (a floor). Rotation: about z only, and only when gravity is along z (or zero).
        """
        m = self.mj_model
        root = self.layout.find("position")
        translate: tuple[bool, ...] = ()
        if root is not None and self.spec.translation_invariant:
            world_collides = any(
                m.geom_bodyid[g] == 0 and (m.geom_contype[g] or m.geom_conaffinity[g]) for g in range(m.ngeom)
            )
            translate = tuple(not (world_collides and axis == 2) for axis in range(root.size))
        g = np.asarray(m.opt.gravity)
        gravity_vertical = bool(np.allclose(g[:2], 0.0))
        has_orientation = self.layout.find("quaternion", "heading") is not None
        rotate = bool(
            self.spec.rotation_invariant
            and gravity_vertical
            and has_orientation
            and self.world_control_vectors is not None
        )
        slides = self.invariant_slides() if self.spec.translation_invariant else ()
        return Frame(translate=translate, rotate=rotate, slides=slides)

    def invariant_slides(self) -> tuple[str, ...]:
        """The position groups of the slide joints the physics does not depend on the position of:
        on a body whose parent is the world and that carries every body that moves (so that sliding
        it moves the whole model, its place among the others unchanged), after no hinge or ball of
        that body (so that it moves along a world axis), horizontal (vertical only in a world
        without colliding geoms: a floor), unlimited, without a spring, in no tendon and no equality
        constraint, no actuator pulling towards a position along it (the planar cheetah's, walker's
        and hopper's ``rootx``)."""
        m = self.mj_model
        names = {g.address: g.name for g in self.layout.groups if g.kind == "scalar" and g.source == "qpos"}
        world_collides = any(
            m.geom_bodyid[g] == 0 and (m.geom_contype[g] or m.geom_conaffinity[g]) for g in range(m.ngeom)
        )
        in_tendons = {
            int(m.wrap_objid[w]) for w in range(m.nwrap) if m.wrap_type[w] == mujoco.mjtWrap.mjWRAP_JOINT
        }
        in_equality = {
            int(m.eq_obj1id[e]) for e in range(m.neq) if m.eq_type[e] == mujoco.mjtEq.mjEQ_JOINT
        } | {int(m.eq_obj2id[e]) for e in range(m.neq) if m.eq_type[e] == mujoco.mjtEq.mjEQ_JOINT}
        held = {
            int(m.actuator_trnid[a, 0])
            for a in range(m.nu)
            if m.actuator_trntype[a] == mujoco.mjtTrn.mjTRN_JOINT and m.actuator_biasprm[a, 1] != 0
        }
        gravity = np.asarray(m.opt.gravity)
        strength = float(np.linalg.norm(gravity))
        down = gravity / strength if strength > 0 else np.array([0.0, 0.0, -1.0])
        moving = [b for b in range(1, m.nbody) if m.body_jntnum[b] > 0]
        out: list[str] = []
        for j in range(m.njnt):
            body = int(m.jnt_bodyid[j])
            if m.jnt_type[j] != mujoco.mjtJoint.mjJNT_SLIDE or m.body_parentid[body] != 0:
                continue
            if not all(_descends(m, b, body) for b in moving):
                continue  # it moves one body among others (a ball beside its cup): where matters
            if any(m.jnt_type[k] != mujoco.mjtJoint.mjJNT_SLIDE for k in range(m.body_jntadr[body], j)):
                continue
            # the axis in the world: the body's frame at rest turns it (slides move it, not turn it)
            axis = np.zeros(3)
            mujoco.mju_rotVecQuat(axis, m.jnt_axis[j], m.body_quat[body])
            along = abs(float(axis @ down))
            horizontal, vertical = along < 1e-9, abs(along - 1.0) < 1e-9
            if not (horizontal or (vertical and not world_collides)):
                continue
            if (
                m.jnt_limited[j]
                or m.jnt_stiffness[j] != 0
                or j in in_tendons
                or j in in_equality
                or j in held
            ):
                continue
            name = names.get(int(m.jnt_qposadr[j]))
            if name is not None:
                out.append(name)
        return tuple(out)

    @cached_property
    def world_control_vectors(self) -> tuple[tuple[int, ...], ...] | None:
        """Controls that push along axes fixed in the world (a site actuator whose ``refsite`` is on the
        world body), as vectors of control indices (x, y) or (x, y, z), one per site; the emulator turns
        them with the frame, so the rotation about gravity stays a symmetry. ``None`` when such a control
        is not a force along one world axis, or lacks its horizontal partner: then the rotation is no
        symmetry of the model under its controls."""
        m = self.mj_model
        by_site: dict[int, dict[int, int]] = {}
        for k, i in enumerate(self._control_ids):
            if m.actuator_trntype[i] != mujoco.mjtTrn.mjTRN_SITE:
                continue
            ref = int(m.actuator_trnid[i, 1])
            if ref < 0 or int(m.site_bodyid[ref]) != 0:
                continue
            gear = np.asarray(m.actuator_gear[i])
            axes = np.flatnonzero(gear[:3])
            if (
                gear[3:].any()
                or axes.size != 1
                or gear[axes[0]] != 1.0
                or axes[0] in by_site.get(int(m.actuator_trnid[i, 0]), {})
            ):
                return None
            by_site.setdefault(int(m.actuator_trnid[i, 0]), {})[int(axes[0])] = k
        vectors = []
        for axes_of in by_site.values():
            if 0 not in axes_of or 1 not in axes_of:
                return None
            vectors.append(tuple(axes_of[a] for a in (0, 1, 2) if a in axes_of))
        return tuple(vectors)

    def mjcf_sha256(self) -> str:
        return hashlib.sha256(self.xml.encode()).hexdigest()

    # ------------------------------------------------------------------ checks
    def _check_layout(self) -> None:
        m = self.mj_model
        for g in self.layout:
            limit = {"qpos": m.nq, "qvel": m.nv, "act": m.na}[g.source]
            if g.address + g.size > limit:
                raise ModelError(
                    f"model {self.name}: state group {g.name!r} reads {g.source}[{g.address}:{g.address + g.size}]"
                    f" but the model has {limit} {g.source} values"
                )

    def _resolve_forces(self) -> NDArray[np.int64]:
        m = self.mj_model
        idx = []
        for f in self.spec.forces:
            body = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, f.body)
            if body < 0:
                raise ModelError(
                    f"model {self.name}: force {f.name!r} names body {f.body!r}, which is not in the MJCF"
                )
            idx.append(body * 6 + f.component)
        return np.asarray(idx, dtype=np.int64)

    def check_batch(
        self, name: str, values: NDArray[np.floating], width: int, batch: int | None = None
    ) -> FloatArray:
        """Validate a (B, width) input: shape and finiteness; returns it as float64."""
        arr = np.asarray(values, dtype=np.float64)
        if arr.ndim == 1:
            arr = arr[None, :]
        if arr.ndim != 2 or arr.shape[1] != width:
            raise ModelError(
                f"{name} must have {width} values per row for model {self.name}, got shape {arr.shape}"
            )
        if batch is not None and arr.shape[0] not in (1, batch):
            raise ModelError(f"{name} must have {batch} rows (or 1) to match the states, got {arr.shape[0]}")
        if not np.all(np.isfinite(arr)):
            raise ModelError(f"{name} must be finite for model {self.name}; got NaN or Inf")
        return arr

    # ------------------------------------------------------------------ state <-> MuJoCo
    def _probe_state_offsets(self) -> None:
        """Find where qpos/qvel, ctrl and xfrc_applied sit in MuJoCo's state vectors (no guessing)."""
        m = self.mj_model
        d = mujoco.MjData(m)
        d.qpos[:] = np.arange(m.nq) + 1000.0
        d.qvel[:] = np.arange(m.nv) + 2000.0
        d.act[:] = np.arange(m.na) + 5000.0
        d.time = -1000.0
        full = np.empty(mujoco.mj_stateSize(m, _PHYSICS))
        mujoco.mj_getState(m, d, full, _PHYSICS)
        self._nfull = full.size
        self._time_at = int(np.flatnonzero(full == -1000.0)[0])
        self._qpos_at = int(np.flatnonzero(full == 1000.0)[0]) if m.nq else 0
        self._qvel_at = int(np.flatnonzero(full == 2000.0)[0]) if m.nv else 0
        self._act_at = int(np.flatnonzero(full == 5000.0)[0]) if m.na else 0
        self._template = np.zeros(self._nfull)
        mujoco.mj_resetData(m, d)
        mujoco.mj_getState(m, d, self._template, _PHYSICS)
        d.ctrl[:] = np.arange(m.nu) + 3000.0
        d.xfrc_applied[:] = (np.arange(m.nbody * 6) + 4000.0).reshape(m.nbody, 6)
        cvec = np.empty(mujoco.mj_stateSize(m, _CONTROL_SPEC))
        mujoco.mj_getState(m, d, cvec, _CONTROL_SPEC)
        self._ncontrol_vec = cvec.size
        self._ctrl_at = int(np.flatnonzero(cvec == 3000.0)[0]) if m.nu else 0
        self._xfrc_at = int(np.flatnonzero(cvec == 4000.0)[0])
        # state index -> index in the full-physics vector
        index: list[int] = []
        for g in self.layout:
            base = {"qpos": self._qpos_at, "qvel": self._qvel_at, "act": self._act_at}[g.source]
            index.extend(range(base + g.address, base + g.address + g.size))
        self._state_index = np.asarray(index, dtype=np.int64)
        self._rest = self._template[self._state_index].copy()

    def rest_state(self) -> FloatArray:
        """(S,) the state at MuJoCo's qpos0 with zero velocity."""
        return self._rest.copy()

    @property
    def qpos_slice(self) -> slice:
        """Where ``qpos`` lies in a full-physics state (``to_physics``)."""
        return slice(self._qpos_at, self._qpos_at + self.mj_model.nq)

    def to_physics(self, states: FloatArray) -> FloatArray:
        """(B, S) emulator states -> (B, nfull) MuJoCo full-physics states."""
        full = np.repeat(self._template[None, :], states.shape[0], axis=0)
        full[:, self._state_index] = states
        return full

    def from_physics(self, full: FloatArray) -> FloatArray:
        """(..., nfull) MuJoCo full-physics states -> (..., S) emulator states."""
        return full[..., self._state_index]

    def control_vector(self, controls: FloatArray, forces: FloatArray | None) -> FloatArray:
        """(B, T, U) controls and (B, T, F) forces -> (B, T, nctrl) MuJoCo control vectors.

        Passive actuators get 0; external forces go to their body's ``xfrc_applied`` component.
        Controls are clipped to the actuators' hard limits, as MuJoCo itself would.
        """
        b, t = controls.shape[:2]
        out = np.zeros((b, t, self._ncontrol_vec))
        if self.num_controls:
            out[..., self._ctrl_at + self._control_ids] = controls
        if self.num_forces and forces is not None:
            out[..., self._xfrc_at + self._force_index] = forces
        return out

    # ------------------------------------------------------------------ simulation
    def _datas(self) -> list[mujoco.MjData]:
        datas = getattr(self._local, "datas", None)
        if datas is None:
            datas = [mujoco.MjData(self.mj_model) for _ in range(self._threads)]
            self._local.datas = datas
        return datas

    # ------------------------------------------------------------------ cost
    # Below this many seconds of simulation a measured rate is mostly overhead, not physics
    RATE_MIN_SECONDS = 0.2

    @property
    def step_rate(self) -> float | None:
        """Physical steps per second that ``simulate`` has achieved on all its threads so far (over
        every call, so typical motion's contacts are in it), or None before ``RATE_MIN_SECONDS`` of it."""
        if self._seconds_simulating < self.RATE_MIN_SECONDS:
            return None
        return self._steps_simulated / self._seconds_simulating

    def measure_step_rate(self, seed: int = 0) -> float:
        """``step_rate``, simulating typical motion from typical states first where it is not known yet
        (a fresh model: batches of 16 runs of 100 steps until ``RATE_MIN_SECONDS`` have passed)."""
        rng = np.random.default_rng(seed)
        while (rate := self.step_rate) is None:
            self.simulate(*self.typical_runs(rng, 16, 100))
        return rate

    def simulate(
        self,
        states: FloatArray,
        controls: FloatArray | None = None,
        forces: FloatArray | None = None,
        *,
        nstep: int | None = None,
        threads: int | None = None,
        check: bool = False,
    ) -> FloatArray:
        """Roll the physics out from states (B, S) under controls (B|1, T|1, U) and forces (B|1, T|1, F).

        Returns the states after every physical step, (B, T, S). A control or force with T = 1 is
        held for all ``nstep`` steps (the emulator's super-step contract). With ``check``, a run that
        MuJoCo found unstable (it then resets the run to its initial pose) raises
        ``SimulationDiverged`` naming the time and the joint.
        """
        out, diverged, dof, first = self._simulate(states, controls, forces, nstep, threads, check)
        if check and diverged.any():
            raise self._diverged(np.asarray(states, dtype=np.float64), out, dof, first)
        return out

    def simulate_runs(
        self,
        states: FloatArray,
        controls: FloatArray | None = None,
        forces: FloatArray | None = None,
        *,
        nstep: int | None = None,
        threads: int | None = None,
    ) -> tuple[FloatArray, NDArray[np.bool_]]:
        """``simulate``, and which runs diverged (B,): MuJoCo found them unstable and reset them, or they
        hold a non-finite value or one a thousand times the start's. A sampler drops those and keeps the
        others; MuJoCo running out of arena memory still raises (``ModelError``)."""
        out, diverged, _, _ = self._simulate(states, controls, forces, nstep, threads, True, huge=True)
        return out, diverged

    def _simulate(
        self,
        states: FloatArray,
        controls: FloatArray | None,
        forces: FloatArray | None,
        nstep: int | None,
        threads: int | None,
        arena_check: bool,
        huge: bool = False,
    ) -> tuple[FloatArray, NDArray[np.bool_], int, int | None]:
        """The rollout (B, T, S), which runs diverged (B,), the degree of freedom MuJoCo warned of and
        the first step at which a run was seen reset (None: none was). With ``arena_check`` (a checked
        call), raise when MuJoCo dropped contacts for want of arena memory, and mark the runs MuJoCo
        found unstable (with ``huge``, also those a thousand times their start); without, mark none."""
        states = np.asarray(states, dtype=np.float64)
        if states.ndim != 2 or states.shape[1] != self.state_size:
            raise ModelError(
                f"states must have shape (batch, {self.state_size}) for model {self.name}, got {states.shape}"
            )
        b = states.shape[0]
        u = (
            np.zeros((1, 1, self.num_controls))
            if controls is None
            else np.asarray(controls, dtype=np.float64)
        )
        f = None if forces is None else np.asarray(forces, dtype=np.float64)
        self._check_inputs("controls", u, self.num_controls, b)
        if f is not None:
            self._check_inputs("forces", f, self.num_forces, b)
        elif self.num_forces:
            f = np.zeros((1, 1, self.num_forces))
        steps = nstep if nstep is not None else max(u.shape[1], 1 if f is None else f.shape[1])
        t = max(u.shape[1], 1 if f is None else f.shape[1])
        if u.shape[1] != t:
            u = np.broadcast_to(u, (u.shape[0], t, u.shape[2]))
        if f is not None and f.shape[1] != t:
            f = np.broadcast_to(f, (f.shape[0], t, f.shape[2]))
        if f is not None and f.shape[0] != u.shape[0]:
            bb = max(f.shape[0], u.shape[0])
            u = np.broadcast_to(u, (bb, *u.shape[1:]))
            f = np.broadcast_to(f, (bb, *f.shape[1:]))
        cvec = self.control_vector(u, f)
        datas = self._datas()
        if threads is not None:
            datas = datas[: max(1, threads)]
        for d in datas:
            d.warning[_BAD_QACC].number = 0
        started, arena_warnings = time.perf_counter(), _arena_full
        try:
            out, _ = rollout.rollout(
                self.mj_model,
                datas,
                self.to_physics(states),
                cvec,
                control_spec=int(_CONTROL_SPEC),
                nstep=steps,
            )
        except mujoco.FatalError as exc:  # MuJoCo's stack ran out: too many contacts for the arena
            raise self._arena_too_small(str(exc).strip().replace("\n", "; ")) from exc
        if arena_check and _arena_full > arena_warnings:  # concurrent checked calls may share this count
            raise self._arena_too_small("it dropped contacts or constraints that did not fit")
        if len(datas) == self._threads and b >= len(datas):  # a rate on every thread
            self._steps_simulated += b * steps
            self._seconds_simulating += time.perf_counter() - started
        result = self.from_physics(out).reshape(b, steps, self.state_size)
        if not arena_check:  # unchecked: as MuJoCo gives it, nothing more computed (a speed baseline)
            return result, np.zeros(b, dtype=bool), -1, None
        bad = [d for d in datas if d.warning[_BAD_QACC].number]
        # rollout clears a thread's warnings before each of its runs, so only the last run of a
        # thread would show in ``bad``; but an unstable run's clock stops rising (rollout stops
        # stepping it after MuJoCo's reset), the step after the one that diverged
        clock = np.concatenate([np.zeros((b, 1)), out[..., self._time_at]], axis=1)
        stalled = np.diff(clock, axis=1) <= 0  # (B, T)
        diverged: NDArray[np.bool_] = np.asarray(stalled.any(axis=1))
        if huge:  # values a thousand times the start's: a run on its way to MuJoCo's reset
            diverged |= (
                ~np.isfinite(result) | (np.abs(result) > 1e3 * (1.0 + np.abs(states[:, None, :])))
            ).any(axis=(1, 2))
        dof = int(bad[0].warning[_BAD_QACC].lastinfo) if bad else _last_bad_dof
        first = max(0, int(np.flatnonzero(stalled.any(axis=0))[0]) - 1) if stalled.any() else None
        if bad and not diverged.any():  # a thread warned and its runs did not show it: count them all
            diverged[:] = True
        return result, diverged, dof, first

    def _arena_too_small(self, what: str) -> ModelError:
        """The error for a simulation whose contacts and constraints MuJoCo's arena cannot hold."""
        return ModelError(
            f"model {self.name}: MuJoCo ran out of arena memory ({self.mj_model.narena:,} bytes) in a "
            f'simulation: {what}. Give the MJCF more (<size memory="..."/>, or larger njmax / nconmax), or '
            "start from states with fewer contacts (limbs that start interpenetrating make many)"
        )

    def _diverged(
        self, start: FloatArray, traj: FloatArray, dof: int, step: int | None = None
    ) -> SimulationDiverged:
        """The error for an unstable rollout from (B, S) to (B, T, S): it names the first step with a
        non-finite value or one a thousand times the start's (MuJoCo resets the run right after), or
        ``step``, where a run was seen to be reset."""
        m = self.mj_model
        huge = ~np.isfinite(traj) | (np.abs(traj) > 1e3 * (1.0 + np.abs(start[:, None, :])))
        steps = np.flatnonzero(huge.any(axis=(0, 2)))
        if step is not None and (not steps.size or step < steps[0]):
            steps = np.array([step])
        when = f"{(int(steps[0]) + 1) * self.dt:.4g} s into" if steps.size else "during"
        if 0 <= dof < m.nv:
            joint = mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_JOINT, int(m.dof_jntid[dof]))
            where = f"degree of freedom {dof} (joint {joint!r})"
        else:  # MuJoCo named no degree of freedom (a run caught by its values): the first that blew up
            where = f"joint {self._blown_joint(huge, steps)!r}, the first whose state blew up"
        return SimulationDiverged(
            f"the simulation of model {self.name} diverged {when} a run from a typical state: MuJoCo found "
            f"NaN, Inf or huge accelerations at {where}. Try a smaller "
            f"timestep (now {self.dt:g} s), more damping or less stiffness at that joint, or narrower "
            "typical controls and initial states"
        )

    def _blown_joint(self, huge: NDArray[np.bool_], steps: NDArray[np.intp]) -> str | None:
        """The joint of the first state variable that is not finite or huge (B, T, S) at the first such
        step, from its layout group's name (``stiff.angle`` → ``stiff``), or None."""
        cols = np.flatnonzero(huge[:, int(steps[0])].any(axis=0)) if steps.size else np.zeros(0, np.intp)
        if not cols.size:  # reset by MuJoCo before its values grew: any that ever did
            cols = np.flatnonzero(huge.any(axis=(0, 1)))
        for g, at in zip(self.layout.groups, self.layout.offsets, strict=True):
            if cols.size and at <= cols[0] < at + g.size and g.source in ("qpos", "qvel"):
                return g.name.rsplit(".", 1)[0]
        if self.mj_model.njnt == 1:  # the only joint there is
            return mujoco.mj_id2name(self.mj_model, mujoco.mjtObj.mjOBJ_JOINT, 0)
        return None

    def _check_inputs(self, name: str, values: FloatArray, width: int, batch: int) -> None:
        if values.ndim != 3 or values.shape[2] != width:
            if width == 0 and values.size:
                raise ModelError(
                    f"model {self.name} takes no {name} (it has none besides passive ones), "
                    f"got {name} of shape {values.shape}"
                )
            raise ModelError(
                f"{name} must have shape (batch, steps, {width}) for model {self.name}, got {values.shape}"
            )
        if values.shape[0] not in (1, batch):
            raise ModelError(
                f"{name} must have {batch} rows (or 1) to match the states, got {values.shape[0]}"
            )
        if not np.all(np.isfinite(values)):
            raise ModelError(f"{name} must be finite for model {self.name}; got NaN or Inf")

    def step_held(
        self,
        states: FloatArray,
        controls: FloatArray | None,
        forces: FloatArray | None,
        substeps: int,
        *,
        check: bool = False,
        threads: int | None = None,
    ) -> FloatArray:
        """One super-step of the physics: hold controls (B, U) and forces (B, F) for ``substeps`` steps
        (on at most ``threads`` of MuJoCo's threads; None: all of them)."""
        u = None if controls is None else np.asarray(controls, dtype=np.float64)[:, None, :]
        f = None if forces is None else np.asarray(forces, dtype=np.float64)[:, None, :]
        return self.simulate(states, u, f, nstep=substeps, threads=threads, check=check)[:, -1]

    # ------------------------------------------------------------------ typical inputs
    def initial_states(self, rng: np.random.Generator, batch: int) -> FloatArray:
        """(batch, S) typical initial states (spec.initial), deterministic for the generator; a start that
        would begin inside the floor or inside another body is lifted or drawn nearer the rest pose
        (``separation``)."""
        init = self.spec.initial
        if init.centres:  # operating states (keyframes): one per start, at random
            centres = np.asarray(init.centres, dtype=np.float64)
            if centres.shape[1:] != (self.state_size,):
                raise ModelError(
                    f"model {self.name}: initial centres must have {self.state_size} values each"
                )
            rest = centres[rng.integers(0, len(centres), size=batch)]  # (batch, S)
        else:
            rest = np.repeat(self.rest_state()[None, :], batch, axis=0)
        delta = np.zeros((batch, self.state_size))
        if init.low:
            lo, hi = np.asarray(init.low), np.asarray(init.high)
            if lo.size != self.state_size or hi.size != self.state_size:
                raise ModelError(f"model {self.name}: initial low/high must have {self.state_size} values")
            delta = lo + (hi - lo) * rng.random((batch, self.state_size))
        qg = self.layout.find("quaternion")
        turn: tuple[slice, FloatArray, FloatArray, FloatArray] | None = None
        if qg is not None and (init.random_yaw or init.max_tilt > 0):
            yaw = rng.uniform(-np.pi, np.pi, batch) if init.random_yaw else np.zeros(batch)
            # uniform over the spherical cap of half-angle max_tilt (the whole sphere for π)
            tilt = np.arccos(1.0 - rng.random(batch) * (1.0 - np.cos(min(init.max_tilt, np.pi))))
            axis_angle = rng.uniform(-np.pi, np.pi, batch)
            axis = np.stack([np.cos(axis_angle), np.sin(axis_angle), np.zeros(batch)], axis=1)
            turn = (self.layout.slice_of(qg.name), yaw, tilt, axis)
        op = self.spec.operating
        if init.centres and op is not None and op.held_share > 0:  # these start at an operating state
            still = rng.random(batch) < op.held_share
            delta[still] = 0.0
            if turn is not None:
                turn[2][still] = 0.0

        def build(rows: NDArray[np.int64], scale: float) -> FloatArray:
            """The starts of ``rows`` with their perturbation (tilt included) scaled by ``scale``."""
            states = rest[rows] + scale * delta[rows]
            if turn is not None:
                sl, yaw, tilt, axis = turn
                q_yaw = quat.from_axis_angle(np.array([0.0, 0.0, 1.0]), yaw[rows])
                q_tilt = quat.from_axis_angle(axis[rows], scale * tilt[rows])
                q = quat.multiply(q_yaw, quat.multiply(q_tilt, states[:, sl]))
                states[:, sl] = q / np.linalg.norm(q, axis=1, keepdims=True)
            return states

        states = build(np.arange(batch), 1.0)
        if self._separator is None:
            return states
        return self._separated(states, lambda i, scale: build(np.array([i]), scale)[0])

    @cached_property
    def _separator(self) -> separation.Separator | None:
        """The penetration check of the starts; None for a model whose geoms never collide."""
        m = self.mj_model
        if m.npair == 0 and not (np.any(m.geom_contype) and np.any(m.geom_conaffinity)):
            return None
        return separation.Separator(m)

    def _separated(self, states: FloatArray, rebuild: Callable[[int, float], FloatArray]) -> FloatArray:
        sep = self._separator
        assert sep is not None
        m = self.mj_model
        at = slice(self._qpos_at, self._qpos_at + m.nq)
        full = self.to_physics(states)
        with self._separator_lock:  # one MjData for the check
            qpos, lifted, shrunk = separation.separate(
                sep, full[:, at], lambda i, scale: self.to_physics(rebuild(i, scale)[None])[0, at]
            )
        if lifted or shrunk:
            log.debug(
                "%s: of %d starts, %d lifted off the floor, %d drawn nearer rest",
                self.name,
                len(states),
                lifted,
                shrunk,
            )
        full[:, at] = qpos
        return self.from_physics(full)

    def typical_runs(
        self, rng: np.random.Generator, batch: int, steps: int
    ) -> tuple[FloatArray, FloatArray, FloatArray | None]:
        """``batch`` typical starts (B, S) and their controls (B, T, U) and forces (B, T, F; None for a
        model without force inputs) over ``steps`` physical steps: what ``simulate`` takes for typical
        motion."""
        times = np.arange(steps, dtype=np.float64) * self.dt
        s0 = self.initial_states(rng, batch)
        u = self.typical_controls(rng, batch, times)
        f = self.typical_forces(rng, batch, times) if self.num_forces else None
        return s0, u, f

    def typical_controls(self, rng: np.random.Generator, batch: int, times: FloatArray) -> FloatArray:
        """(batch, T, U) smooth Catmull-Rom controls over the useful range, at the given times; where the
        spec has ``travelling_waves``, that share of the runs under a rhythmic gait's waves."""
        bands = self._operating_bands(rng, batch)
        random = self._smooth(
            rng, batch, times, self.control_range if bands is None else bands, self.spec.control_spacing_s
        )
        if self.spec.travelling_waves is None:
            return random
        return mix_waves(self.spec.travelling_waves, rng, random, times, self.control_range)

    def _operating_bands(self, rng: np.random.Generator, batch: int) -> FloatArray | None:
        """(batch, U, 2) each run's control band around one of the operating point's centres (drawn at
        random per run; ``held_share`` of the runs with no spread), within the control range; None
        without an operating point."""
        op = self.spec.operating
        if op is None or not op.control_centres or not self.num_controls:
            return None
        centres = np.asarray(op.control_centres, dtype=np.float64)  # (K, U)
        spread = np.asarray(op.control_spread, dtype=np.float64)  # (U,)
        if centres.shape[1:] != (self.num_controls,) or spread.shape != (self.num_controls,):
            raise ModelError(
                f"model {self.name}: operating centres and spread need {self.num_controls} values"
            )
        c = centres[rng.integers(0, len(centres), size=batch)]  # (batch, U)
        half = np.repeat(spread[None, :], batch, axis=0)
        if op.held_share > 0:  # these runs hold the operating point's own controls
            half[rng.random(batch) < op.held_share] = 0.0
        lo, hi = self.control_range[:, 0], self.control_range[:, 1]
        return np.stack([np.clip(c - half, lo, hi), np.clip(c + half, lo, hi)], axis=-1)

    def typical_forces(self, rng: np.random.Generator, batch: int, times: FloatArray) -> FloatArray:
        """(batch, T, F) smooth external forces over their ranges."""
        return self._smooth(rng, batch, times, self.force_range, self.spec.force_spacing_s)

    @staticmethod
    def _smooth(
        rng: np.random.Generator, batch: int, times: FloatArray, rng_lohi: FloatArray, spacing: float
    ) -> FloatArray:
        """(batch, T, W) smooth random values within ``rng_lohi``: (W, 2) for every run, or (batch, W, 2)
        one band per run."""
        width = rng_lohi.shape[-2]
        times = np.asarray(times, dtype=np.float64)
        if width == 0:
            return np.zeros((batch, times.size, 0))
        t0 = float(times.min())
        npts = int(np.ceil((float(times.max()) - t0) / spacing)) + 2
        lo, hi = rng_lohi[..., 0], rng_lohi[..., 1]
        if rng_lohi.ndim == 3:  # per run: (batch, 1, W) against the points' (batch, npts, W)
            lo, hi = lo[:, None, :], hi[:, None, :]
        points = catmull_rom.random_points(rng, (batch, npts), lo, hi)
        # Catmull-Rom overshoots a little between points: keep it inside the range
        values = catmull_rom.evaluate(points, times - t0, spacing)
        return np.clip(values, lo, hi)


def read_model_name(xml: str, fallback: str) -> str:
    """The MJCF's ``model`` attribute, else the fallback (the file name)."""
    try:
        root = ET.fromstring(xml)
    except ET.ParseError as exc:
        raise ModelError(f"malformed MJCF ({fallback}): {exc}") from exc
    if root.tag != "mujoco":
        raise ModelError(f"malformed MJCF ({fallback}): the root element must be <mujoco>, got <{root.tag}>")
    name = root.get("model")
    return name.strip() if name and name.strip() else fallback
