"""Training data from MuJoCo, as in thesis 4.5, and the faster default built on the same runs.

Many long runs are simulated side by side under typical smooth controls (Catmull-Rom over random
control points in the useful range), each from a fresh typical state. Two samplers take examples
from them; both are deterministic for a seed.

- ``"runs"`` (the default, ``generate_runs``): after a random lead of [1, 5n] physical steps under
  the smooth controls (so the start states and their transients are seen too), a run goes on as
  consecutive super-steps with each control held at its smooth value at the super-step's start:
  exactly how the emulator is driven when served. Every super-step is an example, so an example
  costs about n physical steps, and the runs double as the rollout phase's sequences.
  A held-out set (``generate_held_out``) is drawn like the training set it tests: whole runs of its
  horizon, not runs shortened to the held-out count.
- ``"spaced"`` (thesis 4.5, ``generate_spaced``): examples at well-separated times; the lag between
  two samples of a run is drawn uniformly in [Δt, 5Δt], and for each sample the physics is stepped n
  more times with the controls held. An example costs about 6n physical steps (the runs of a batch
  all step to the longest lag).
"""

from __future__ import annotations

import hashlib
import logging
import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from tqdm import tqdm

from neuroanimator.sim.model import MAX_DIVERGED, PhysicalModel, SimulationDiverged

log = logging.getLogger(__name__)
FloatArray = NDArray[np.float64]


@dataclass
class Examples:
    """N transitions: states (N,S), controls (N,U), forces (N,F) -> next_states (N,S)."""

    states: FloatArray
    controls: FloatArray
    forces: FloatArray
    next_states: FloatArray

    def __len__(self) -> int:
        return int(self.states.shape[0])

    def subset(self, index: NDArray[np.int64] | slice) -> Examples:
        return Examples(self.states[index], self.controls[index], self.forces[index], self.next_states[index])

    def sha256(self) -> str:
        h = hashlib.sha256()
        for a in (self.states, self.controls, self.forces, self.next_states):
            h.update(np.ascontiguousarray(a, dtype=np.float64).tobytes())
        return h.hexdigest()

    def check_finite(self, what: str = "training data") -> None:
        for name in ("states", "controls", "forces", "next_states"):
            arr = getattr(self, name)
            bad = ~np.isfinite(arr).all(axis=1)
            if bad.any():
                raise ValueError(f"{what}: {int(bad.sum())} rows of {name} contain NaN or Inf")


def sample_lags(rng: np.random.Generator, substeps: int, size: int) -> NDArray[np.int64]:
    """Physical steps between successive samples of a run: uniform integers in [n, 5n]."""
    return rng.integers(substeps, 5 * substeps + 1, size=size)


SAMPLERS = ("runs", "spaced")


def generate(
    model: PhysicalModel,
    substeps: int,
    count: int,
    seed: int,
    *,
    runs: int = 256,
    progress: bool = True,
    sampler: str = "runs",
) -> Examples:
    """``count`` shuffled examples of super-steps of ``substeps`` physical steps, by ``sampler``."""
    if sampler == "runs":
        return generate_runs(model, substeps, count, seed, runs=runs, progress=progress).examples(count, seed)
    if sampler == "spaced":
        return generate_spaced(model, substeps, count, seed, runs=runs, progress=progress)
    raise ValueError(f"sampler must be one of {', '.join(SAMPLERS)}, got {sampler!r}")


