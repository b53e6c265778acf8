"""The structured emulator (thesis 4.3, eq. 4.14): its transforms, their inverses and its symmetries."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import overload

import numpy as np
import pytest
import torch

from neuroanimator import catalog
from neuroanimator.core import quaternion
from neuroanimator.emulator.structured import StructuredEmulator, make_core
from neuroanimator.sim import sampling
from neuroanimator.sim.model import PhysicalModel
from neuroanimator.training import train as training
from neuroanimator.training.train import TrainConfig

NAMES = sorted(catalog.CATALOG)
MakeEmulator = Callable[..., StructuredEmulator]
InputsOf = Callable[..., tuple[np.ndarray, np.ndarray | None, np.ndarray | None]]


@overload
def t32(a: np.ndarray) -> torch.Tensor: ...
@overload
def t32(a: np.ndarray | None) -> torch.Tensor | None: ...
def t32(a: np.ndarray | None) -> torch.Tensor | None:
    return None if a is None else torch.from_numpy(np.asarray(a)).float()


@overload
def t64(a: np.ndarray) -> torch.Tensor: ...
@overload
def t64(a: np.ndarray | None) -> torch.Tensor | None: ...
def t64(a: np.ndarray | None) -> torch.Tensor | None:
    return None if a is None else torch.from_numpy(np.asarray(a)).double()


def predict(emu: StructuredEmulator, s: np.ndarray, u: np.ndarray | None, f: np.ndarray | None) -> np.ndarray:
    with torch.no_grad():
        return emu(t32(s), t32(u), t32(f)).double().numpy()


def rot_z(angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


# ---------------------------------------------------------------------------- (a) T'_y is invertible
@pytest.mark.parametrize("name", NAMES)
def test_delta_to_world_inverts_delta_to_local(
    name: str, make_emulator: MakeEmulator, inputs_of: InputsOf
) -> None:
    model = catalog.get(name)
    emu = make_emulator(model).double()
    s, _, _ = inputs_of(model, 32, seed=1)
    delta = torch.from_numpy(np.random.default_rng(2).normal(size=s.shape))
    state = t64(s)
    back = emu.delta_to_world(state, emu.delta_to_local(state, delta))
    expected, got = (state + delta).numpy(), (state + back).numpy()
    for g, sl in model.layout.group_slices():
        if g.kind == "quaternion":  # the body frame's increment stands for q' and −q' alike
            flip = np.sign(np.sum(expected[:, sl] * got[:, sl], axis=1, keepdims=True))
            got[:, sl] *= flip
    np.testing.assert_allclose(got, expected, atol=1e-9)


def test_lander_delta_to_local_rotates_by_minus_heading(make_emulator: MakeEmulator) -> None:
    model = catalog.get("lander")
    emu = make_emulator(model, frame="heading").double()
    lay = model.layout
    s = model.rest_state()[None].copy()
    yaw = 0.9
    tilt = quaternion.from_axis_angle(np.array([1.0, 0.0, 0.0]), 0.3)
    s[0, lay.slice_of("orientation")] = quaternion.multiply(
        quaternion.from_axis_angle(np.array([0.0, 0.0, 1.0]), yaw), tilt
    )
    delta = np.random.default_rng(3).normal(size=s.shape)
    local = emu.delta_to_local(t64(s), t64(delta)).numpy()[0]
    back = rot_z(-yaw)
    np.testing.assert_allclose(
        local[lay.slice_of("position")], back @ delta[0, lay.slice_of("position")], atol=1e-9
    )
    np.testing.assert_allclose(
        local[lay.slice_of("velocity")], back @ delta[0, lay.slice_of("velocity")], atol=1e-9
    )
    h = quaternion.from_axis_angle(np.array([0.0, 0.0, 1.0]), yaw)
    np.testing.assert_allclose(
        local[lay.slice_of("orientation")],
        quaternion.multiply(quaternion.conjugate(h), delta[0, lay.slice_of("orientation")]),
        atol=1e-9,
    )
    # the angular velocity is already in the body frame: untouched
    np.testing.assert_allclose(
        local[lay.slice_of("angular_velocity")], delta[0, lay.slice_of("angular_velocity")]
    )


# ---------------------------------------------------------------------------- (b) the composition
@pytest.mark.parametrize("name", NAMES)
def test_forward_is_finish_of_core_of_network_inputs(
    name: str, make_emulator: MakeEmulator, inputs_of: InputsOf
) -> None:
    model = catalog.get(name)
    emu = make_emulator(model)
    ins = inputs_of(model, 16, seed=3)
    s, u, f = t32(ins[0]), t32(ins[1]), t32(ins[2])
    with torch.no_grad():
        expected = emu.finish(s, emu.network(emu.network_inputs(s, u, f)))
        torch.testing.assert_close(emu(s, u, f), expected, rtol=0, atol=0)


@pytest.mark.parametrize("name", NAMES)
@pytest.mark.parametrize("mode", ["group", "variable"])
def test_forward_is_the_composition_of_eq_4_14(
    name: str, mode: str, make_emulator: MakeEmulator, inputs_of: InputsOf
) -> None:
    """s' = T^Δ_y T'_y T^σ_y N T^σ_x T'_x [s, u, f], each transform written out here."""
    model = catalog.get(name)
    emu = make_emulator(model, seed=4, mode=mode).double()
    ins = inputs_of(model, 16, seed=4)
    s, u, f = t64(ins[0]), t64(ins[1]), t64(ins[2])
    with torch.no_grad():
        x_local = emu.local_inputs(s, u, f)  # T'_x
        x = (x_local - emu.x_mean) / emu.x_std  # T^σ_x (eq. 4.9)
        torch.testing.assert_close(emu.normalize_inputs(x_local), x)
        y = emu.network(x)  # N
        d_local = y * emu.y_std + emu.y_mean  # T^σ_y (eq. 4.12)
        torch.testing.assert_close(emu.denormalize_outputs(y), d_local)
        nxt = s + emu.delta_to_world(s, d_local)  # T^Δ_y T'_y (eqs. 4.7, 4.8, 4.13)
        for g, sl in model.layout.group_slices():
            if g.kind in ("quaternion", "local_quaternion"):
                nxt[:, sl] = nxt[:, sl] / nxt[:, sl].norm(dim=1, keepdim=True)
        torch.testing.assert_close(emu(s, u, f), nxt, rtol=1e-12, atol=1e-12)
    # the normalisation statistics really are used (not the identity)
    assert not torch.allclose(emu.x_std, torch.ones_like(emu.x_std))
    assert not torch.allclose(emu.y_mean, torch.zeros_like(emu.y_mean))


