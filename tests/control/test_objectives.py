"""The objective J and its terms: values, invariances, and gradients against finite differences."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch

from neuroanimator.artifacts import registry
from neuroanimator.catalog.lander import LABELS as LANDER_LABELS
from neuroanimator.control.objectives import Objective, StateDistance, control_scale
from neuroanimator.control.validation import validate_job
from neuroanimator.core.state import LayoutGroup
from neuroanimator.goals.spec import JobSpec

ARTIFACTS = Path(__file__).resolve().parents[2] / "artifacts"


def lander_layout() -> list[LayoutGroup]:
    return registry.read_manifest(registry.resolve(ARTIFACTS, "lander")).layout


ALL_TERMS = [
    {"term": "final_state", "weight": 0.7},
    {"term": "control_effort", "weight": 0.1},
    {"term": "control_smoothness", "weight": 0.3},
    {"term": "final_velocity", "weight": 0.5},
    {"term": "forward_distance", "weight": 0.2, "direction": [1.0, 1.0, 0.0]},
    {"term": "stay_within_bounds", "weight": 2.0, "variable": "position.z", "low": 0.5, "high": 1.0},
    {
        "term": "path_target",
        "weight": 0.4,
        "waypoints": [{"step": 2, "target": [0.0] * 3 + [1.0] + [0.0] * 9}],
    },
    {"term": "success_margin", "weight": 0.05},
]


@pytest.fixture
def lander_spec() -> JobSpec:
    return validate_job({"task": "lander-landing", "horizon": 4, "terms": ALL_TERMS}, ARTIFACTS)


def random_trajectory(rng: np.random.Generator, batch: int = 2) -> tuple[torch.Tensor, torch.Tensor]:
    states = rng.normal(size=(batch, 5, 13))
    q = states[..., 3:7]
    states[..., 3:7] = q / np.linalg.norm(q, axis=-1, keepdims=True)
    controls = rng.normal(size=(batch, 4, 4))
    return torch.from_numpy(states), torch.from_numpy(controls)


def test_every_term_has_gradients_that_match_finite_differences(lander_spec: JobSpec) -> None:
    objective = Objective(lander_spec, lander_layout(), control_scale(np.array([[0, 32.4]] + [[-1, 1]] * 3)))
    states, controls = random_trajectory(np.random.default_rng(1), batch=1)
    s = states.clone().requires_grad_(True)
    u = controls.clone().requires_grad_(True)
    for name, part in objective.parts(s, u).items():
        gs, gu = torch.autograd.grad(part.sum(), (s, u), allow_unused=True, retain_graph=True)
        for x, g, label in ((states, gs, "states"), (controls, gu, "controls")):
            g = torch.zeros_like(x) if g is None else g
            flat = x.reshape(-1)
            rng = np.random.default_rng(len(name))
            for i in rng.choice(flat.numel(), size=12, replace=False):
                h = 1e-6
                xp, xm = flat.clone(), flat.clone()
                xp[i] += h
                xm[i] -= h
                args_p = (
                    (xp.reshape(x.shape), controls) if label == "states" else (states, xp.reshape(x.shape))
                )
                args_m = (
                    (xm.reshape(x.shape), controls) if label == "states" else (states, xm.reshape(x.shape))
                )
                fd = (objective.parts(*args_p)[name] - objective.parts(*args_m)[name]).sum() / (2 * h)
                assert float(g.reshape(-1)[i]) == pytest.approx(float(fd), rel=1e-5, abs=1e-7), (
                    name,
                    label,
                    i,
                )


def test_objective_is_the_sum_of_its_parts(lander_spec: JobSpec) -> None:
    objective = Objective(lander_spec, lander_layout(), np.ones(4))
    states, controls = random_trajectory(np.random.default_rng(2))
    total = objective(states, controls)
    assert total.shape == (2,)
    torch.testing.assert_close(total, sum(objective.parts(states, controls).values()))


def test_quaternion_error_is_sign_invariant_and_small_angle_consistent() -> None:
    dist = StateDistance(lander_layout(), 13)
    target = torch.tensor([0.0] * 3 + [1.0, 0, 0, 0] + [0.0] * 6, dtype=torch.float64)
    weights = torch.ones(13, dtype=torch.float64)
    theta = 0.2
    q = [math.cos(theta / 2), math.sin(theta / 2), 0.0, 0.0]
    s = target.clone()
    s[3:7] = torch.tensor(q, dtype=torch.float64)
    s_neg = s.clone()
    s_neg[3:7] = -s[3:7]  # the same orientation
    assert float(dist(s, target, weights)) == pytest.approx(float(dist(s_neg, target, weights)))
    # 1 - <q, q_d>^2 = sin^2(θ/2): the orientation error, not the component difference
    assert float(dist(s, target, weights)) == pytest.approx(math.sin(theta / 2) ** 2)
    # the raw component difference of -q would be ~4: the sign-invariant error is not
    assert float(((s_neg[3:7] - target[3:7]) ** 2).sum()) > 3.9


def test_angle_error_wraps_a_full_turn() -> None:
    layout = [
        LayoutGroup(name="angles", kind="angle", size=1, source="qpos", address=0, offset=0),
        LayoutGroup(name="rates", kind="scalar", size=1, source="qvel", address=0, offset=1),
    ]
    dist = StateDistance(layout, 2)
    w = torch.ones(2, dtype=torch.float64)
    target = torch.tensor([0.5, 0.0], dtype=torch.float64)
    near = torch.tensor([0.6, 0.0], dtype=torch.float64)
    turned = torch.tensor([0.6 + 2 * math.pi, 0.0], dtype=torch.float64)
    assert float(dist(near, target, w)) == pytest.approx(float(dist(turned, target, w)))
    assert float(dist(near, target, w)) == pytest.approx(0.01, rel=1e-3)  # ≈ Δ² near the goal


def test_eq_5_3_effort_and_final_state(lander_spec: JobSpec) -> None:
    spec = lander_spec.model_copy(update={"terms": [], "mu_u": 2.0, "mu_s": 3.0})
    scale = np.array([32.4, 1.0, 1.0, 1.0])
    objective = Objective(spec, lander_layout(), scale)
    states, controls = random_trajectory(np.random.default_rng(3), batch=1)
    states[..., -1, 3:7] = torch.tensor([1.0, 0, 0, 0], dtype=torch.float64)  # on the target orientation
    u = controls[0].numpy() / scale
    e = (states[0, -1].numpy() - np.asarray(spec.target_state)) * np.asarray(spec.state_weights)
    e[3:7] = 0.0
    expected = 2.0 / 2 * (u**2).sum() + 3.0 / 2 * (e**2).sum()
    assert float(objective(states, controls)[0]) == pytest.approx(expected, rel=1e-10)


def test_term_behaviour(lander_spec: JobSpec) -> None:
    objective = Objective(lander_spec, lander_layout(), np.ones(4))
    states = torch.zeros(1, 5, 13, dtype=torch.float64)
    states[..., 3] = 1.0
    controls = torch.zeros(1, 4, 4, dtype=torch.float64)
    parts = objective.parts(states, controls)
    # z = 0 is below the soft box [0.5, 1]: penalised on the 4 controlled states
    assert float(parts["5:stay_within_bounds"]) == pytest.approx(2.0 * 0.5 * 4 * 0.25)
    moved = states.clone()
    moved[0, -1, 0] = 3.0  # 3 m along +x, direction (1, 1, 0)/√2
    assert float(objective.parts(moved, controls)["4:forward_distance"]) == pytest.approx(
        -0.2 * 3 / math.sqrt(2)
    )
    assert LANDER_LABELS[2] == "position.z"


def test_success_margin_is_zero_with_room_to_spare_and_grows_past_each_bound(lander_spec: JobSpec) -> None:
    """The lander's checks: within 1 m of the pad, tilt ≤ 10°, vz in [-1, 0], |v_xy| ≤ 0.5."""
    objective = Objective(lander_spec, lander_layout(), np.ones(4))
    (i,) = [k for k, t in enumerate(lander_spec.terms) if t.term == "success_margin"]
    name = f"{i}:success_margin"
    controls = torch.zeros(1, 4, 4, dtype=torch.float64)
    landed = torch.zeros(1, 5, 13, dtype=torch.float64)
    landed[..., 3] = 1.0
    landed[..., -1, 9] = -0.5  # the target's small downward speed
    assert float(objective.parts(landed, controls)[name]) == 0.0

    def penalty(index: int, value: float) -> float:
        s = landed.clone()
        s[0, -1, index] = value
        if 3 <= index < 7:
            s[0, -1, 3:7] = s[0, -1, 3:7] / s[0, -1, 3:7].norm()
        return float(objective.parts(s, controls)[name])

    assert penalty(0, 0.5) == 0.0 < penalty(0, 0.9) < penalty(0, 1.5)  # 1 m from the pad: r = 0.81
    tilt = math.sin(math.radians(15) / 2)  # 15° about x: past the 10° bound
    assert penalty(4, tilt) > 0.05 * (1.5**2 * 1.0 - 0.5) ** 2 * 0.9
    assert penalty(9, -0.9) > 0.0 and penalty(9, 0.2) > penalty(9, -0.1) > 0.0
    assert penalty(7, 0.3) == 0.0 < penalty(7, 0.6)


