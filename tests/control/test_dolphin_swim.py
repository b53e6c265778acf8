"""The dolphin-swim task: a hierarchical emulator under BPTT (thesis 6.3), its mechanics on a tiny
trained dolphin, the swim itself on the committed emulator."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from neuroanimator import catalog
from neuroanimator.artifacts import registry
from neuroanimator.artifacts import store as artifacts
from neuroanimator.catalog import dolphin as body
from neuroanimator.catalog.tasks import TASKS
from neuroanimator.control.bptt import ControlProblem, FrozenStep, GlobalStep
from neuroanimator.control.job import load_problem, run_job
from neuroanimator.control.validation import validate_job
from neuroanimator.training.hierarchy import train_hierarchy
from tests.test_hierarchy import TINY


@pytest.fixture(scope="module")
def root(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("dolphin-artifacts")
    model = catalog.get("dolphin")
    artifacts.save(out, model, train_hierarchy(model, TINY))
    return out


def test_the_task_has_60_control_variables_in_0_1() -> None:
    task = TASKS["dolphin-swim"]
    assert task.control_variables(6) == 60
    model = catalog.get("dolphin")
    np.testing.assert_allclose(task.initial_state, model.rest_state())
    assert [(lo, hi) for lo, hi in model.control_range] == [(0.0, 1.0)] * 6
    # the forward-distance term weighs each node's x by its mass: the centre of mass
    (term,) = task.terms
    direction = np.asarray(term["direction"])
    np.testing.assert_allclose(direction / direction.sum(), body.node_masses() / body.node_masses().sum())


def test_the_swim_goes_through_the_global_network_alone(root: Path) -> None:
    """The centre of mass is a weighted sum of the segments' centres: the objective depends on the
    frames only, so BPTT runs the global network, and its objective is the frames' own."""
    spec = validate_job({"task": "dolphin-swim", "horizon": 8}, root)
    assert spec.model == "dolphin" and spec.horizon == 8 and spec.success == []
    problem, manifest, _ = load_problem(spec, root)
    assert isinstance(problem.step, FrozenStep) and manifest.emulator.parts
    assert isinstance(problem.gradient_step, GlobalStep) and problem.networks == "global"
    z = problem.initial_points()
    j, grad, states, held = problem.value_and_grad(z)
    assert np.isfinite(j) and grad.shape == z.shape and np.abs(grad).max() > 0
    assert states.shape == (9, manifest.state_size)
    # each step's frames are the global network's prediction from the last step's frames
    emu = problem.step.emu
    s = torch.as_tensor(states, dtype=torch.float32)
    # the full step runs stacked (as the ONNX graph does): the same map as the hierarchy's own
    with torch.no_grad():
        u = torch.as_tensor(held, dtype=torch.float32)
        torch.testing.assert_close(problem.step(s[:-1], u), emu(s[:-1], u), atol=2e-5, rtol=1e-4)
    predicted = emu.global_step(s[:-1], torch.as_tensor(held, dtype=torch.float32))
    # (the fluke shares segment 5's up axis: those two predictions are averaged)
    shared = np.zeros(predicted.shape[1], dtype=bool)
    for k in (4, 5):
        shared[18 * k + 6 : 18 * k + 9] = shared[18 * k + 15 : 18 * k + 18] = True
    got = emu.frames_of(s[1:]).numpy()
    np.testing.assert_allclose(got[:, ~shared], predicted.numpy()[:, ~shared], atol=2e-4)
    mean = 0.5 * (predicted[:, 4 * 18 + 6 : 4 * 18 + 9] + predicted[:, 5 * 18 + 6 : 5 * 18 + 9]).numpy()
    np.testing.assert_allclose(got[:, 4 * 18 + 6 : 4 * 18 + 9], mean, atol=2e-4)
    # and the centre of mass of the states it carries is the segments' centres weighed by mass
    mass = body.node_masses()
    com = body.centre_of_mass(states)[:, 0]
    centres = emu.frames_of(s).numpy()[:, 0::18]  # each part's centre x
    weights = [mass[[body.NODES.index(p.split(".")[0]) for p, _ in part.points]].sum() for part in emu.parts]
    np.testing.assert_allclose(com, centres @ np.asarray(weights) / mass.sum(), atol=1e-5)
    # the returned trajectory is the whole hierarchy's, whose centre of mass is close to it
    full, _ = problem.trajectory(z)
    assert np.abs(body.centre_of_mass(full)[:, 0] - com).max() < 0.05


def test_an_objective_on_one_node_goes_through_every_network(root: Path) -> None:
    """A goal for the nose alone is not a function of the frames: the whole hierarchy is unrolled."""
    spec = validate_job(
        {
            "task": "dolphin-swim",
            "horizon": 4,
            "terms": [{"term": "forward_distance", "variables": ["nose.pos.x"], "direction": [1.0]}],
        },
        root,
    )
    problem, _, _ = load_problem(spec, root)
    assert problem.networks == "all" and problem.gradient_step is problem.step


def test_the_swim_gradient_matches_finite_differences(root: Path) -> None:
    spec = validate_job({"task": "dolphin-swim", "horizon": 8}, root)
    path = registry.resolve(root, spec.model, spec.version)
    emu = artifacts.load_emulator(path).double()
    problem = ControlProblem(emu, spec, registry.read_manifest(path), dtype=torch.float64)
    rng = np.random.default_rng(2)
    z = np.clip(problem.initial_points() + 0.3 * rng.normal(size=problem.initial_points().shape), -0.9, 0.9)
    _, grad, _, _ = problem.value_and_grad(z)
    h = 1e-4
    for idx in [(0, 0), (1, 3), (problem.num_points - 1, 5)]:
        zp, zm = z.copy(), z.copy()
        zp[idx] += h
        zm[idx] -= h
        fd = (problem.evaluate(zp[None])[0] - problem.evaluate(zm[None])[0]) / (2 * h)
        assert grad[idx] == pytest.approx(fd, rel=1e-5, abs=1e-8), idx


ARTIFACTS = Path(__file__).resolve().parents[2] / "artifacts"


def test_the_dolphin_learns_to_swim_and_swims_so_on_mujoco() -> None:
    """The task's defaults on the committed N^50 hierarchy: at most 20 BPTT iterations through the
    global network, and the controller moves the body forward on MuJoCo about as far as the emulator
    said (the bench measures how far: BENCHMARKS.md)."""
    result = run_job({"task": "dolphin-swim"}, ARTIFACTS, threads=1)
    assert result.status == "succeeded" and result.bptt_networks == "global"
    assert result.iterations is not None and result.iterations <= 20
    history = [h for h in result.objective_history if h is not None]
    assert history[-1] < history[0]
    assert result.emulated is not None and result.physical is not None
    emulated = body.centre_of_mass(np.asarray(result.emulated.states, dtype=float))[:, 0]
    physical = body.centre_of_mass(np.asarray(result.physical.states, dtype=float))[:, 0]
    forward_emu, forward_phys = emulated[-1] - emulated[0], physical[-1] - physical[0]
    assert forward_phys > 0.3  # metres in 20 s, from rest
    assert abs(forward_phys - forward_emu) <= 0.2 * forward_emu
    points = np.asarray(result.control_points, dtype=float)
    assert points.shape == (10, 6) and points.min() >= 0.0 and points.max() <= 1.0