def test_lander_local_inputs_written_out(make_emulator: MakeEmulator, inputs_of: InputsOf) -> None:
    """T'_x for the lander in the heading frame: heading removed from the orientation (z dropped) and
    from the velocity."""
    model = catalog.get("lander")
    emu = make_emulator(model, frame="heading").double()
    s, u, _ = inputs_of(model, 8, seed=5)
    assert u is not None  # the model has controls
    lay = model.layout
    x = emu.local_inputs(t64(s), t64(u), None).numpy()
    for i in range(s.shape[0]):
        q = s[i, lay.slice_of("orientation")]
        yaw = 2.0 * np.arctan2(q[3], q[0])  # the twist of q about z
        h = quaternion.from_axis_angle(np.array([0.0, 0.0, 1.0]), yaw)
        local_q = quaternion.multiply(quaternion.conjugate(h), q)
        assert abs(local_q[3]) < 1e-9  # pure tilt: nothing left about z
        expected = np.concatenate(
            [
                local_q[:3],
                rot_z(-yaw) @ s[i, lay.slice_of("velocity")],
                s[i, lay.slice_of("angular_velocity")],
                u[i],
            ]
        )
        np.testing.assert_allclose(x[i], expected, atol=1e-9)


def test_truck_local_inputs_written_out(make_emulator: MakeEmulator, inputs_of: InputsOf) -> None:
    model = catalog.get("truck")
    emu = make_emulator(model).double()
    s, u, _ = inputs_of(model, 8, seed=6)
    assert u is not None  # the model has controls
    x = emu.local_inputs(t64(s), t64(u), None).numpy()
    for i in range(s.shape[0]):
        psi = s[i, 2]
        expected = np.concatenate([rot_z(-psi)[:2, :2] @ s[i, 3:5], s[i, 5:6], u[i]])
        np.testing.assert_allclose(x[i], expected, atol=1e-9)


def test_pendulum_angles_are_encoded_as_sin_and_cos(make_emulator: MakeEmulator, inputs_of: InputsOf) -> None:
    model = catalog.get("pendulum-active")
    emu = make_emulator(model).double()
    s, u, _ = inputs_of(model, 8, seed=7)
    x = emu.local_inputs(t64(s), t64(u), None).numpy()
    np.testing.assert_allclose(x, np.concatenate([np.sin(s[:, :3]), np.cos(s[:, :3]), s[:, 3:], u], axis=1))


