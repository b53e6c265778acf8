"""The dolphin (thesis E.4): springs, muscles, water plates, deformation energy and swimming."""

from __future__ import annotations

import mujoco
import numpy as np
import pytest

from neuroanimator import catalog
from neuroanimator.catalog import dolphin
from neuroanimator.sim.model import PhysicalModel


@pytest.fixture(scope="module")
def model() -> PhysicalModel:
    return catalog.get("dolphin")


def _deformed(model: PhysicalModel, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """A randomly deformed, moving dolphin: its state and MjData after mj_forward with activations."""
    rng = np.random.default_rng(seed)
    s = model.rest_state()
    s[dolphin.NODE_POS] += rng.uniform(-0.03, 0.03, 3 * dolphin.NUM_NODES)
    s[dolphin.NODE_VEL] += rng.uniform(-0.5, 0.5, 3 * dolphin.NUM_NODES)
    return s, rng.uniform(0.0, 1.0, 6)


def _forward(model: PhysicalModel, s: np.ndarray, a: np.ndarray) -> mujoco.MjData:
    m = model.mj_model
    d = mujoco.MjData(m)
    for g, sl in model.layout.group_slices():
        getattr(d, g.source)[g.address : g.address + g.size] = s[sl]
    d.ctrl[:] = a
    mujoco.mj_forward(m, d)
    return d


def test_state_is_node_positions_velocities_and_plate_orientations(model: PhysicalModel) -> None:
    assert dolphin.NUM_NODES == 23
    assert model.state_size == 6 * 23 + 2 * len(dolphin.PLATES)
    assert model.num_controls == 6 and model.control_names == dolphin.CONTROL_NAMES
    assert model.dt == pytest.approx(0.01)
    np.testing.assert_allclose(model.mj_model.opt.gravity, 0.0)  # neutrally buoyant: no gravity
    assert model.mj_model.opt.disableflags & mujoco.mjtDisableBit.mjDSBL_CONTACT
    rest = model.rest_state()
    np.testing.assert_allclose(
        dolphin.node_positions(rest), dolphin.rest_positions()
    )  # qpos is world position
    np.testing.assert_array_equal(rest[dolphin.NODE_VEL], 0.0)
    d = _forward(model, rest, np.zeros(6))
    node_bodies = [mujoco.mj_name2id(model.mj_model, mujoco.mjtObj.mjOBJ_BODY, n) for n in dolphin.NODES]
    np.testing.assert_allclose(d.xpos[node_bodies], dolphin.rest_positions(), atol=1e-12)


def _node_forces_by_hand(model: PhysicalModel, d: mujoco.MjData, a: np.ndarray) -> np.ndarray:
    """(23, 3) every spring, muscle, alignment tendon and node damping force on each node, from E.1:
    f = −(c·e + γ·ė)·r/‖r‖, and for a muscle spring −c(l − l(a)) − γ·l̇, l(a) = a·l_c + (1 − a)·l_r."""
    x, v = dolphin.node_positions(_state(model, d)), _node_velocities(model, d)
    out = -dolphin.NODE_DAMPING * v
    muscle_of = {spring: k for k, pair in enumerate(dolphin.MUSCLES) for spring in pair}
    for (i, j), rest in zip(dolphin.SPRINGS, dolphin.rest_lengths(), strict=True):
        r = x[j] - x[i]
        length = np.linalg.norm(r)
        unit = r / length
        rate = (v[j] - v[i]) @ unit
        natural = rest
        if (i, j) in muscle_of:
            act = a[muscle_of[(i, j)]]
            natural = act * dolphin.MUSCLE_CONTRACTION * rest + (1 - act) * rest
        tension = -(dolphin.STIFFNESS * (length - natural) + dolphin.DAMPING * rate)
        out[j] += tension * unit
        out[i] -= tension * unit
    m = model.mj_model
    for plate in dolphin.PLATES:
        for k, (node, _) in enumerate(plate.align):
            site = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_SITE, f"{plate.name}_align{k}")
            tendon = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_TENDON, f"{plate.name}_align{k}")
            r = x[node] - d.site_xpos[site]
            length = np.linalg.norm(r)
            tension = -(
                dolphin.ALIGN_STIFFNESS * (length - dolphin.ALIGN_OFFSET)
                + dolphin.ALIGN_DAMPING * d.ten_velocity[tendon]
            )
            out[node] += tension * r / length
            out[plate.anchor] -= tension * r / length  # the plate hangs from its anchor node
    return out