def generate_spaced(
    model: PhysicalModel,
    substeps: int,
    count: int,
    seed: int,
    *,
    runs: int = 256,
    progress: bool = True,
) -> Examples:
    """``count`` shuffled examples of super-steps of ``substeps`` physical steps, sampled as in thesis
    4.5: lags of [Δt, 5Δt] between the samples of a run, the controls held from each sample."""
    if count < 1:
        raise ValueError(f"count must be positive, got {count}")
    if substeps < 1:
        raise ValueError(f"substeps must be positive, got {substeps}")
    rng = np.random.default_rng(seed)
    runs = max(1, min(runs, count))
    dt = model.dt
    episode = max(round(model.spec.episode_s / dt), 6 * substeps)  # steps per episode
    max_lag = 5 * substeps
    times = np.arange(episode + max_lag + 1, dtype=np.float64) * dt

    state = model.initial_states(rng, runs)
    step_at = np.zeros(runs, dtype=np.int64)  # time index within each run's episode
    u_traj = model.typical_controls(rng, runs, times)  # (R, E, U)
    f_traj = model.typical_forces(rng, runs, times)  # (R, E, F)

    S, U, F = model.state_size, model.num_controls, model.num_forces
    out_s, out_u, out_f, out_n = (np.empty((count, k)) for k in (S, U, F, S))
    filled = 0
    bar = tqdm(
        total=count, desc=f"sampling {model.name} n={substeps}", unit="ex", disable=not progress, leave=False
    )
    rows = np.arange(runs)
    while filled < count:
        # restart runs whose episode is over (fresh state and fresh control functions)
        done = step_at + max_lag >= episode
        if done.any():
            k = int(done.sum())
            state[done] = model.initial_states(rng, k)
            u_traj[done] = model.typical_controls(rng, k, times)
            f_traj[done] = model.typical_forces(rng, k, times)
            step_at[done] = 0
        lags = sample_lags(rng, substeps, runs)
        # A run's first sample may come right after its start: the start states are typical too
        # (a client's session begins at one), including their transients (a truck's side-slip
        # dies out within a super-step). Later samples keep the [Δt, 5Δt] spacing.
        fresh = step_at == 0
        lags[fresh] = rng.integers(1, 5 * substeps + 1, size=int(fresh.sum()))
        span = int(lags.max())
        idx = np.minimum(step_at[:, None] + np.arange(span)[None, :], times.size - 1)  # (R, span)
        traj = model.simulate(
            state, u_traj[rows[:, None], idx], f_traj[rows[:, None], idx] if F else None, check=True
        )
        state = traj[rows, lags - 1]  # each run continues from its own sample time
        step_at = step_at + lags
        u_now = u_traj[rows, step_at]
        f_now = f_traj[rows, step_at]
        # the example: the same state stepped n times with u and f held at their sampled values
        nxt = model.step_held(state, u_now if U else None, f_now if F else None, substeps, check=True)
        take = min(runs, count - filled)
        sel = slice(filled, filled + take)
        out_s[sel], out_u[sel], out_f[sel], out_n[sel] = state[:take], u_now[:take], f_now[:take], nxt[:take]
        filled += take
        bar.update(take)
    bar.close()
    perm = rng.permutation(count)  # shuffle: successive examples of a run are not neighbours
    ex = Examples(out_s[perm], out_u[perm], out_f[perm], out_n[perm])
    ex.check_finite(f"simulated data of {model.name}")
    return ex


@dataclass
class Sequences:
    """N runs of K super-steps each: states (N, K+1, S), controls (N, K, U), forces (N, K, F); the
    controls and forces are held over each super-step, as the emulator takes them."""

    states: FloatArray
    controls: FloatArray
    forces: FloatArray
    diverged: int = 0  # runs MuJoCo could not simulate, dropped while sampling

    def __len__(self) -> int:
        return int(self.states.shape[0])

    def examples(self, count: int | None = None, seed: int = 0) -> Examples:
        """Every super-step of every run as one example, shuffled (by ``seed``); the first ``count``."""
        s = self.states
        total = len(self) * (s.shape[1] - 1)
        ex = Examples(
            s[:, :-1].reshape(total, s.shape[2]),
            self.controls.reshape(total, self.controls.shape[2]),
            self.forces.reshape(total, self.forces.shape[2]),
            s[:, 1:].reshape(total, s.shape[2]),
        )
        if count is not None and count > total:
            raise ValueError(f"{count} examples asked of runs that hold {total}")
        return ex.subset(np.random.default_rng(seed).permutation(total)[:count])

    def windows(self, horizon: int, count: int | None = None, seed: int = 0) -> Sequences:
        """Non-overlapping windows of ``horizon`` super-steps cut from the runs, shuffled (by ``seed``);
        the first ``count``: (count, horizon+1, S) states, (count, horizon, U|F) controls and forces."""
        k = self.states.shape[1] - 1
        per_run = k // horizon
        if per_run < 1:
            raise ValueError(f"runs of {k} super-steps hold no window of {horizon}")
        starts = np.arange(per_run) * horizon
        steps = starts[:, None] + np.arange(horizon + 1)[None, :]  # (W, horizon+1)
        w = len(self) * per_run
        states = self.states[:, steps].reshape(w, horizon + 1, self.states.shape[2])
        controls = self.controls[:, steps[:, :-1]].reshape(w, horizon, self.controls.shape[2])
        forces = self.forces[:, steps[:, :-1]].reshape(w, horizon, self.forces.shape[2])
        pick = np.random.default_rng(seed).permutation(states.shape[0])[:count]
        return Sequences(states[pick], controls[pick], forces[pick])