def test_pendulum_full_turn_gives_the_same_change(make_emulator: MakeEmulator, inputs_of: InputsOf) -> None:
    model = catalog.get("pendulum-active")
    emu = make_emulator(model).double()
    s, u, _ = inputs_of(model, 8, seed=8)
    turned = s.copy()
    turned[:, 1] += 2 * np.pi
    with torch.no_grad():
        d0 = (emu(t64(s), t64(u)) - t64(s)).numpy()
        d1 = (emu(t64(turned), t64(u)) - t64(turned)).numpy()
    np.testing.assert_allclose(d1, d0, atol=1e-9)


# ---------------------------------------------------------------------------- (c) targets invert finish
@pytest.mark.parametrize("name", NAMES)
def test_network_targets_through_finish_give_next_state(name: str, make_emulator: MakeEmulator) -> None:
    model = catalog.get(name)
    emu = make_emulator(model).double()
    ex = sampling.generate(model, 10, 64, seed=9, runs=32, progress=False)
    s, nxt = t64(ex.states), t64(ex.next_states)
    with torch.no_grad():
        back = emu.finish(s, emu.network_targets(s, nxt)).numpy()
    # exact up to float64 rounding; for the lander finish also renormalises the (unit) quaternion
    np.testing.assert_allclose(back, ex.next_states, rtol=1e-10, atol=1e-10)


def test_lander_finish_renormalises_quaternion(make_emulator: MakeEmulator, inputs_of: InputsOf) -> None:
    model = catalog.get("lander")
    emu = make_emulator(model)
    s, u, _ = inputs_of(model, 32, seed=10)
    q = predict(emu, s, u, None)[:, model.layout.slice_of("orientation")]
    np.testing.assert_allclose(np.linalg.norm(q, axis=1), 1.0, atol=1e-6)


# ---------------------------------------------------------------------------- (d) symmetries
def _lander_transform(
    model: PhysicalModel, s: np.ndarray, rotation: np.ndarray, quat: np.ndarray, shift: np.ndarray
) -> np.ndarray:
    lay = model.layout
    out = s.copy()
    out[:, lay.slice_of("position")] = s[:, lay.slice_of("position")] @ rotation.T + shift
    out[:, lay.slice_of("orientation")] = quaternion.multiply(
        np.broadcast_to(quat, (s.shape[0], 4)), s[:, lay.slice_of("orientation")]
    )
    out[:, lay.slice_of("velocity")] = s[:, lay.slice_of("velocity")] @ rotation.T
    return out  # the angular velocity is in the body frame: unchanged


def _assert_close_scaled(a: np.ndarray, b: np.ndarray, rel: float) -> None:
    scale = np.maximum(1.0, np.abs(b).max(axis=0))
    assert np.all(np.abs(a - b) <= rel * scale), np.abs(a - b).max(axis=0)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_lander_is_equivariant_under_translation_and_yaw(
    seed: int, make_emulator: MakeEmulator, inputs_of: InputsOf
) -> None:
    model = catalog.get("lander")
    emu = make_emulator(model, seed=seed)
    s, u, _ = inputs_of(model, 32, seed=seed)
    rng = np.random.default_rng(100 + seed)
    shift, angle = rng.uniform(-10.0, 10.0, 3), rng.uniform(-np.pi, np.pi)
    q_z = quaternion.from_axis_angle(np.array([0.0, 0.0, 1.0]), angle)
    moved = _lander_transform(model, s, rot_z(angle), q_z, shift)
    expected = _lander_transform(model, predict(emu, s, u, None), rot_z(angle), q_z, shift)
    _assert_close_scaled(predict(emu, moved, u, None), expected, 1e-5)


def test_lander_is_not_equivariant_under_tilt(make_emulator: MakeEmulator, inputs_of: InputsOf) -> None:
    """Gravity points down: turning the whole scene about a horizontal axis is not a symmetry."""
    model = catalog.get("lander")
    emu = make_emulator(model)
    s, u, _ = inputs_of(model, 32, seed=11)
    angle = 0.7
    c, sn = np.cos(angle), np.sin(angle)
    rot_x = np.array([[1.0, 0.0, 0.0], [0.0, c, -sn], [0.0, sn, c]])
    q_x = quaternion.from_axis_angle(np.array([1.0, 0.0, 0.0]), angle)
    moved = _lander_transform(model, s, rot_x, q_x, np.zeros(3))
    expected = _lander_transform(model, predict(emu, s, u, None), rot_x, q_x, np.zeros(3))
    assert np.abs(predict(emu, moved, u, None) - expected).max() > 1e-3


