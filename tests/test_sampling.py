"""Training data from MuJoCo (thesis 4.5)."""

from __future__ import annotations

import numpy as np
import pytest

from neuroanimator import physics, sampling


@pytest.mark.parametrize("n", [1, 10, 50])
def test_lags_are_integers_in_n_to_5n(n: int) -> None:
    lags = sampling.sample_lags(np.random.default_rng(0), n, 20_000)
    assert np.issubdtype(lags.dtype, np.integer)
    assert lags.min() == n
    assert lags.max() == 5 * n


def test_lags_are_uniform() -> None:
    n = 20
    lags = sampling.sample_lags(np.random.default_rng(1), n, 20_000)
    assert abs(lags.mean() - 3 * n) < 0.02 * 3 * n
    # every value in [n, 5n] appears about equally often
    counts = np.bincount(lags - n, minlength=4 * n + 1)
    assert counts.size == 4 * n + 1
    expected = lags.size / counts.size
    assert counts.min() > 0.6 * expected and counts.max() < 1.4 * expected


@pytest.fixture(scope="module", params=["pendulum-force", "lander"])
def data(request: pytest.FixtureRequest) -> tuple[physics.PhysicalModel, sampling.Examples]:
    model = physics.get(request.param)
    return model, sampling.generate(model, 10, 300, seed=4, runs=64, progress=False)


def test_shapes(data: tuple[physics.PhysicalModel, sampling.Examples]) -> None:
    model, ex = data
    assert len(ex) == 300
    assert ex.states.shape == (300, model.state_size)
    assert ex.controls.shape == (300, model.num_controls)
    assert ex.forces.shape == (300, model.num_forces)
    assert ex.next_states.shape == (300, model.state_size)


def test_all_finite(data: tuple[physics.PhysicalModel, sampling.Examples]) -> None:
    _, ex = data
    for a in (ex.states, ex.controls, ex.forces, ex.next_states):
        assert np.all(np.isfinite(a))


def test_controls_are_in_the_useful_range(data: tuple[physics.PhysicalModel, sampling.Examples]) -> None:
    model, ex = data
    assert np.all(ex.controls >= model.control_range[:, 0]) and np.all(
        ex.controls <= model.control_range[:, 1]
    )


def test_next_states_are_held_control_super_steps(
    data: tuple[physics.PhysicalModel, sampling.Examples],
) -> None:
    model, ex = data
    pick = np.array([0, 7, 42, 123, 299])
    u = ex.controls[pick] if model.num_controls else None
    f = ex.forces[pick] if model.num_forces else None
    np.testing.assert_array_equal(model.step_held(ex.states[pick], u, f, 10), ex.next_states[pick])


def test_examples_are_distinct_states(data: tuple[physics.PhysicalModel, sampling.Examples]) -> None:
    _, ex = data
    assert np.unique(ex.states, axis=0).shape[0] == len(ex)
    assert not np.allclose(ex.states, ex.next_states)


def test_generate_is_deterministic_for_a_seed() -> None:
    model = physics.get("truck")
    a = sampling.generate(model, 5, 120, seed=7, runs=32, progress=False)
    b = sampling.generate(model, 5, 120, seed=7, runs=32, progress=False)
    for x, y in ((a.states, b.states), (a.controls, b.controls), (a.next_states, b.next_states)):
        np.testing.assert_array_equal(x, y)
    assert a.sha256() == b.sha256()


def test_generate_differs_for_another_seed() -> None:
    model = physics.get("truck")
    a = sampling.generate(model, 5, 120, seed=7, runs=32, progress=False)
    c = sampling.generate(model, 5, 120, seed=8, runs=32, progress=False)
    assert not np.allclose(a.states, c.states)
    assert a.sha256() != c.sha256()


def test_passive_model_has_empty_controls() -> None:
    ex = sampling.generate(physics.get("pendulum-passive"), 5, 50, seed=0, progress=False)
    assert ex.controls.shape == (50, 0)
    assert ex.forces.shape == (50, 0)


@pytest.mark.parametrize("count", [0, -3])
def test_non_positive_count_raises(count: int) -> None:
    with pytest.raises(ValueError, match="count"):
        sampling.generate(physics.get("truck"), 5, count, seed=0, progress=False)


def test_non_positive_substeps_raise() -> None:
    with pytest.raises(ValueError, match="substeps"):
        sampling.generate(physics.get("truck"), 0, 10, seed=0, progress=False)


def test_subset_and_check_finite() -> None:
    ex = sampling.generate(physics.get("pendulum-active"), 5, 20, seed=0, progress=False)
    sub = ex.subset(np.array([3, 5]))
    np.testing.assert_array_equal(sub.states, ex.states[[3, 5]])
    np.testing.assert_array_equal(sub.next_states, ex.next_states[[3, 5]])
    sub.next_states[0, 1] = np.nan
    with pytest.raises(ValueError, match="next_states"):
        sub.check_finite()


def test_sequences_are_held_super_steps_of_the_physics() -> None:
    """Each super-step of a sequence is the physics stepped n times with its controls held."""
    model = physics.get("lander")
    seq = sampling.generate_sequences(model, 10, 12, 3, seed=5, progress=False)
    assert seq.states.shape == (12, 4, model.state_size)
    assert seq.controls.shape == (12, 3, model.num_controls)
    for k in range(3):
        nxt = model.step_held(seq.states[:, k], seq.controls[:, k], None, 10)
        np.testing.assert_allclose(seq.states[:, k + 1], nxt, atol=1e-9)
    again = sampling.generate_sequences(model, 10, 12, 3, seed=5, progress=False)
    np.testing.assert_array_equal(again.states, seq.states)