def test_residuals_square_to_the_objective_less_its_linear_term(lander_spec: JobSpec) -> None:
    """½‖r‖² is J without ``forward_distance`` (the one linear term), for every other term."""
    objective = Objective(lander_spec, lander_layout(), control_scale(np.array([[0, 32.4]] + [[-1, 1]] * 3)))
    states, controls = random_trajectory(np.random.default_rng(4), batch=3)
    states[..., -1, 3:7] = -states[..., -1, 3:7]  # a quaternion's sign changes nothing
    r = objective.residuals(states, controls)
    parts = objective.parts(states, controls)
    linear = sum(v for k, v in parts.items() if k.endswith("forward_distance"))
    torch.testing.assert_close(0.5 * (r * r).sum(-1), objective(states, controls) - linear)


def test_residuals_of_angles_wrap_like_the_distance() -> None:
    layout = [LayoutGroup(name="angles", kind="angle", size=1, source="qpos", address=0, offset=0)]
    dist = StateDistance(layout, 1)
    w = torch.tensor([2.0], dtype=torch.float64)
    target = torch.tensor([0.5], dtype=torch.float64)
    for x in (0.6, 0.6 + 2 * math.pi, 0.5 + math.pi, -2.0):
        s = torch.tensor([x], dtype=torch.float64)
        r = dist.residuals(s, target, w)
        assert float((r * r).sum()) == pytest.approx(float(dist(s, target, w)))