def test_lander_physics_shares_the_emulator_symmetry() -> None:
    """The symmetry the emulator builds in is true of MuJoCo's lander (and the tilt one is not)."""
    model = catalog.get("lander")
    rng = np.random.default_rng(12)
    s = model.initial_states(rng, 4)
    u = model.typical_controls(rng, 4, np.zeros(1))[:, 0]
    angle, shift = 1.1, np.array([3.0, -4.0, 2.0])
    q_z = quaternion.from_axis_angle(np.array([0.0, 0.0, 1.0]), angle)
    moved = _lander_transform(model, s, rot_z(angle), q_z, shift)
    expected = _lander_transform(model, model.step_held(s, u, None, 20), rot_z(angle), q_z, shift)
    np.testing.assert_allclose(model.step_held(moved, u, None, 20), expected, atol=1e-8)


def _truck_transform(s: np.ndarray, angle: float, shift: np.ndarray) -> np.ndarray:
    out = s.copy()
    r = rot_z(angle)[:2, :2]
    out[:, 0:2] = s[:, 0:2] @ r.T + shift
    out[:, 2] = s[:, 2] + angle
    out[:, 3:5] = s[:, 3:5] @ r.T
    return out  # the yaw rate is unchanged


@pytest.mark.parametrize("seed", [0, 1])
def test_truck_is_equivariant_under_translation_and_yaw(
    seed: int, make_emulator: MakeEmulator, inputs_of: InputsOf
) -> None:
    model = catalog.get("truck")
    emu = make_emulator(model, seed=seed)
    s, u, _ = inputs_of(model, 32, seed=seed)
    rng = np.random.default_rng(200 + seed)
    shift, angle = rng.uniform(-20.0, 20.0, 2), rng.uniform(-np.pi, np.pi)
    expected = _truck_transform(predict(emu, s, u, None), angle, shift)
    _assert_close_scaled(predict(emu, _truck_transform(s, angle, shift), u, None), expected, 1e-5)


def test_pendulum_emulator_has_no_frame(make_emulator: MakeEmulator) -> None:
    emu = make_emulator(catalog.get("pendulum-force"))
    assert emu.frame.rotate is False
    assert emu.frame.translate == ()


# ---------------------------------------------------------------------------- (e) inputs
def expected_input_size(model: PhysicalModel) -> int:
    """Network inputs from the layout rules of the module docstring (App. F.1)."""
    fr = training.frame_config(model)
    size = 0
    for g in model.layout:
        if g.kind == "position":
            size += g.size - sum(fr.translate)  # translated axes are always 0: dropped
        elif g.kind == "heading":
            size += 0 if fr.rotate else 1  # the heading defines the frame: dropped
        elif g.kind == "quaternion":
            size += 3 if fr.rotate else 4  # the z component is 0 once the heading is removed
        elif g.kind == "angle":
            size += 2 * g.size  # sin and cos
        else:
            size += g.size
    return size + model.num_controls + model.num_forces


@pytest.mark.parametrize(
    ("name", "size"),
    [
        ("lander", 3 + 3 + 3 + 4),  # tilt quaternion without z, velocity, angular velocity, controls
        ("truck", 2 + 1 + 2),  # velocity, yaw rate, controls
        ("pendulum-passive", 6 + 3),  # sin and cos of 3 angles, 3 rates
        ("pendulum-active", 6 + 3 + 3),
        ("pendulum-force", 6 + 3 + 3 + 3),
    ],
)
def test_constant_inputs_are_dropped(name: str, size: int) -> None:
    model = catalog.get(name)
    emu = training.build_emulator(model, TrainConfig(hidden=(16,)))
    assert emu.input_size == size == expected_input_size(model)
    arch = emu.architecture()
    assert arch["input_size"] == size
    groups = arch["input_groups"]
    assert isinstance(groups, list)
    assert sum(w for _, w in groups) == size
    assert arch["output_size"] == model.state_size


@pytest.mark.parametrize("name", NAMES)
def test_local_inputs_have_input_size_columns(name: str, inputs_of: InputsOf) -> None:
    model = catalog.get(name)
    emu = training.build_emulator(model, TrainConfig(hidden=(16,)))
    s, u, f = inputs_of(model, 5)
    with torch.no_grad():
        assert emu.local_inputs(t32(s), t32(u), t32(f)).shape == (5, emu.input_size)


