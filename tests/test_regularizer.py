"""The spring regulariser of thesis 6.1.3 (neuroanimator.emulator.regularizer) on the dolphin's body."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from neuroanimator import catalog
from neuroanimator.catalog import dolphin as body
from neuroanimator.core.model_spec import HingeAlignment, SpringRegularizer
from neuroanimator.core.state import StateGroup, StateLayout
from neuroanimator.emulator.hierarchy import HierarchicalEmulator
from neuroanimator.emulator.regularizer import SpringRegularization, deformation_energy, regularization
from neuroanimator.export.onnx import to_onnx
from neuroanimator.export.runtime import OnnxEmulator
from neuroanimator.sim import sampling
from neuroanimator.sim.model import PhysicalModel


@pytest.fixture(scope="module")
def dolphin() -> PhysicalModel:
    return catalog.get("dolphin")


@pytest.fixture(scope="module")
def examples(dolphin: PhysicalModel) -> sampling.Examples:
    return sampling.generate(dolphin, 50, 32, seed=5, progress=False)


def two_points(steps: int = 1, muscles: list[tuple[int, int, float]] | None = None) -> SpringRegularization:
    layout = StateLayout(
        tuple(
            StateGroup(name=f"{p}.{q}", kind="scalar", size=3, source="qpos", address=0)
            for q in ("pos", "vel")
            for p in "ab"
        )
    )
    spec = SpringRegularizer(
        steps=steps, dt=0.1, stiffness=4.0, damping=0.5, points=[("a.pos", "a.vel"), ("b.pos", "b.vel")],
        masses=[1.0, 2.0], springs=[(0, 1, 1.0)], muscles=muscles or [],
    )  # fmt: skip
    return SpringRegularization(layout, spec, num_controls=1).double()


def test_one_euler_step_matches_a_hand_computation() -> None:
    reg = two_points()
    # a at the origin moving +x at 1 m/s; b at (1.5, 0, 0) at rest: stretched 0.5, closing at 1 m/s
    state = torch.tensor([[0.0, 0, 0, 1.5, 0, 0, 1.0, 0, 0, 0, 0, 0]], dtype=torch.float64)
    tension = 4.0 * 0.5 + 0.5 * (0.0 - 1.0)  # k·(l − l_r) + c·l̇ = 1.5 N, pulling the ends together
    va, vb = 1.0 + 0.1 * tension / 1.0, 0.0 - 0.1 * tension / 2.0
    expected = [0.1 * va, 0, 0, 1.5 + 0.1 * vb, 0, 0, va, 0, 0, vb, 0, 0]
    got = reg(state, torch.zeros(1, 1, dtype=torch.float64))
    np.testing.assert_allclose(got[0].numpy(), expected, atol=1e-12)


def test_a_muscle_moves_its_springs_rest_length() -> None:
    reg = two_points(muscles=[(0, 0, 0.5)])  # fully contracted: rest length 0.5
    state = torch.tensor([[0.0, 0, 0, 1.0, 0, 0] + [0.0] * 6], dtype=torch.float64)
    relaxed = reg(state, torch.zeros(1, 1, dtype=torch.float64))
    torch.testing.assert_close(relaxed, state)  # at rest length, at rest: nothing moves
    half = reg(state, torch.full((1, 1), 0.5, dtype=torch.float64))
    # rest 0.75: the spring pulls a towards +x with 4·0.25 = 1 N
    assert half[0, 6].item() == pytest.approx(0.1 * 1.0) and half[0, 9].item() == pytest.approx(-0.1 * 0.5)


def test_the_body_at_rest_is_left_alone(dolphin: PhysicalModel) -> None:
    assert dolphin.spec.regularizer is not None and dolphin.spec.regularizer.steps == 2  # on by default
    assert dolphin.spec.regularizer.hinge_pull > 0 and len(dolphin.spec.regularizer.hinges) == len(
        body.PLATES
    )
    assert regularization(dolphin.layout, dolphin.spec.regularizer, dolphin.num_controls, steps=0) is None
    reg = regularization(dolphin.layout, dolphin.spec.regularizer, dolphin.num_controls, steps=5)
    assert reg is not None and reg.steps == 5
    rest = torch.from_numpy(dolphin.rest_state()[None, :]).float()
    torch.testing.assert_close(reg(rest, torch.zeros(1, 6)), rest, atol=5e-6, rtol=0)
    assert reg.deformation_energy(rest).item() == pytest.approx(0.0, abs=1e-10)


def test_it_reduces_the_deformation_and_keeps_the_momentum(
    dolphin: PhysicalModel, examples: sampling.Examples
) -> None:
    assert dolphin.spec.regularizer is not None
    spec = dolphin.spec.regularizer.model_copy(update={"steps": 5})
    reg = SpringRegularization(dolphin.layout, spec, dolphin.num_controls).double()
    states = torch.from_numpy(examples.next_states)
    controls = torch.from_numpy(examples.controls)
    # an emulator's drift: every node off by a few centimetres
    g = torch.Generator().manual_seed(0)
    noisy = states.clone()
    noisy[:, body.NODE_POS] += 0.03 * torch.randn(
        noisy[:, body.NODE_POS].shape, generator=g, dtype=torch.float64
    )
    out = reg(noisy, controls)
    before, after = reg.deformation_energy(noisy), reg.deformation_energy(out)
    assert bool((after < before).all()), f"E_d before {before[:4]}, after {after[:4]}"
    # the numpy E_d of the benchmarks is the same quantity
    np.testing.assert_allclose(
        deformation_energy(spec, body.node_positions(out.numpy())), after.numpy(), rtol=1e-6
    )
    # internal forces only: the body's momentum does not change
    m = torch.tensor(body.node_masses())
    momentum = lambda s: (s[:, body.NODE_VEL].reshape(-1, 23, 3) * m[None, :, None]).sum(1)  # noqa: E731
    torch.testing.assert_close(momentum(out), momentum(noisy), atol=1e-6, rtol=0)
    # the plates' columns move only by their hinges' pull towards their strips
    others = torch.ones(dolphin.state_size, dtype=torch.bool)
    others[body.NODE_POS] = others[body.NODE_VEL] = False
    unpulled = SpringRegularization(
        dolphin.layout, spec.model_copy(update={"hinge_pull": 0.0}), dolphin.num_controls
    ).double()
    torch.testing.assert_close(unpulled(noisy, controls)[:, others], noisy[:, others])
    assert (out[:, others] - noisy[:, others]).abs().max() > 1e-4


def _plate(dolphin: PhysicalModel, name: str) -> tuple[int, int]:
    return dolphin.layout.slice_of(f"{name}.pitch").start, dolphin.layout.slice_of(f"{name}.rate").start


def test_a_plate_is_pulled_towards_its_strip(dolphin: PhysicalModel) -> None:
    """A plate's pitch moves ``hinge_pull`` of the way to the turn of its strip (its node to the far
    node its pitch tendon holds) about the lateral axis; its rate likewise to the strip's rate."""
    assert dolphin.spec.regularizer is not None
    spec = dolphin.spec.regularizer.model_copy(
        update={"steps": 1, "hinge_pull": 0.5, "stiffness": 1e-9, "damping": 0.0}
    )
    reg = SpringRegularization(dolphin.layout, spec, dolphin.num_controls).double()
    plate = body.PLATES[1]  # strip 2, top left
    anchor, far = plate.anchor, plate.align[0][0]
    pitch, rate = _plate(dolphin, plate.name)
    state = dolphin.rest_state().copy()
    # turn the far node about the anchor by 0.2 rad about +y (x towards −z), moving at 0.1 rad/s
    q0 = body.rest_positions()[far] - body.rest_positions()[anchor]
    turn, spin = 0.2, 0.1
    rot = np.array([[np.cos(turn), 0, np.sin(turn)], [0, 1, 0], [-np.sin(turn), 0, np.cos(turn)]])
    q = rot @ q0
    state[body.NODE_POS.start + 3 * far : body.NODE_POS.start + 3 * far + 3] = (
        body.rest_positions()[anchor] + q
    )
    state[body.NODE_VEL.start + 3 * far : body.NODE_VEL.start + 3 * far + 3] = spin * np.cross(
        [0.0, 1.0, 0.0], q
    )
    state[pitch], state[rate] = -0.1, 0.3
    out = reg(torch.from_numpy(state[None]), torch.zeros(1, 6, dtype=torch.float64))[0].numpy()
    assert out[pitch] == pytest.approx(-0.1 + 0.5 * (turn + 0.1), abs=1e-3)  # the far node moved a step
    assert out[rate] == pytest.approx(0.3 + 0.5 * (spin - 0.3), abs=1e-3)
    # a body that looped once: the pitch is pulled the near way round, not by 2π
    state[pitch] = 2 * np.pi + 0.1
    out = reg(torch.from_numpy(state[None]), torch.zeros(1, 6, dtype=torch.float64))[0].numpy()
    assert out[pitch] == pytest.approx(2 * np.pi + 0.1 + 0.5 * (turn - 0.1), abs=1e-3)
    # every other plate sits on an unturned strip and is left where it is
    others = [_plate(dolphin, p.name)[0] for p in body.PLATES if p.align[0][0] != far and p.anchor != far]
    np.testing.assert_allclose(out[others], 0.0, atol=1e-7)