# The most physical states one rollout call of ``generate_sequences`` may return (about 128 MB):
# a model's runs are cut shorter where its state is large.
MAX_TRAJECTORY_VALUES = 16_000_000


def run_horizon(model: PhysicalModel, substeps: int, count: int, runs: int) -> int:
    """Super-steps per run for ``generate_runs`` of ``count`` examples: an episode
    (``spec.episode_s``), shorter so that the examples come from at least ``runs`` runs (independent
    starts: a few thousand held-out examples from a dozen runs would cover a dozen motions), and
    shorter where a batch of ``runs`` runs would not fit in ``MAX_TRAJECTORY_VALUES``; at least 1."""
    episode = round(model.spec.episode_s / model.dt) // substeps
    spread = math.ceil(count / max(1, runs))
    fits = MAX_TRAJECTORY_VALUES // max(1, runs * substeps * model.state_size)
    return int(max(1, min(episode, spread, fits)))


def lead_steps(model: PhysicalModel, substeps: int) -> int:
    """The longest lag (physical steps) before a sampled sequence starts: five super-steps, within a run
    (a run cut short where a body spins up starts its sequences before it has)."""
    return max(1, min(5 * substeps, round(model.spec.episode_s / model.dt)))


def steps_to_sample(
    model: PhysicalModel, substeps: int, count: int, sampler: str = "runs", runs: int = 256
) -> float:
    """Physical steps that ``generate`` simulates for ``count`` examples: batches of ``runs`` runs (the
    last one whole), each run a lead of up to 5n steps and then ``run_horizon`` super-steps ("runs"), or
    a lag of up to 5n steps and a super-step per example ("spaced")."""
    n = substeps
    if sampler == "spaced":
        batch = max(1, min(runs, count))
        return math.ceil(count / batch) * batch * 6.0 * n
    horizon = run_horizon(model, n, count, runs)
    sequences = math.ceil(count / horizon)
    batch = max(1, min(runs, sequences))
    return math.ceil(sequences / batch) * batch * (lead_steps(model, n) + horizon * n)


def sampling_steps(
    model: PhysicalModel, substeps: int, examples: int, test_examples: int, sampler: str = "runs"
) -> float:
    """Physical steps that simulating ``examples`` and ``test_examples`` held out like them takes
    (``steps_to_sample``, ``held_out_steps``)."""
    return steps_to_sample(model, substeps, examples, sampler) + held_out_steps(
        model, substeps, test_examples, examples, sampler
    )


# Held-out examples of the runs sampler come from at least this many whole runs (``generate_held_out``)
HELD_OUT_RUNS = 64


