"""What a client needs to draw a model without kinematics of its own, from the artifact's MJCF.

``geometry(emu)``: the bodies (with parents), their geoms and the model's skins, as ``GET /models/{model}/geometry``
answers. ``Kinematics.poses(states)``: every body's world pose for states (K, S), by MuJoCo's forward
kinematics (``mj_kinematics``). ``MujocoShadow``: a MuJoCo copy of one session stepped with the same
held inputs (a driven session's copy: with its own instance of the driver; a policy-driven one's: with
the policy evaluated on the copy's own state, towards the session's goal), for the websocket's
``shadow`` option. Torch-free, like the rest of the service.

A pose is ``[x, y, z, qw, qx, qy, qz]`` in the world frame; bodies are MuJoCo's bodies 1..nbody-1
(the world body 0 is left out: its geoms are ``ModelGeometry.world``).
"""

from __future__ import annotations

import threading
from collections.abc import Collection, Sequence
from functools import cached_property

import mujoco
import numpy as np
from numpy.typing import NDArray

from neuroanimator.contracts.emulator import (
    BodyInfo,
    GeomInfo,
    MaterialInfo,
    MeshInfo,
    ModelGeometry,
    SkinBone,
    SkinInfo,
)
from neuroanimator.core.quaternion import wrap_angle
from neuroanimator.sim.driver import Driver
from neuroanimator.sim.model import PhysicalModel
from services.emulator.errors import BadInput
from services.emulator.policies import LoadedPolicy

_PHYSICS = mujoco.mjtState.mjSTATE_FULLPHYSICS


def _geom_type(m: mujoco.MjModel, g: int) -> str:
    return mujoco.mjtGeom(int(m.geom_type[g])).name.removeprefix("mjGEOM_").lower()


def _floats(values: NDArray[np.float64]) -> list[float]:
    return [round(float(v), 6) for v in values]


def _path(m: mujoco.MjModel, adr: int) -> str | None:
    """A file name from the model's ``paths`` (``*_pathadr``; -1: none)."""
    if adr < 0:
        return None
    raw: bytes = m.paths[adr:].split(b"\0", 1)[0]
    return raw.decode() or None


def _material(m: mujoco.MjModel, g: int) -> MaterialInfo | None:
    mat = int(m.geom_matid[g])
    if mat < 0:
        return None
    return MaterialInfo(
        name=mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_MATERIAL, mat) or f"material{mat}",
        rgba=_floats(m.mat_rgba[mat]),
        emission=round(float(m.mat_emission[mat]), 6),
        specular=round(float(m.mat_specular[mat]), 6),
        shininess=round(float(m.mat_shininess[mat]), 6),
        reflectance=round(float(m.mat_reflectance[mat]), 6),
    )


def _mesh(m: mujoco.MjModel, g: int, assets: Collection[str]) -> MeshInfo | None:
    """A mesh geom's file (when the artifact has it) and MuJoCo's placement of its vertices."""
    mesh = int(m.geom_dataid[g])
    if m.geom_type[g] != mujoco.mjtGeom.mjGEOM_MESH or mesh < 0:
        return None
    file = _path(m, int(m.mesh_pathadr[mesh]))
    return MeshInfo(
        name=mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_MESH, mesh) or f"mesh{mesh}",
        asset=file if file in assets else None,
        scale=_floats(m.mesh_scale[mesh]),
        pos=_floats(m.mesh_pos[mesh]),
        quat=_floats(m.mesh_quat[mesh]),
    )


def _geom(m: mujoco.MjModel, g: int, assets: Collection[str] = ()) -> GeomInfo:
    size = m.geom_size[g]
    if m.geom_type[g] == mujoco.mjtGeom.mjGEOM_MESH:
        size = m.geom_aabb[g][3:]  # half-extents of the mesh's box; centred at the geom's frame
    return GeomInfo(
        name=mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_GEOM, g) or f"geom{g}",
        type=_geom_type(m, g),
        size=_floats(size),
        pos=_floats(m.geom_pos[g]),
        quat=_floats(m.geom_quat[g]),
        rgba=_floats(m.geom_rgba[g]),
        group=int(m.geom_group[g]),
        material=_material(m, g),
        mesh=_mesh(m, g, assets),
    )