def _plain_steps(spec: SpringRegularizer, x: np.ndarray, v: np.ndarray, activation: np.ndarray) -> np.ndarray:
    """Symplectic Euler of the springs written spring by spring: x, v (P, 3), activation (U,) -> (2P, 3)."""
    x, v = x.copy(), v.copy()
    rest = np.array([s[2] for s in spec.springs])
    for spring, control, contracted in spec.muscles:
        rest[spring] += activation[control] * (contracted - spec.springs[spring][2])
    mass = np.asarray(spec.masses)
    for _ in range(spec.steps):
        force = np.zeros_like(x)
        for i, (a, b, _) in enumerate(spec.springs):
            r, rate = x[b] - x[a], v[b] - v[a]
            length = np.linalg.norm(r)
            tension = spec.stiffness * (length - rest[i]) + spec.damping * (rate @ r) / length
            force[a] += tension * r / length
            force[b] -= tension * r / length
        v = v + spec.dt * force / mass[:, None]
        x = x + spec.dt * v
    return np.concatenate([x, v])


def test_the_steps_equal_the_springs_one_by_one(dolphin: PhysicalModel, examples: sampling.Examples) -> None:
    """The fused form (``SpringRegularization.features``: the k·r part folded into the update, the axes
    summed by a product) is the textbook step, spring by spring, on a deformed body with muscles on."""
    assert dolphin.spec.regularizer is not None
    spec = dolphin.spec.regularizer.model_copy(update={"steps": 4})
    reg = SpringRegularization(dolphin.layout, spec, dolphin.num_controls).double()
    g = np.random.default_rng(2)
    states = examples.next_states[:5].copy()
    states[:, body.NODE_POS] += 0.05 * g.standard_normal(states[:, body.NODE_POS].shape)
    states[:, body.NODE_VEL] += 0.2 * g.standard_normal(states[:, body.NODE_VEL].shape)
    controls = g.uniform(0.0, 1.0, (5, dolphin.num_controls))
    with torch.no_grad():
        got = reg(torch.from_numpy(states), torch.from_numpy(controls)).numpy()
    # to float32's precision: the module holds its constants (lengths, δt/m) as the exported graph does
    for s, u, out in zip(states, controls, got, strict=True):
        expected = _plain_steps(spec, s[body.NODE_POS].reshape(-1, 3), s[body.NODE_VEL].reshape(-1, 3), u)
        np.testing.assert_allclose(out[body.NODE_POS].reshape(-1, 3), expected[:23], rtol=1e-5, atol=1e-7)
        np.testing.assert_allclose(out[body.NODE_VEL].reshape(-1, 3), expected[23:], rtol=1e-5, atol=1e-6)
        assert np.abs(out - s).max() > 1e-3