# ---------------------------------------------------------------------------- normalisation and core
def test_group_normalization_shares_statistics_within_a_group() -> None:
    model = catalog.get("lander")
    emu = training.build_emulator(model, TrainConfig(hidden=(16,)))
    x = torch.randn(200, emu.input_size) * torch.linspace(0.5, 3.0, emu.input_size) + 2.0
    y = torch.randn(200, model.state_size)
    emu.set_normalization(x, y, "group")
    at = 0
    for _name, width in emu.input_groups:
        block = x[:, at : at + width].double()
        torch.testing.assert_close(emu.x_mean[at : at + width], block.mean().float().expand(width))
        torch.testing.assert_close(emu.x_std[at : at + width], block.std().float().expand(width))
        at += width


def test_variable_normalization_standardises_every_column() -> None:
    model = catalog.get("truck")
    emu = training.build_emulator(model, TrainConfig(hidden=(16,)))
    x = torch.randn(500, emu.input_size) * 4.0 + 1.0
    emu.set_normalization(x, torch.randn(500, model.state_size), "variable")
    z = emu.normalize_inputs(x)
    torch.testing.assert_close(z.mean(dim=0), torch.zeros(emu.input_size), atol=1e-5, rtol=0)
    torch.testing.assert_close(z.std(dim=0), torch.ones(emu.input_size), atol=1e-5, rtol=0)


def test_constant_variable_is_left_unscaled() -> None:
    model = catalog.get("truck")
    emu = training.build_emulator(model, TrainConfig(hidden=(16,)))
    x = torch.randn(100, emu.input_size)
    x[:, 0] = 3.0
    emu.set_normalization(x, torch.randn(100, model.state_size), "variable")
    assert float(emu.x_std[0]) == 1.0
    assert torch.isfinite(emu.normalize_inputs(x)).all()


def test_bad_normalization_mode_raises() -> None:
    model = catalog.get("truck")
    emu = training.build_emulator(model, TrainConfig(hidden=(16,)))
    with pytest.raises(ValueError, match="normalization"):
        emu.set_normalization(torch.randn(10, emu.input_size), torch.randn(10, 6), "global")


def test_make_core_layers_and_bad_activation() -> None:
    core = make_core(5, 3, (8, 4), "sigmoid")
    assert [type(m).__name__ for m in core] == ["Linear", "Sigmoid", "Linear", "Sigmoid", "Linear"]
    assert core(torch.zeros(2, 5)).shape == (2, 3)
    with pytest.raises(ValueError, match="activation"):
        make_core(5, 3, (8,), "swish")


def test_bilinear_tables_give_the_outer_and_the_hamilton_product() -> None:
    """The export's quaternion arithmetic without reshapes: (q E₁)·(p E₂) is q pᵀ flattened, and that
    times the product table is q ⊗ p."""
    from neuroanimator.emulator.structured import _pair_expansions, _product_table

    g = torch.Generator().manual_seed(4)
    q, p = torch.randn(32, 4, generator=g), torch.randn(32, 4, generator=g)
    e1, e2 = _pair_expansions()
    outer = (q @ e1) * (p @ e2)
    torch.testing.assert_close(outer, (q.unsqueeze(2) * p.unsqueeze(1)).reshape(-1, 16))
    torch.testing.assert_close(outer @ _product_table(), quaternion.multiply(q, p))


def test_the_body_frame_step_is_a_small_graph(
    make_emulator: Callable[..., StructuredEmulator], tmp_path: Path
) -> None:
    """ONNX Runtime's cost per node sets the one-client speed: the lander's body-frame step (one hidden
    layer here), as ONNX Runtime optimises it, stays within 36 nodes (11 more before the quaternion
    arithmetic went without reshapes)."""
    import onnx
    import onnxruntime as ort

    from neuroanimator.export.onnx import to_onnx
    from neuroanimator.export.runtime import session_options

    options = session_options()
    options.optimized_model_filepath = str(tmp_path / "optimised.onnx")
    ort.InferenceSession(
        to_onnx(make_emulator(catalog.get("lander"))), options, providers=["CPUExecutionProvider"]
    )
    nodes = [n.op_type for n in onnx.load(str(tmp_path / "optimised.onnx")).graph.node]
    assert len(nodes) <= 36, nodes