def _skins(m: mujoco.MjModel) -> list[SkinInfo]:
    """The model's skins with their bones (bodies as indices of ``ModelGeometry.bodies``)."""
    out = []
    for k in range(m.nskin):
        v0, nv = int(m.skin_vertadr[k]), int(m.skin_vertnum[k])
        f0, nf = int(m.skin_faceadr[k]), int(m.skin_facenum[k])
        bones = []
        for b in range(int(m.skin_boneadr[k]), int(m.skin_boneadr[k]) + int(m.skin_bonenum[k])):
            a, n = int(m.skin_bonevertadr[b]), int(m.skin_bonevertnum[b])
            bones.append(
                SkinBone(
                    body=int(m.skin_bonebodyid[b]) - 1,
                    bindpos=_floats(m.skin_bonebindpos[b]),
                    bindquat=_floats(m.skin_bonebindquat[b]),
                    vertices=[int(v) for v in m.skin_bonevertid[a : a + n]],
                    weights=_floats(m.skin_bonevertweight[a : a + n]),
                )
            )
        out.append(
            SkinInfo(
                name=mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_SKIN, k) or f"skin{k}",
                rgba=_floats(m.skin_rgba[k]),
                inflate=round(float(m.skin_inflate[k]), 6),
                vertices=_floats(m.skin_vert[v0 : v0 + nv].ravel()),
                faces=[int(i) for i in m.skin_face[f0 : f0 + nf].ravel()],
                bones=bones,
            )
        )
    return out


class Kinematics:
    """World poses of a model's bodies for emulator states, through one reusable ``MjData`` (guarded
    by a lock: ``POST /models/{m}/poses`` runs in worker threads, websocket poses on the event loop)."""

    def __init__(self, physical: PhysicalModel) -> None:
        self.physical = physical
        self.m = physical.mj_model
        self.d = mujoco.MjData(self.m)
        self._lock = threading.Lock()
        self.quaternion_slices = [
            physical.layout.slice_of(g.name)
            for g in physical.layout
            if g.kind in ("quaternion", "local_quaternion")
        ]

    @cached_property
    def body_names(self) -> list[str]:
        m = self.m
        return [mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_BODY, b) or f"body{b}" for b in range(1, m.nbody)]

    def poses(self, states: NDArray[np.floating]) -> NDArray[np.float64]:
        """(K, S) states -> (K, nbody-1, 7) world poses. Quaternion groups are normalised first (a
        zero one is taken as the identity); the states must be finite (the caller checks)."""
        states64: NDArray[np.float64] = np.array(states, dtype=np.float64, ndmin=2)
        states = states64
        for sl in self.quaternion_slices:
            q = states[:, sl]
            norm = np.linalg.norm(q, axis=1, keepdims=True)
            ident = np.zeros_like(q)
            ident[:, 0] = 1.0
            states[:, sl] = np.where(norm > 1e-9, q / np.maximum(norm, 1e-12), ident)
        full = self.physical.to_physics(states64)
        m, d = self.m, self.d
        out = np.empty((states.shape[0], m.nbody - 1, 7))
        with self._lock:
            for k in range(states.shape[0]):
                mujoco.mj_setState(m, d, full[k], _PHYSICS)
                mujoco.mj_kinematics(m, d)
                out[k, :, :3] = d.xpos[1:]
                out[k, :, 3:] = d.xquat[1:]
        return out

    def rest_poses(self) -> NDArray[np.float64]:
        return self.poses(self.physical.rest_state()[None])[0]


