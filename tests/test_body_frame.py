"""The body frame of a free root: every attitude, upside down included, is continuous and equivariant.

The quadrotor's data cover the whole sphere of attitudes. In the heading frame the heading of a body
turned upside down is undefined and the inputs jump there; the body frame (world vectors rotated by
the whole orientation, gravity as a body-frame up vector) has no such point.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import pytest
import torch

from neuroanimator import catalog
from neuroanimator.core import quaternion
from neuroanimator.emulator.structured import StructuredEmulator
from neuroanimator.sim.model import PhysicalModel

MakeEmulator = Callable[..., StructuredEmulator]
FREE_FLYERS = ["lander", "quadrotor"]


def _predict(emu: StructuredEmulator, s: np.ndarray, u: np.ndarray) -> np.ndarray:
    with torch.no_grad():
        return emu(torch.from_numpy(s).double(), torch.from_numpy(u).double()).numpy()


def _rotation(q: np.ndarray) -> np.ndarray:
    """The 3×3 rotation matrix of a unit quaternion (4,): its columns are the turned axes."""
    return np.stack([quaternion.rotate(q, e) for e in np.eye(3)], axis=-1)


def _move(model: PhysicalModel, s: np.ndarray, q_world: np.ndarray, shift: np.ndarray) -> np.ndarray:
    """Turn the whole scene by ``q_world`` and translate it by ``shift``."""
    lay, out = model.layout, s.copy()
    r = _rotation(q_world)
    pos, att = lay.find("position"), lay.find("quaternion")
    assert pos is not None and att is not None
    out[:, lay.slice_of(pos.name)] = s[:, lay.slice_of(pos.name)] @ r.T + shift
    out[:, lay.slice_of(att.name)] = quaternion.multiply(
        np.broadcast_to(q_world, (s.shape[0], 4)), s[:, lay.slice_of(att.name)]
    )
    for g, sl in lay.group_slices():
        if g.kind == "world_vector":
            out[:, sl] = s[:, sl] @ r.T
    return out  # body-frame angular velocity: unchanged


def _sphere_of_attitudes(model: PhysicalModel, count: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """States at ``count`` attitudes spread over the whole sphere, with typical controls."""
    rng = np.random.default_rng(seed)
    s = model.initial_states(rng, count)
    q = rng.normal(size=(count, 4))
    att = model.layout.find("quaternion")
    assert att is not None
    s[:, model.layout.slice_of(att.name)] = q / np.linalg.norm(q, axis=1, keepdims=True)
    u = model.typical_controls(rng, count, np.zeros(1))[:, 0]
    return s, u


@pytest.mark.parametrize("name", FREE_FLYERS)
def test_free_roots_use_the_body_frame_by_default(name: str, make_emulator: MakeEmulator) -> None:
    emu = make_emulator(catalog.get(name))
    assert emu.architecture()["frame"]["body"] is True  # type: ignore[index]


@pytest.mark.parametrize("name", FREE_FLYERS)
@pytest.mark.parametrize("seed", [0, 1])
def test_equivariant_under_translation_and_rotation_about_gravity_at_every_attitude(
    name: str, seed: int, make_emulator: MakeEmulator
) -> None:
    model = catalog.get(name)
    emu = make_emulator(model, seed=seed).double()
    s, u = _sphere_of_attitudes(model, 64, seed)
    rng = np.random.default_rng(10 + seed)
    for _ in range(3):
        q_z = quaternion.from_axis_angle(np.array([0.0, 0.0, 1.0]), rng.uniform(-np.pi, np.pi))
        shift = rng.uniform(-50.0, 50.0, 3)
        got = _predict(emu, _move(model, s, q_z, shift), u)
        expected = _move(model, _predict(emu, s, u), q_z, shift)
        np.testing.assert_allclose(got, expected, atol=1e-9 * max(1.0, np.abs(expected).max()))


@pytest.mark.parametrize("name", FREE_FLYERS)
def test_not_equivariant_under_tilt(name: str, make_emulator: MakeEmulator) -> None:
    """Gravity points down: turning the scene about a horizontal axis changes the prediction."""
    model = catalog.get(name)
    emu = make_emulator(model).double()
    s, u = _sphere_of_attitudes(model, 32, 3)
    q_x = quaternion.from_axis_angle(np.array([1.0, 0.0, 0.0]), 0.7)
    moved = _move(model, s, q_x, np.zeros(3))
    assert np.abs(_predict(emu, moved, u) - _move(model, _predict(emu, s, u), q_x, np.zeros(3))).max() > 1e-3


@pytest.mark.parametrize("axis", [np.array([1.0, 0.0, 0.0]), np.array([0.6, 0.8, 0.0])])
def test_prediction_is_continuous_through_upside_down(axis: np.ndarray, make_emulator: MakeEmulator) -> None:
    """Sweep the attitude through a full turn about a horizontal axis (upside down half way): the
    predicted state changes by at most a small multiple of the step, in the body frame; the heading
    frame jumps where the heading is undefined."""
    model = catalog.get("quadrotor")
    angles = np.linspace(0.0, 2.0 * np.pi, 721)
    base = np.repeat(model.initial_states(np.random.default_rng(4), 1), angles.size, axis=0)
    att = model.layout.find("quaternion")
    assert att is not None
    base[:, model.layout.slice_of(att.name)] = quaternion.from_axis_angle(axis, angles)
    u = np.full((angles.size, model.num_controls), 2.0)

    def largest_jump(frame: str) -> float:
        pred = _predict(make_emulator(model, seed=5, frame=frame).double(), base, u)
        change = pred - base  # the predicted state change, free of the sweep itself
        return float(np.abs(np.diff(change, axis=0)).max() / np.abs(change).max())

    assert largest_jump("body") < 0.05
    assert largest_jump("heading") > 5 * largest_jump("body")


def test_quadrotor_physics_shares_the_symmetry() -> None:
    """Translation and rotation about gravity are true of MuJoCo's quadrotor, upside down too."""
    model = catalog.get("quadrotor")
    s, u = _sphere_of_attitudes(model, 6, 7)
    q_z = quaternion.from_axis_angle(np.array([0.0, 0.0, 1.0]), 1.1)
    shift = np.array([3.0, -4.0, 2.0])
    expected = _move(model, model.step_held(s, u, None, 20), q_z, shift)
    np.testing.assert_allclose(model.step_held(_move(model, s, q_z, shift), u, None, 20), expected, atol=1e-7)