def _held_out_runs(
    model: PhysicalModel, substeps: int, count: int, like: int, runs: int
) -> tuple[int, int, int]:
    """(runs, their horizon, runs per batch) that ``generate_held_out`` simulates."""
    horizon = run_horizon(model, substeps, like, runs)
    total = max(math.ceil(count / horizon), HELD_OUT_RUNS)
    batch = max(1, min(runs, total, MAX_TRAJECTORY_VALUES // max(1, horizon * substeps * model.state_size)))
    return total, horizon, batch


def held_out_steps(
    model: PhysicalModel, substeps: int, count: int, like: int, sampler: str = "runs", runs: int = 256
) -> float:
    """Physical steps that ``generate_held_out`` simulates for ``count`` examples like ``like``'s."""
    if sampler != "runs":
        return steps_to_sample(model, substeps, count, sampler, runs)
    total, horizon, batch = _held_out_runs(model, substeps, count, like, runs)
    return math.ceil(total / batch) * batch * (lead_steps(model, substeps) + horizon * substeps)


def generate_held_out(
    model: PhysicalModel,
    substeps: int,
    count: int,
    seed: int,
    *,
    like: int,
    runs: int = 256,
    progress: bool = True,
    sampler: str = "runs",
) -> Examples:
    """``count`` held-out examples drawn as a training set of ``like`` examples is (``generate``, with
    another seed): of the runs sampler, whole runs of that training set's horizon (``run_horizon`` of
    ``like``), at least ``HELD_OUT_RUNS`` of them, ``count`` of their super-steps at random. The spaced
    sampler's examples do not depend on their count: as ``generate``.

    Why not ``generate(count)``: the runs sampler shortens its runs to spread a small count over many
    of them, so 4,000 examples came from 250 runs of 16 super-steps, every one within two seconds of a
    typical start, where a training set of 360,000 spreads over whole episodes. A start perturbed from
    ``qpos0`` rings for the first second (dm_control's ball_in_cup begins with its string past its
    length, the hopper falls from standing): there a ball_in_cup emulator's error was 0.16 and from
    1.6 s on 0.0003-0.0005, so such a held-out set measured the start (0.0125) and not the emulator
    over the motion it was trained on (0.004)."""
    if sampler != "runs":
        return generate(model, substeps, count, seed, runs=runs, progress=progress, sampler=sampler)
    total, horizon, batch = _held_out_runs(model, substeps, count, like, runs)
    seq = generate_sequences(
        model, substeps, total, horizon, seed, runs=batch, progress=progress, as_examples=True
    )
    return seq.examples(count, seed)


# The fewest examples a capped sampling keeps: below this a network learns nothing worth writing, and
# a model this slow overruns its budget rather than going untrained
MIN_TRAINING_EXAMPLES = 2000
MIN_TEST_EXAMPLES = 1000


@dataclass(frozen=True)
class SamplingPlan:
    """How many training and held-out examples to simulate, and why (None when nothing was cut)."""

    examples: int
    test_examples: int
    reason: str | None = None


def plan_within(
    model: PhysicalModel,
    substeps: int,
    examples: int,
    test_examples: int,
    seconds: float,
    *,
    sampler: str = "runs",
    seed: int = 0,
    least: tuple[int, int] = (MIN_TRAINING_EXAMPLES, MIN_TEST_EXAMPLES),
) -> SamplingPlan:
    """The examples that simulating fits in ``seconds`` at the model's measured step rate
    (``PhysicalModel.measure_step_rate``): all that were asked for when they fit; else both counts cut
    in proportion (no fewer than ``least``, training and held out), saying why.

    Why: a model's cost per physical step spans three orders of magnitude (a pendulum, dm_control's
    quadruped on its height field at about 3,000 steps/s on two cores), so a count set by the network's
    weights alone can take half an hour to simulate."""
    rate = model.measure_step_rate(seed)

    def steps(train: int, test: int) -> float:
        return sampling_steps(model, substeps, train, test, sampler)

    wanted = steps(examples, test_examples)
    if wanted <= seconds * rate:
        return SamplingPlan(examples, test_examples)

    def counts(fraction: float) -> tuple[int, int]:
        return (
            max(min(least[0], examples), int(examples * fraction)),
            max(min(least[1], test_examples), int(test_examples * fraction)),
        )

    low, high = 0.0, 1.0  # the largest fraction of both counts that fits (bisection: steps grow with it)
    for _ in range(40):
        mid = (low + high) / 2
        low, high = (mid, high) if steps(*counts(mid)) <= seconds * rate else (low, mid)
    train, test = counts(low)
    reason = (
        f"sampling cut to {train:,} examples and {test:,} held out (of {examples:,} and {test_examples:,}): "
        f"the model simulates {rate:,.0f} physical steps/s here, {wanted / rate:,.0f} s for all of them, "
        f"and the time budget leaves {seconds:,.0f} s for sampling; a longer --time-budget, or --examples, "
        "samples more"
    )
    return SamplingPlan(train, test, reason)


def generate_runs(
    model: PhysicalModel,
    substeps: int,
    count: int,
    seed: int,
    *,
    runs: int = 256,
    progress: bool = True,
) -> Sequences:
    """Runs of consecutive held super-steps that hold at least ``count`` examples (``run_horizon``
    super-steps each, from typical states after a random lead under the smooth controls)."""
    if count < 1:
        raise ValueError(f"count must be positive, got {count}")
    if substeps < 1:
        raise ValueError(f"substeps must be positive, got {substeps}")
    horizon = run_horizon(model, substeps, count, runs)
    return generate_sequences(
        model,
        substeps,
        math.ceil(count / horizon),
        horizon,
        seed,
        runs=runs,
        progress=progress,
        as_examples=True,
    )


def generate_sequences(
    model: PhysicalModel,
    substeps: int,
    count: int,
    horizon: int,
    seed: int,
    *,
    runs: int = 256,
    progress: bool = True,
    as_examples: bool = False,
) -> Sequences:
    """``count`` runs of ``horizon`` super-steps from typical states, for training over rollouts.
    With ``as_examples`` the progress bar is the one-step sampler's ("sampling", in examples).

    Each starts where a run under typical smooth controls is after a random lag (as ``generate``'s
    examples do); the controls and forces of its super-steps are that run's, sampled at the start of
    each super-step and held for it.
    """
    if count < 1 or horizon < 1:
        raise ValueError(f"count and horizon must be positive, got {count} and {horizon}")
    rng = np.random.default_rng(seed)
    runs = max(1, min(runs, count))
    n, k = substeps, horizon
    S, U, F = model.state_size, model.num_controls, model.num_forces
    warm = lead_steps(model, n)
    times = np.arange(warm + k * n + 1, dtype=np.float64) * model.dt
    out_s = np.empty((count, k + 1, S))
    out_u = np.empty((count, k, U))
    out_f = np.empty((count, k, F))
    filled = 0
    scale = k if as_examples else 1  # the bar counts super-steps as examples, or runs as sequences
    bar = tqdm(
        total=count * scale,
        desc=f"{'sampling' if as_examples else 'sequences'} {model.name} n={n}",
        unit="ex" if as_examples else "seq",
        disable=not progress,
        leave=False,
    )
    rows = np.arange(runs)
    tally = Divergence()
    while filled < count:
        state = model.initial_states(rng, runs)
        u_traj = model.typical_controls(rng, runs, times)  # (R, T, U)
        f_traj = model.typical_forces(rng, runs, times)
        lags = rng.integers(1, warm + 1, size=runs)
        span = int(lags.max())
        lead, lost = model.simulate_runs(state, u_traj[:, :span], f_traj[:, :span] if F else None)
        start = lead[rows, lags - 1]  # (R, S)
        at = lags[:, None] + np.arange(k)[None, :] * n  # (R, K): time index of each super-step start
        u_held = u_traj[rows[:, None], at]  # (R, K, U)
        f_held = f_traj[rows[:, None], at]
        full, lost_later = model.simulate_runs(
            start, np.repeat(u_held, n, axis=1), np.repeat(f_held, n, axis=1) if F else None
        )
        traj = full[:, n - 1 :: n]  # (R, K, S) at the super-step ends
        # a run MuJoCo could not simulate is dropped, and counted: too many, and sampling stops
        kept = np.flatnonzero(~(lost | lost_later))[: count - filled]
        try:
            tally.add(model, runs, runs - int((~(lost | lost_later)).sum()))
        except SimulationDiverged as exc:  # say when and where, as a checked simulation does
            try:
                model.simulate(state, u_traj[:, :span], f_traj[:, :span] if F else None, check=True)
                model.simulate(
                    start,
                    np.repeat(u_held, n, axis=1),
                    np.repeat(f_held, n, axis=1) if F else None,
                    check=True,
                )
            except SimulationDiverged as where:
                raise SimulationDiverged(f"{where}; {exc}") from exc
            raise
        take = kept.size
        sel = slice(filled, filled + take)
        out_s[sel, 0], out_s[sel, 1:] = start[kept], traj[kept]
        out_u[sel], out_f[sel] = u_held[kept], f_held[kept]
        filled += take
        bar.update(take * scale)
    bar.close()
    tally.report(model)
    if not np.all(np.isfinite(out_s)):
        raise ValueError(f"simulated sequences of {model.name} contain NaN or Inf")
    return Sequences(out_s, out_u, out_f, tally.dropped)


@dataclass
class Divergence:
    """Runs simulated and runs dropped because MuJoCo could not simulate them."""

    runs: int = 0
    dropped: int = 0

    def add(self, model: PhysicalModel, runs: int, dropped: int) -> None:
        self.runs += runs
        self.dropped += dropped
        if self.dropped > MAX_DIVERGED * max(self.runs, 64):
            raise SimulationDiverged(
                f"it diverged in {self.dropped} of {self.runs} runs of typical motion of model {model.name} (more "
                f"than {MAX_DIVERGED:.0%}): narrower typical controls or starts (an operating spec: --spec, or the "
                "form's operating spec), a smaller timestep or more damping"
            )

    def report(self, model: PhysicalModel) -> None:
        if self.dropped:
            log.warning(
                "%s: %d of %d sampled runs diverged in MuJoCo and were dropped",
                model.name,
                self.dropped,
                self.runs,
            )