def geometry(model: str, version: str, kin: Kinematics) -> ModelGeometry:
    """The model's bodies, their geoms (a mesh names its file among the artifact's assets), the world's
    geoms and the rest poses."""
    m = kin.m
    assets = kin.physical.assets.keys()
    by_body: dict[int, list[GeomInfo]] = {b: [] for b in range(m.nbody)}
    for g in range(m.ngeom):
        by_body[int(m.geom_bodyid[g])].append(_geom(m, g, assets))
    bodies = [
        BodyInfo(name=name, parent=int(m.body_parentid[b]) - 1, geoms=by_body[b])
        for b, name in zip(range(1, m.nbody), kin.body_names, strict=True)
    ]
    return ModelGeometry(
        model=model,
        version=version,
        bodies=bodies,
        world=by_body[0],
        skins=_skins(m),
        rest_state=_floats(kin.physical.rest_state()),
        rest_poses=[_floats(p) for p in kin.rest_poses()],
        center=_floats(m.stat.center),
        extent=float(m.stat.extent),
    )


def check_states(states: Sequence[Sequence[float]], width: int, what: str, limit: int) -> NDArray[np.float64]:
    """(K, S) finite float64 states from JSON lists; ``BadInput`` naming the first bad row or value."""
    if len(states) > limit:
        raise BadInput(
            f"states may hold at most {limit} states (MAX_FRAMES_PER_REQUEST), got {len(states)}",
            code="too_many_states",
            field="states",
            expected=f"<= {limit}",
            got=len(states),
        )
    for i, row in enumerate(states):
        if len(row) != width:
            raise BadInput(
                f"states[{i}] must have {width} values for {what}, got {len(row)}",
                code="wrong_length",
                field=f"states[{i}]",
                expected=width,
                got=len(row),
            )
    arr = np.asarray(states, dtype=np.float64).reshape(len(states), width)
    bad = np.argwhere(~np.isfinite(arr))
    if bad.size:
        i, j = (int(v) for v in bad[0])
        raise BadInput(
            f"states[{i}][{j}] is not a finite number",
            code="not_finite",
            field=f"states[{i}][{j}]",
            expected="a finite number",
            got=str(arr[i, j]),
        )
    return arr


class MujocoShadow:
    """A MuJoCo copy of a session: started from a state, stepped one super-step (``substeps`` physical
    steps under held inputs, the emulator's contract) at a time. Stops when its state stops being
    finite. ``controls`` (U,): what its driver or policy chose for its last step (None: the client's)."""

    def __init__(
        self,
        physical: PhysicalModel,
        substeps: int,
        state: NDArray[np.floating],
        driver: Driver | None = None,
        policy: LoadedPolicy | None = None,
    ) -> None:
        self.physical = physical
        self.driver = driver  # a driven session's twin runs its own instance of the controller
        self.policy = policy  # a policy-driven session's twin: the policy on the twin's own state
        self.controls: NDArray[np.float32] | None = None
        self.substeps = substeps
        self.state = np.asarray(state, dtype=np.float64).copy()
        self.diverged = False
        # a heading is reported wrapped to [-π, π), as the emulator's (state.heading_columns)
        self.wrap = [sl.start for g, sl in physical.layout.group_slices() if g.kind == "heading"]

    def step(
        self,
        controls: NDArray[np.float32],
        forces: NDArray[np.float32],
        goal: NDArray[np.float32] | None = None,
        since_goal: int = 0,
    ) -> NDArray[np.float64]:
        """One super-step under held ``controls`` (U,) and ``forces`` (F,); a policy-driven twin's
        controls are its policy's for its own state, ``goal`` (G,) and the super-steps ``since_goal``
        was set (the session's)."""
        if self.diverged:
            return self.state
        p = self.physical
        if self.driver is not None:
            controls = self.driver.act(self.state).astype(np.float32)
            self.controls = controls
        elif self.policy is not None and goal is not None:
            state = self.state[None].astype(np.float32)
            # (already within the controls' limits: the policy's graph ends by clipping to them)
            controls = self.policy.controls(state, goal[None], np.asarray([since_goal], np.int64))[0]
            self.controls = controls
        u = controls[None].astype(np.float64) if p.num_controls else None
        f = forces[None].astype(np.float64) if p.num_forces else None
        new = p.step_held(self.state[None], u, f, self.substeps)[0]
        if np.all(np.isfinite(new)):
            new[self.wrap] = wrap_angle(new[self.wrap])
            self.state = new
        else:
            self.diverged = True
        return self.state