def _state(model: PhysicalModel, d: mujoco.MjData) -> np.ndarray:
    return np.concatenate([getattr(d, g.source)[g.address : g.address + g.size] for g in model.layout])


def _node_velocities(model: PhysicalModel, d: mujoco.MjData) -> np.ndarray:
    return _state(model, d)[dolphin.NODE_VEL].reshape(dolphin.NUM_NODES, 3)


def _node_dofs(model: PhysicalModel) -> np.ndarray:
    m = model.mj_model
    dofs = [
        m.jnt_dofadr[mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, f"{n}_{ax}")]
        for n in dolphin.NODES
        for ax in "xyz"
    ]
    return np.asarray(dofs)


@pytest.mark.parametrize("seed", [0, 1])
def test_spring_and_muscle_forces_match_a_hand_computation(model: PhysicalModel, seed: int) -> None:
    s, a = _deformed(model, seed)
    d = _forward(model, s, a)
    mujoco_forces = (d.qfrc_spring + d.qfrc_damper + d.qfrc_actuator)[_node_dofs(model)].reshape(-1, 3)
    np.testing.assert_allclose(mujoco_forces, _node_forces_by_hand(model, d, a), rtol=1e-9, atol=1e-9)
    assert np.abs(mujoco_forces).max() > 10.0  # a real deformation, not a trivial agreement


def test_one_activation_contracts_both_muscles_of_its_pair(model: PhysicalModel) -> None:
    s = model.rest_state()
    for k, (left, right) in enumerate(dolphin.MUSCLES):
        a = np.zeros(6)
        a[k] = 1.0
        d = _forward(model, s, a)
        forces = d.qfrc_actuator[_node_dofs(model)].reshape(-1, 3)
        moved = set(np.flatnonzero(np.abs(forces).sum(axis=1) > 1e-9))
        assert moved == {*left, *right}
        x = dolphin.rest_positions()
        for i, j in (left, right):
            rest = np.linalg.norm(x[j] - x[i])
            pull = (x[i] - x[j]) / rest  # contraction pulls j toward i
            expected = dolphin.STIFFNESS * (1 - dolphin.MUSCLE_CONTRACTION) * rest
            np.testing.assert_allclose(forces[j], expected * pull, rtol=1e-9)


def test_a_plate_resists_motion_normal_to_it_more_than_along_it(model: PhysicalModel) -> None:
    """The drag law of one water plate (MuJoCo's ellipsoid model with the dolphin's water and plate)."""
    plate = dolphin.PLATES[0]
    opt = model.mj_model.opt
    xml = f"""<mujoco><option density="{opt.density}" viscosity="{opt.viscosity}" gravity="0 0 0"/>
      <worldbody><body><freejoint/><geom type="ellipsoid" size="{" ".join(map(str, plate.half))}"
      fluidshape="ellipsoid" mass="1"/></body></worldbody></mujoco>"""
    m = mujoco.MjModel.from_xml_string(xml)
    d = mujoco.MjData(m)

    def force(velocity: list[float]) -> np.ndarray:
        d.qvel[:] = 0.0
        d.qvel[:3] = velocity
        mujoco.mj_forward(m, d)
        return d.qfrc_fluid[:3].copy()

    normal, twice = force([0.0, 0.0, 1.0]), force([0.0, 0.0, 2.0])
    along = force([1.0, 0.0, 0.0])
    assert normal[2] < 0 and np.allclose(normal[:2], 0.0)  # against the motion
    assert twice[2] == pytest.approx(4 * normal[2], rel=0.01)  # quadratic in the speed
    assert abs(normal[2]) > 1.8 * abs(along[0])
    angle = np.radians(30.0)  # oblique: per unit of velocity, the normal part is resisted ≥ 4× more
    oblique = force([-np.cos(angle), 0.0, -np.sin(angle)])
    assert oblique[2] / np.sin(angle) > 4.0 * oblique[0] / np.cos(angle) > 0


