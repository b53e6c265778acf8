"""The physics catalog: every built-in model against the contract and the thesis' numbers."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import mujoco
import numpy as np
import pytest

from neuroanimator import catalog
from neuroanimator.catalog import lander
from neuroanimator.sim import sampling
from neuroanimator.sim.model import PhysicalModel

NAMES = sorted(catalog.CATALOG)


@pytest.fixture(params=NAMES)
def model(request: pytest.FixtureRequest) -> PhysicalModel:
    return catalog.get(request.param)


def test_every_model_loads_under_its_catalog_name(model: PhysicalModel) -> None:
    assert model.name in catalog.CATALOG
    assert model.spec.name == model.name
    assert model.dt > 0


@pytest.mark.parametrize(
    ("obj", "count"),
    [
        (mujoco.mjtObj.mjOBJ_JOINT, "njnt"),
        (mujoco.mjtObj.mjOBJ_ACTUATOR, "nu"),
    ],
)
def test_joints_and_actuators_are_named(model: PhysicalModel, obj: mujoco.mjtObj, count: str) -> None:
    m = model.mj_model
    names = [mujoco.mj_id2name(m, obj, i) for i in range(getattr(m, count))]
    assert all(names), names
    assert len(set(names)) == len(names)


def test_bodies_are_named(model: PhysicalModel) -> None:
    m = model.mj_model
    names = [mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_BODY, i) for i in range(1, m.nbody)]  # 0 is the world
    assert m.nbody > 1
    assert all(names), names


def test_simulation_from_typical_states_stays_finite(model: PhysicalModel) -> None:
    rng = np.random.default_rng(5)
    steps = 2000
    times = np.arange(float(steps)) * model.dt
    s0 = model.initial_states(rng, 4)
    u = model.typical_controls(rng, 4, times)
    f = model.typical_forces(rng, 4, times) if model.num_forces else None
    traj = model.simulate(s0, u, f)
    assert traj.shape == (4, steps, model.state_size)
    assert np.all(np.isfinite(traj))
    assert not np.allclose(traj[:, -1], s0)  # something happened


def test_same_seed_gives_same_inputs_and_data(model: PhysicalModel) -> None:
    times = np.arange(50.0) * model.dt

    def draw(seed: int) -> list[np.ndarray]:
        rng = np.random.default_rng(seed)
        return [
            model.initial_states(rng, 5),
            model.typical_controls(rng, 5, times),
            model.typical_forces(rng, 5, times),
        ]

    for a, b in zip(draw(9), draw(9), strict=True):
        np.testing.assert_array_equal(a, b)
    one, two = (
        sampling.generate(model, 5, 40, 3, progress=False),
        sampling.generate(model, 5, 40, 3, progress=False),
    )
    np.testing.assert_array_equal(one.states, two.states)
    np.testing.assert_array_equal(one.next_states, two.next_states)
    # another seed draws other starts (where the model's start range is more than a point, unlike the
    # dolphin's, which starts at rest) and other controls
    init = model.spec.initial
    if np.any(np.asarray(init.high) > np.asarray(init.low)) or init.random_yaw or init.max_tilt > 0:
        assert not np.array_equal(draw(9)[0], draw(10)[0])
    if model.num_controls:
        assert not np.array_equal(draw(9)[1], draw(10)[1])


def test_typical_controls_and_forces_stay_in_their_ranges(model: PhysicalModel) -> None:
    rng = np.random.default_rng(2)
    times = np.arange(400.0) * model.dt
    u = model.typical_controls(rng, 6, times)
    f = model.typical_forces(rng, 6, times)
    assert u.shape == (6, 400, model.num_controls)
    assert f.shape == (6, 400, model.num_forces)
    assert np.all(u >= model.control_range[:, 0]) and np.all(u <= model.control_range[:, 1])
    assert np.all(f >= model.force_range[:, 0]) and np.all(f <= model.force_range[:, 1])


def test_step_held_equals_simulate_with_repeated_control(model: PhysicalModel) -> None:
    rng = np.random.default_rng(8)
    n = 7
    s0 = model.initial_states(rng, 3)
    u = model.typical_controls(rng, 3, np.zeros(1))[:, 0]
    f = model.typical_forces(rng, 3, np.zeros(1))[:, 0]
    held = model.step_held(s0, u if model.num_controls else None, f if model.num_forces else None, n)
    repeated = model.simulate(
        s0, np.repeat(u[:, None], n, axis=1), np.repeat(f[:, None], n, axis=1) if model.num_forces else None
    )
    np.testing.assert_array_equal(held, repeated[:, -1])


def test_state_round_trips_through_mujoco(model: PhysicalModel) -> None:
    s = model.initial_states(np.random.default_rng(1), 3)
    np.testing.assert_array_equal(model.from_physics(model.to_physics(s)), s)


def test_state_matches_single_mujoco_step(model: PhysicalModel) -> None:
    """The batched rollout reads and writes qpos/qvel where the layout says (checked against mj_step)."""
    s = model.initial_states(np.random.default_rng(4), 1)[0]
    u = model.typical_controls(np.random.default_rng(4), 1, np.zeros(1))[0, 0]
    f = model.typical_forces(np.random.default_rng(4), 1, np.zeros(1))[0, 0]
    m = model.mj_model
    d = mujoco.MjData(m)
    for g, sl in model.layout.group_slices():
        getattr(d, g.source)[g.address : g.address + g.size] = s[sl]
    ctrl_ids = [mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_ACTUATOR, name) for name in model.control_names]
    d.ctrl[ctrl_ids] = u
    for value, fi in zip(f, model.spec.forces, strict=True):
        d.xfrc_applied[mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, fi.body), fi.component] = value
    for _ in range(3):
        mujoco.mj_step(m, d)
    expected = np.concatenate([getattr(d, g.source)[g.address : g.address + g.size] for g in model.layout])
    got = model.step_held(
        s[None], u[None] if model.num_controls else None, f[None] if model.num_forces else None, 3
    )
    np.testing.assert_allclose(got[0], expected, atol=1e-10)


@pytest.mark.parametrize(
    ("name", "state", "controls", "forces"),
    [
        ("pendulum-passive", 6, 0, 0),
        ("pendulum-active", 6, 3, 0),
        ("pendulum-force", 6, 3, 3),
        ("lander", 13, 4, 0),
        ("truck", 6, 2, 0),
    ],
)
def test_layout_sizes_match_the_thesis(name: str, state: int, controls: int, forces: int) -> None:
    model = catalog.get(name)
    assert (model.state_size, model.num_controls, model.num_forces) == (state, controls, forces)
    assert len(model.control_names) == controls
    assert len(model.force_names) == forces


def test_lander_physical_constants_match_the_thesis() -> None:
    m = catalog.get("lander").mj_model
    np.testing.assert_allclose(m.opt.gravity, [0.0, 0.0, -1.62])
    assert m.opt.timestep == pytest.approx(0.01)
    ship = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, "ship")
    assert m.body_mass[ship] == pytest.approx(100.0)
    np.testing.assert_allclose(m.body_inertia[ship], [5.0, 5.0, 2.0])


def test_lander_hovers_in_place_at_hover_thrust() -> None:
    model = catalog.get("lander")
    s0 = model.rest_state()[None]
    s0[0, model.layout.slice_of("position")] = [3.0, -2.0, 15.0]
    u = np.array([[lander.HOVER_THRUST, 0.0, 0.0, 0.0]])
    end = model.step_held(s0, u, None, 500)[0]  # 5 s
    np.testing.assert_allclose(end[model.layout.slice_of("position")], [3.0, -2.0, 15.0], atol=1e-3)
    np.testing.assert_allclose(end[model.layout.slice_of("velocity")], 0.0, atol=1e-3)
    np.testing.assert_allclose(end[model.layout.slice_of("orientation")], [1.0, 0.0, 0.0, 0.0], atol=1e-6)


def test_lander_falls_without_thrust() -> None:
    model = catalog.get("lander")
    s0 = model.rest_state()[None]
    end = model.step_held(s0, np.zeros((1, 4)), None, 100)[0]
    assert end[model.layout.slice_of("velocity")][2] < -1.0  # about -1.62 m/s after 1 s, less drag


def test_truck_friction_actuators_are_not_controls() -> None:
    model = catalog.get("truck")
    assert model.control_names == ["steer", "gas"]
    assert model.mj_model.nu == 4  # the two friction actuators are in the MJCF, in the passive group


def test_truck_sideways_friction_resists_sliding() -> None:
    model = catalog.get("truck")
    s0 = model.rest_state()[None]
    s0[0, model.layout.slice_of("velocity")] = [0.0, 2.0]  # heading 0: pure sideways slide
    end = model.step_held(s0, np.zeros((1, 2)), None, 100)[0]
    assert abs(end[model.layout.slice_of("velocity")][1]) < 1.0


def test_passive_pendulum_has_no_controls() -> None:
    model = catalog.get("pendulum-passive")
    assert model.num_controls == 0
    assert model.control_names == []
    assert model.mj_model.nu == 0


def test_pendulum_force_inputs_push_their_links() -> None:
    model = catalog.get("pendulum-force")
    assert model.force_names == ["push0", "push1", "push2"]
    s0 = model.rest_state()[None]
    pushed = model.step_held(s0, np.zeros((1, 3)), np.array([[0.0, 0.0, 2.0]]), 50)
    still = model.step_held(s0, np.zeros((1, 3)), np.zeros((1, 3)), 50)
    np.testing.assert_allclose(still, s0, atol=1e-12)  # hanging at rest stays at rest
    assert np.abs(pushed - s0).max() > 1e-3


def test_unknown_model_raises_model_error_naming_it() -> None:
    with pytest.raises(catalog.ModelError, match="no-such-model"):
        catalog.get("no-such-model")


def test_bad_input_width_is_rejected() -> None:
    model = catalog.get("truck")
    with pytest.raises(catalog.ModelError, match="controls"):
        model.check_batch("controls", np.zeros((2, 3)), model.num_controls)
    with pytest.raises(catalog.ModelError, match="finite"):
        model.check_batch("controls", np.full((2, 2), np.nan), model.num_controls)


def _truck_with_layout(change: dict[str, object], group: int) -> PhysicalModel:
    truck = catalog.get("truck")
    assert truck.spec.layout is not None
    layout = [g.model_dump() for g in truck.spec.layout]
    layout[group].update(change)
    spec = catalog.ModelSpec.model_validate({**truck.spec.model_dump(), "layout": layout})
    return PhysicalModel(truck.xml, spec)


def test_layout_reading_past_mujoco_arrays_raises_naming_the_group() -> None:
    with pytest.raises(catalog.ModelError, match="'yaw_rate'"):
        _truck_with_layout({"address": 3}, group=3)  # the truck has 3 qvel values


def test_layout_with_negative_address_raises_naming_the_group() -> None:
    # address -1 of qpos would read the slot before qpos in MuJoCo's state vector (the time)
    with pytest.raises(ValueError, match="'position'"):
        _truck_with_layout({"address": -1}, group=0)


def test_layout_with_unknown_source_raises_naming_the_group() -> None:
    # a group must live in qpos or qvel; anything else must not silently read qvel
    with pytest.raises(ValueError, match="'yaw_rate'"):
        _truck_with_layout({"source": "qacc"}, group=3)


def test_simulate_rejects_controls_for_a_model_without_actuators() -> None:
    model = catalog.get("pendulum-passive")
    s0 = model.initial_states(np.random.default_rng(0), 2)
    with pytest.raises(catalog.ModelError, match="takes no controls"):
        model.simulate(s0, np.zeros((2, 5, 3)))


@pytest.mark.parametrize(
    ("states_shape", "controls", "match"),
    [
        ((2, 5), np.zeros((2, 4, 3)), r"states must have shape \(batch, 6\)"),
        ((2, 6), np.zeros((2, 4, 2)), r"controls must have shape \(batch, steps, 3\)"),
        ((2, 6), np.full((2, 4, 3), np.nan), "controls must be finite"),
        ((2, 6), np.zeros((3, 4, 3)), "controls must have 2 rows"),
    ],
)
def test_simulate_names_the_bad_argument(
    states_shape: tuple[int, int], controls: np.ndarray, match: str
) -> None:
    model = catalog.get("pendulum-active")
    with pytest.raises(catalog.ModelError, match=match):
        model.simulate(np.zeros(states_shape), controls)


TASK_NAMES = sorted(t.name for system in catalog.SYSTEMS for t in system.TASKS)


@pytest.mark.parametrize("name", TASK_NAMES)
def test_tasks_live_beside_their_model_and_speak_its_layout(name: str) -> None:
    """A task is defined in the module of its model's system, and its labels are that model's layout's."""
    (system, task) = next((s, t) for s in catalog.SYSTEMS for t in s.TASKS if t.name == name)
    assert catalog.CATALOG[task.model].__module__ == system.__name__
    model = catalog.get(task.model)
    assert list(task.labels) == model.layout.labels()
    assert len(task.initial_controls) == model.num_controls
    assert all(set(check.variables) <= set(task.labels) for check in task.success)


def test_the_catalog_lists_its_names_and_tasks_without_mujoco() -> None:
    code = (
        "import sys; from neuroanimator import catalog; "
        "assert [t.name for s in catalog.SYSTEMS for t in s.TASKS]; assert catalog.CATALOG; "
        "assert 'mujoco' not in sys.modules, 'mujoco loaded'; "
        "catalog.get('truck'); assert 'mujoco' in sys.modules"
    )
    subprocess.run([sys.executable, "-c", code], check=True, timeout=60, cwd=Path(__file__).parents[2])
