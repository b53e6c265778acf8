"""Training data from MuJoCo (thesis 4.5)."""

from __future__ import annotations

import numpy as np
import pytest

from neuroanimator import catalog
from neuroanimator.sim import sampling


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


@pytest.fixture(
    scope="module",
    params=[
        ("pendulum-force", "runs"),
        ("lander", "runs"),
        ("pendulum-force", "spaced"),
        ("lander", "spaced"),
    ],
    ids=lambda p: f"{p[0]}-{p[1]}",
)
def data(request: pytest.FixtureRequest) -> tuple[catalog.PhysicalModel, sampling.Examples]:
    name, sampler = request.param
    model = catalog.get(name)
    return model, sampling.generate(model, 10, 300, seed=4, runs=64, progress=False, sampler=sampler)


def test_shapes(data: tuple[catalog.PhysicalModel, sampling.Examples]) -> None:
    model, ex = data
    assert len(ex) == 300
    assert ex.states.shape == (300, model.state_size)
    assert ex.controls.shape == (300, model.num_controls)
    assert ex.forces.shape == (300, model.num_forces)
    assert ex.next_states.shape == (300, model.state_size)


def test_all_finite(data: tuple[catalog.PhysicalModel, sampling.Examples]) -> None:
    _, ex = data
    for a in (ex.states, ex.controls, ex.forces, ex.next_states):
        assert np.all(np.isfinite(a))


def test_controls_are_in_the_useful_range(data: tuple[catalog.PhysicalModel, sampling.Examples]) -> None:
    model, ex = data
    assert np.all(ex.controls >= model.control_range[:, 0]) and np.all(
        ex.controls <= model.control_range[:, 1]
    )


def test_next_states_are_held_control_super_steps(
    data: tuple[catalog.PhysicalModel, sampling.Examples],
) -> None:
    model, ex = data
    pick = np.array([0, 7, 42, 123, 299])
    u = ex.controls[pick] if model.num_controls else None
    f = ex.forces[pick] if model.num_forces else None
    # a run's super-step continues one rollout, a held step starts one from the same state
    np.testing.assert_allclose(model.step_held(ex.states[pick], u, f, 10), ex.next_states[pick], atol=1e-9)


def test_examples_are_distinct_states(data: tuple[catalog.PhysicalModel, sampling.Examples]) -> None:
    _, ex = data
    assert np.unique(ex.states, axis=0).shape[0] == len(ex)
    assert not np.allclose(ex.states, ex.next_states)


@pytest.mark.parametrize("sampler", sampling.SAMPLERS)
def test_generate_is_deterministic_for_a_seed(sampler: str) -> None:
    model = catalog.get("truck")
    a = sampling.generate(model, 5, 120, seed=7, runs=32, progress=False, sampler=sampler)
    b = sampling.generate(model, 5, 120, seed=7, runs=32, progress=False, sampler=sampler)
    for x, y in ((a.states, b.states), (a.controls, b.controls), (a.next_states, b.next_states)):
        np.testing.assert_array_equal(x, y)
    assert a.sha256() == b.sha256()


def test_generate_differs_for_another_seed() -> None:
    model = catalog.get("truck")
    a = sampling.generate(model, 5, 120, seed=7, runs=32, progress=False)
    c = sampling.generate(model, 5, 120, seed=8, runs=32, progress=False)
    assert not np.allclose(a.states, c.states)
    assert a.sha256() != c.sha256()


def test_passive_model_has_empty_controls() -> None:
    ex = sampling.generate(catalog.get("pendulum-passive"), 5, 50, seed=0, progress=False)
    assert ex.controls.shape == (50, 0)
    assert ex.forces.shape == (50, 0)


@pytest.mark.parametrize("count", [0, -3])
def test_non_positive_count_raises(count: int) -> None:
    with pytest.raises(ValueError, match="count"):
        sampling.generate(catalog.get("truck"), 5, count, seed=0, progress=False)


def test_non_positive_substeps_raise() -> None:
    with pytest.raises(ValueError, match="substeps"):
        sampling.generate(catalog.get("truck"), 0, 10, seed=0, progress=False)


def test_subset_and_check_finite() -> None:
    ex = sampling.generate(catalog.get("pendulum-active"), 5, 20, seed=0, progress=False)
    sub = ex.subset(np.array([3, 5]))
    np.testing.assert_array_equal(sub.states, ex.states[[3, 5]])
    np.testing.assert_array_equal(sub.next_states, ex.next_states[[3, 5]])
    sub.next_states[0, 1] = np.nan
    with pytest.raises(ValueError, match="next_states"):
        sub.check_finite()