def test_deformation_energy_is_zero_at_rest_and_grows_with_deformation() -> None:
    rest = dolphin.rest_positions()
    assert dolphin.deformation_energy(rest) == pytest.approx(0.0, abs=1e-20)
    moved = rest + np.array([3.0, -2.0, 1.0])  # a rigid motion is no deformation
    assert dolphin.deformation_energy(moved) == pytest.approx(0.0, abs=1e-20)
    direction = np.random.default_rng(3).normal(size=rest.shape)
    energies = [float(dolphin.deformation_energy(rest + eps * direction)) for eps in (0.005, 0.01, 0.02)]
    assert 0 < energies[0] < energies[1] < energies[2]
    assert energies[1] == pytest.approx(4 * energies[0], rel=0.05)  # quadratic for small strains
    stretched = rest * np.array([1.1, 1.0, 1.0])
    i, j = np.asarray(dolphin.SPRINGS).T
    strain = (
        np.linalg.norm(stretched[j] - stretched[i], axis=1) - dolphin.rest_lengths()
    ) / dolphin.rest_lengths()
    assert dolphin.deformation_energy(stretched) == pytest.approx(0.5 * np.sum(strain**2))
    batch = np.stack([rest, stretched])
    both = dolphin.deformation_energy(batch)
    assert both.shape == (2,)
    assert both[0] == pytest.approx(0.0, abs=1e-20)
    assert both[1] == pytest.approx(float(dolphin.deformation_energy(stretched)))


def test_travelling_wave_is_antagonistic_and_in_range() -> None:
    t = np.linspace(0.0, 3.0, 301)
    u = dolphin.travelling_wave(t)
    assert u.shape == (301, 6)
    assert u.min() >= 0.0 and u.max() <= 1.0
    np.testing.assert_allclose(u[:, 0::2] + u[:, 1::2], 1.0)  # dorsal and ventral in antiphase


def test_the_travelling_wave_swims_forward_keeping_its_shape(model: PhysicalModel) -> None:
    """20 s of the hand-written stroke (period 4 s): at least 0.8 m forward (about 1 m; 0.067 m/s,
    0.033 body lengths per second once under way), straight, with the deformation energy bounded."""
    steps = 2000
    u = dolphin.travelling_wave(np.arange(steps) * model.dt)[None]
    traj = model.simulate(model.rest_state()[None], u)[0]
    com = dolphin.centre_of_mass(traj)
    start = dolphin.centre_of_mass(model.rest_state())
    assert com[-1, 0] - start[0] > 0.8
    assert com[-1, 0] - com[steps // 2, 0] > 0.5  # still swimming in the second half
    assert np.abs(com[:, 1] - start[1]).max() < 1e-6  # left-right symmetric: no drift sideways
    assert np.abs(com[:, 2] - start[2]).max() < 0.2
    energy = dolphin.deformation_energy(dolphin.node_positions(traj))
    assert energy.max() < 0.3


def test_without_muscles_the_dolphin_drifts_to_rest(model: PhysicalModel) -> None:
    s, _ = _deformed(model, 5)
    traj = model.simulate(s[None], np.zeros((1, 1, 6)), nstep=1000)[0]
    assert dolphin.deformation_energy(dolphin.node_positions(traj[-1])) < 1e-3
    assert np.abs(traj[-1, dolphin.NODE_VEL]).max() < 0.05


def test_the_skin_is_the_body_surface_and_changes_nothing_simulated() -> None:
    """The MJCF skin (drawn over the nodes) is visual only: without it MuJoCo computes the very same
    motion; its triangles close the body and face outwards."""
    xml = dolphin.mjcf()
    start, end = xml.index("  <deformable>"), xml.index("  </deformable>") + len("  </deformable>\n")
    runs = []
    for text in (xml, xml[:start] + xml[end:]):
        m = mujoco.MjModel.from_xml_string(text)
        d = mujoco.MjData(m)
        for k in range(300):
            d.ctrl[:] = 0.5 + 0.5 * np.sin(0.05 * k + np.arange(6))
            mujoco.mj_step(m, d)
        runs.append((m.nskin, np.concatenate([d.qpos, d.qvel])))
    (with_skin, a), (without, b) = runs
    assert (with_skin, without) == (1, 0)
    np.testing.assert_array_equal(a, b)
    faces = dolphin.skin_faces()
    assert len(faces) == 40 and sorted({i for f in faces for i in f}) == list(range(dolphin.NUM_NODES))
    # every edge of the closed trunk (nose to the tail cap) is shared by two triangles
    trunk = [
        f
        for f in faces
        if dolphin.NODES.index("fluke_l") not in f and dolphin.NODES.index("fluke_r") not in f
    ]
    edges: dict[tuple[int, int], int] = {}
    for f in trunk:
        for i, j in ((f[0], f[1]), (f[1], f[2]), (f[2], f[0])):
            edges[(min(i, j), max(i, j))] = edges.get((min(i, j), max(i, j)), 0) + 1
    assert set(edges.values()) == {2}
    # outward: the enclosed volume of the trunk (divergence theorem) is positive
    p = dolphin.rest_positions()
    volume = sum(float(np.dot(p[a], np.cross(p[b], p[c]))) for a, b, c in trunk) / 6
    assert volume > 0.05