def test_body_frame_inputs_written_out(make_emulator: MakeEmulator) -> None:
    """T'_x in the body frame: velocity turned by Rᵀ, the attitude as Rᵀ e_z, translation dropped."""
    model = catalog.get("quadrotor")
    emu = make_emulator(model).double()
    s, u = _sphere_of_attitudes(model, 8, 8)
    lay = model.layout
    att, pos = lay.find("quaternion"), lay.find("position")
    vel = next(g for g in lay if g.kind == "world_vector")
    spin = next(g for g in lay if g.kind == "local_vector")
    assert att is not None and pos is not None
    x = emu.local_inputs(torch.from_numpy(s), torch.from_numpy(u), None).numpy()
    for i in range(s.shape[0]):
        r = _rotation(s[i, lay.slice_of(att.name)])
        expected = np.concatenate(
            [
                r.T @ np.array([0.0, 0.0, 1.0]),
                r.T @ s[i, lay.slice_of(vel.name)],
                s[i, lay.slice_of(spin.name)],
                u[i],
            ]
        )
        np.testing.assert_allclose(x[i], expected, atol=1e-12)


def test_a_tumbling_body_is_learned_as_well_upside_down_as_upright() -> None:
    """A small quadrotor emulator: its held-out one-step error on states turned upside down is close
    to its error on upright ones (in the heading frame, the upside-down half is much worse)."""
    from neuroanimator.sim import sampling
    from neuroanimator.training import train as training
    from neuroanimator.training.train import TrainConfig, relative_error, to_tensors

    model = catalog.get("quadrotor")
    cfg = TrainConfig(
        substeps=10, hidden=(32, 32), examples=6000, max_epochs=40, rollout_steps=0, progress=False, threads=1
    )
    emu = training.train(model, cfg).emulator
    test = sampling.generate(model, 10, 3000, seed=77, progress=False)
    att = model.layout.find("quaternion")
    assert att is not None
    q = test.states[:, model.layout.slice_of(att.name)]
    up_z = 1.0 - 2.0 * (q[:, 1] ** 2 + q[:, 2] ** 2)  # world z of the body's z axis
    s, u, f, nxt = to_tensors(test)
    with torch.no_grad():
        pred, target = emu.network(emu.network_inputs(s, u, f)), emu.network_targets(s, nxt)
    upright, upside_down = torch.from_numpy(up_z > 0.5), torch.from_numpy(up_z < -0.5)
    assert upright.sum() > 300 and upside_down.sum() > 300  # the data cover both
    err_up = relative_error(pred[upright], target[upright])
    err_down = relative_error(pred[upside_down], target[upside_down])
    assert err_up < 0.05 and err_down < 0.05
    print(f"one-step relative error upright {err_up:.4g}, upside down {err_down:.4g}")
    assert 0.5 < err_down / err_up < 2.0


def test_the_attitude_target_is_continuous_through_a_half_turn_in_one_step(
    make_emulator: MakeEmulator,
) -> None:
    """A tumbling body can turn by more than π in one long super-step (the quadrotor's N^100: 7% of its
    examples). The training target for the attitude, the body-frame increment q⁻¹ ⊗ q' − 1, follows the
    turn φ continuously from 0 to 2π (the simulation's q' keeps its sign), and maps back to q'."""
    model = catalog.get("quadrotor")
    emu = make_emulator(model).double()
    att = model.layout.find("quaternion")
    assert att is not None
    sl = model.layout.slice_of(att.name)
    turns = np.linspace(0.0, 1.99 * np.pi, 400)
    s = np.repeat(model.initial_states(np.random.default_rng(9), 1), turns.size, axis=0)
    s[:, sl] = quaternion.from_axis_angle(np.array([0.3, -0.5, 0.8]) / np.sqrt(0.98), 0.4)
    nxt = s.copy()
    nxt[:, sl] = quaternion.multiply(s[:, sl], quaternion.from_axis_angle(np.array([0.0, 0.6, 0.8]), turns))
    state, delta = torch.from_numpy(s), torch.from_numpy(nxt - s)
    increment = emu.delta_to_local(state, delta).numpy()[:, sl]
    np.testing.assert_allclose(increment[:, 0], np.cos(turns / 2) - 1, atol=1e-9)
    step = np.abs(np.diff(increment, axis=0)).max()
    assert step < 2.0 * (turns[1] - turns[0]), step  # no jump at φ = π
    back = (state + emu.delta_to_world(state, emu.delta_to_local(state, delta))).numpy()
    np.testing.assert_allclose(back[:, sl], nxt[:, sl], atol=1e-9)