def test_sequences_are_held_super_steps_of_the_physics() -> None:
    """Each super-step of a sequence is the physics stepped n times with its controls held."""
    model = catalog.get("lander")
    seq = sampling.generate_sequences(model, 10, 12, 3, seed=5, progress=False)
    assert seq.states.shape == (12, 4, model.state_size)
    assert seq.controls.shape == (12, 3, model.num_controls)
    for k in range(3):
        nxt = model.step_held(seq.states[:, k], seq.controls[:, k], None, 10)
        np.testing.assert_allclose(seq.states[:, k + 1], nxt, atol=1e-9)
    again = sampling.generate_sequences(model, 10, 12, 3, seed=5, progress=False)
    np.testing.assert_array_equal(again.states, seq.states)


def test_unknown_sampler_is_named() -> None:
    with pytest.raises(ValueError, match="sampler must be one of runs, spaced, got 'dense'"):
        sampling.generate(catalog.get("truck"), 5, 10, seed=0, progress=False, sampler="dense")


def test_runs_are_consecutive_held_super_steps_from_typical_states() -> None:
    """Every super-step of a run is an example; a run is an episode long and its controls change only
    at super-step starts (the emulator's contract), taking the smooth controls' values there."""
    model = catalog.get("truck")
    n = 10
    runs = sampling.generate_runs(model, n, 500, seed=3, runs=16, progress=False)
    k = sampling.run_horizon(model, n, 500, 16)
    assert k == 32 < round(model.spec.episode_s / model.dt) // n  # 500 examples over at least 16 runs
    assert runs.states.shape == (len(runs), k + 1, model.state_size) and len(runs) * k >= 500
    assert len(runs) == -(-500 // k)  # no more runs than the count asks for
    for j in (0, k // 2, k - 1):
        nxt = model.step_held(runs.states[:, j], runs.controls[:, j], None, n)
        np.testing.assert_allclose(runs.states[:, j + 1], nxt, atol=1e-9)
    # the runs start from distinct states and their controls vary from super-step to super-step
    assert np.unique(runs.states[:, 0], axis=0).shape[0] == len(runs)
    assert np.abs(np.diff(runs.controls, axis=1)).max() > 0


def test_examples_of_runs_are_every_super_step_once() -> None:
    model = catalog.get("pendulum-active")
    runs = sampling.generate_runs(model, 5, 200, seed=1, runs=8, progress=False)
    total = len(runs) * (runs.states.shape[1] - 1)
    every = runs.examples(seed=2)
    assert len(every) == total
    pairs = {(tuple(a), tuple(b)) for a, b in zip(every.states, every.next_states, strict=True)}
    assert len(pairs) == total
    first, last = runs.states[0, 0], runs.states[-1, -1]
    assert any(np.array_equal(first, s) for s in every.states)
    assert not any(np.array_equal(last, s) for s in every.states)  # a run's end starts no example
    some = runs.examples(200, seed=2)
    assert len(some) == 200
    np.testing.assert_array_equal(some.states, every.states[:200])  # the same shuffle, cut
    with pytest.raises(ValueError, match=f"{total + 1} examples asked of runs that hold {total}"):
        runs.examples(total + 1)


def test_windows_are_cut_from_the_runs_without_overlap() -> None:
    model = catalog.get("lander")
    runs = sampling.generate_runs(model, 10, 300, seed=5, runs=4, progress=False)
    k = runs.states.shape[1] - 1
    win = runs.windows(8, seed=1)
    assert win.states.shape == (len(runs) * (k // 8), 9, model.state_size)
    assert win.controls.shape == (len(win), 8, model.num_controls)
    # each window is a stretch of one run: its states, and the controls held over them
    starts = {tuple(w[0]) for w in win.states}
    assert len(starts) == len(win)
    r, j = np.argwhere((runs.states == win.states[0, 0]).all(axis=2))[0]
    np.testing.assert_array_equal(runs.states[r, j : j + 9], win.states[0])
    np.testing.assert_array_equal(runs.controls[r, j : j + 8], win.controls[0])
    assert len(runs.windows(8, 3, seed=1)) == 3
    with pytest.raises(ValueError, match="no window"):
        runs.windows(k + 1)


def test_run_horizon_spreads_examples_over_runs_and_keeps_batches_small() -> None:
    """A run is an episode long where the count fills ``runs`` runs of it; shorter so that a small
    count still comes from ``runs`` independent runs; shorter where a batch would pass
    MAX_TRAJECTORY_VALUES physical states; never below one super-step."""
    model = catalog.get("lander")
    episode = round(model.spec.episode_s / model.dt) // 10
    assert sampling.run_horizon(model, 10, 10**6, 256) == episode
    assert sampling.run_horizon(model, 10, 4000, 256) == 16  # 250 runs of 16 super-steps
    assert sampling.run_horizon(model, 10, 10, 256) == 1
    many = sampling.MAX_TRAJECTORY_VALUES // (10 * model.state_size * episode) + 1
    short = sampling.run_horizon(model, 10, 10**9, many)
    assert 1 <= short < episode and many * 10 * short * model.state_size <= sampling.MAX_TRAJECTORY_VALUES
    assert sampling.run_horizon(model, 10, 10**12, 10**9) == 1


def test_small_counts_come_from_many_runs() -> None:
    """3,000 held-out examples of the tumbling quadrotor: from about 256 runs, not a dozen episodes,
    so that upright and upside-down states are both well represented."""
    model = catalog.get("quadrotor")
    runs = sampling.generate_runs(model, 10, 3000, seed=77, progress=False)
    assert len(runs) >= 250 and np.unique(runs.states[:, 0], axis=0).shape[0] == len(runs)


def test_held_out_examples_are_drawn_like_the_training_set() -> None:
    """A held-out set of 500 examples, like a training set of 256 episodes: from the same stretch of
    the runs (the truck drives away from its start, so its distance says how far into a run a state
    is), where 500 examples of their own come from the first super-steps of 256 runs."""
    model = catalog.get("truck")
    like = 256 * (round(model.spec.episode_s / model.dt) // 10)
    train = sampling.generate(model, 10, like, seed=1, progress=False)
    held = sampling.generate_held_out(model, 10, 500, seed=2, like=like, progress=False)
    short = sampling.generate(model, 10, 500, seed=2, progress=False)
    assert len(held) == 500 and np.isfinite(held.states).all()
    far = np.abs(train.states[:, :2]).mean()
    assert 0.8 * far <= np.abs(held.states[:, :2]).mean() <= 1.2 * far
    assert np.abs(short.states[:, :2]).mean() < 0.7 * far
    again = sampling.generate_held_out(model, 10, 500, seed=2, like=like, progress=False)
    np.testing.assert_array_equal(again.states, held.states)
    # from at least HELD_OUT_RUNS runs, each as long as the training set's runs
    total, horizon, _ = sampling._held_out_runs(model, 10, 500, like, 256)
    assert total >= sampling.HELD_OUT_RUNS and horizon == sampling.run_horizon(model, 10, like, 256)


# ----------------------------------------------------------------------------- the cost of sampling
def test_a_model_knows_its_step_rate_only_after_simulating() -> None:
    """``step_rate`` is None for a fresh model (nothing measured) and counts every thread's steps."""
    model = catalog.get("pendulum-force")
    assert model.step_rate is None
    rate = model.measure_step_rate()
    assert rate > 0 and model.step_rate == rate
    assert model._seconds_simulating >= model.RATE_MIN_SECONDS


@pytest.mark.parametrize(
    ("sampler", "count", "like"),
    [
        ("runs", 3000, None),
        ("runs", 300, None),
        ("spaced", 300, None),
        ("runs", 300, 3000),
        ("runs", 300, 60000),
    ],
)
def test_the_cost_estimate_is_the_steps_that_sampling_simulates(
    sampler: str, count: int, like: int | None
) -> None:
    """``steps_to_sample`` predicts the physical steps ``generate`` takes (which ``plan_within`` turns
    into seconds), and ``held_out_steps`` those of ``generate_held_out`` (``like``): within 25% for both
    samplers, long runs and short."""
    model = catalog.get("lander")
    before = model._steps_simulated
    if like is None:
        sampling.generate(model, 10, count, seed=3, progress=False, sampler=sampler)
        estimate = sampling.steps_to_sample(model, 10, count, sampler)
    else:
        sampling.generate_held_out(model, 10, count, seed=3, like=like, progress=False, sampler=sampler)
        estimate = sampling.held_out_steps(model, 10, count, like, sampler)
    simulated = model._steps_simulated - before
    assert 0.75 * simulated <= estimate <= 1.25 * simulated, (simulated, estimate)


def test_a_plan_that_fits_keeps_every_example() -> None:
    model = catalog.get("pendulum-force")
    plan = sampling.plan_within(model, 10, 500, 200, seconds=60.0)
    assert (plan.examples, plan.test_examples, plan.reason) == (500, 200, None)


def test_a_plan_that_does_not_fit_is_cut_to_the_seconds_and_says_why() -> None:
    """Both counts shrink in proportion until their estimated steps fit the seconds at the measured
    rate; the reason names the rate, the cut and what to do; never below ``least``."""
    model = catalog.get("lander")
    rate = model.measure_step_rate()
    seconds = 2_000_000 / rate  # about 2 M physical steps: 400,000 examples at n = 50 do not fit
    plan = sampling.plan_within(model, 50, 400_000, 4000, seconds)
    assert 2000 <= plan.examples < 400_000 and 1000 <= plan.test_examples < 4000
    steps = sampling.sampling_steps(model, 50, plan.examples, plan.test_examples)
    assert 0.8 * seconds * rate <= steps <= 1.05 * seconds * rate
    assert plan.reason and "physical steps/s" in plan.reason and "--time-budget" in plan.reason
    tiny = sampling.plan_within(model, 50, 400_000, 4000, 1e-6, least=(700, 300))
    assert (tiny.examples, tiny.test_examples) == (700, 300)