def test_the_onnx_graph_includes_the_regulariser(dolphin: PhysicalModel, examples: sampling.Examples) -> None:
    torch.manual_seed(0)
    emu = HierarchicalEmulator(dolphin.layout, dolphin.num_controls, dolphin.spec.parts, (8,), (8,)).eval()
    s, u = examples.states.astype(np.float32), examples.controls.astype(np.float32)
    with torch.no_grad():
        plain = emu(torch.from_numpy(s), torch.from_numpy(u)).numpy()
        emu.regularizer = regularization(
            dolphin.layout, dolphin.spec.regularizer, dolphin.num_controls, steps=5
        )
        expected = emu(torch.from_numpy(s), torch.from_numpy(u)).numpy()
    assert np.abs(expected - plain).max() > 1e-4  # the regulariser does move the nodes
    np.testing.assert_allclose(OnnxEmulator(to_onnx(emu)).step(s, u), expected, atol=3e-5, rtol=1e-4)


def test_a_hinge_that_cannot_follow_a_line_is_refused() -> None:
    with pytest.raises(ValueError, match="unit vector"):
        HingeAlignment(angle="a", rate="w", anchor=0, target=1, axis=(0, 2, 0), rest=(1, 0, 0))
    with pytest.raises(ValueError, match="across its axis"):
        HingeAlignment(angle="a", rate="w", anchor=0, target=1, axis=(0, 1, 0), rest=(0, 0.5, 0))
    with pytest.raises(ValueError, match="not below 2"):
        SpringRegularizer(
            dt=0.01, stiffness=1, damping=0, points=[("a", "b"), ("c", "d")], masses=[1, 1],
            springs=[(0, 1, 1.0)],
            hinges=[HingeAlignment(angle="a", rate="w", anchor=0, target=2, axis=(0, 1, 0), rest=(1, 0, 0))],
        )  # fmt: skip


def test_a_spec_with_unknown_points_is_refused() -> None:
    with pytest.raises(ValueError, match="two different points"):
        SpringRegularizer(
            dt=0.01,
            stiffness=1,
            damping=0,
            points=[("a", "b"), ("c", "d")],
            masses=[1, 1],
            springs=[(0, 2, 1.0)],
        )
    with pytest.raises(ValueError, match="masses"):
        SpringRegularizer(
            dt=0.01,
            stiffness=1,
            damping=0,
            points=[("a", "b"), ("c", "d")],
            masses=[1],
            springs=[(0, 1, 1.0)],
        )
