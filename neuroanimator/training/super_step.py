"""Choosing the super-step n for a model the user did not give one for, and refusing a useless emulator.

A smooth model (no contact, no limit that engages) is often learned well at the thesis' n = 50; a
contact or a joint limit that switches on inside a super-step makes the map from state to next state a
kink, and the longer the super-step, the more of its examples hold one; a quadrotor that typical thrusts
spin up turns further within a longer one. So for every model: leave out the super-steps within which
the typical body turns a full turn (``motion``), train short probes at n = 50, 25 and 10, longest first,
and take the longest n whose probe reaches the target, else the longest within ``PROBE_TIE`` of the best
probe, saying why. A probe samples no more than ``PROBE_SAMPLING_S`` of simulation; a longer n whose
smallest probe would take over twice that (a slow model: dm_control's quadruped simulates about 2,600
steps/s here) is not probed, and the training's budget goes to the shorter ones. Contacts and limits
count where they engage anywhere within a super-step (``constraint_activity``), not only at its start.

Short probes overstate a full training's error, most for a model whose joint limits engage: the network
reads how far past each limit the joint would go within the super-step (``structured.JointLimit``), and
full trainings at n = 50 met the target where probes did not (dm_control's cartpole: probe 0.077, full
training 0.0054; the reacher: probe 0.0128, full 0.00046). After the real training, an emulator that is
no better than a linear fit, or far off the target, is refused rather than written.

A model whose constraints engage also gets a wider network of units that do not saturate
(``constrained_defaults``) where the user chose none: a contact or a limit puts kinks into the step,
which piecewise-linear-like units (SiLU) fit better than tanh, and a kink needs more units and more
examples to place. Measured on the catalog ball (contacts in 96% of its states, n = 10): tanh with
two layers of 64 reached 0.0168, SiLU with two layers of 128 (and the 10×-weights examples that go
with it) 0.0059.

A model of the user's own (``neuro train --mjcf``, and so the trainer service) gets a deeper network
where the user chose none (``user_defaults``): three layers of 128 SiLU units, the cosine schedule and
batches of 512, whether or not its constraints engage. Measured on dm_control's suite at n = 50
within the 285 s budget: acrobot 0.0106 with two layers of 128 at the same batch, 0.0022 with three;
cartpole 0.0044 → 0.00073; fish 0.0038 (two layers of 64 tanh) → 0.0023. The catalog's models keep
their own (their committed emulators, and the single-client speed bars, were measured with them).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field, replace

import mujoco
import numpy as np

from neuroanimator.core.train_config import TrainConfig
from neuroanimator.sim import sampling
from neuroanimator.sim.model import ModelError, PhysicalModel
from neuroanimator.training.motion import FastestMotion, bound_super_steps, cut_spin_up, fastest_motion

log = logging.getLogger(__name__)

CANDIDATES = (50, 25, 10)  # longest first; never below 10 physical steps per super-step
TARGET = 0.01  # held-out one-step relative error a chosen n should reach
# A short probe overstates the error of a full training, by far more than its noise: dm_control's
# pendulum probed 0.0244 at n = 50 and trains to 1.8e-6 there, ball_in_cup 0.045 and 0.0032; so a probe
# within this many times the target counts as reaching it ...
PROBE_SLACK = 5.0
# ... and, where no contact engages, this many times more: a smooth map (joint limits at most, which the
# limit ramps carry) is learned far better by a full training than a probe's 6,000 examples say
# (dm_control's acrobot: probe 0.0726, full training 0.0014 at n = 50; the cartpole: 0.055 and 0.0007)
SMOOTH_PROBE_SLACK = 2.0
# Probes within this factor of the best are a tie: ball_in_cup's probes of 0.061, 0.053 and 0.056 at
# n = 50, 25 and 10 were within their noise, and full trainings there gave 0.013 (n = 50), 0.019 (25)
# and 0.042 (10, with the pair distances on), BENCHMARKS.md
PROBE_TIE = 1.25
PROBE_SAMPLING_S = 20.0  # the most a probe's examples may take to simulate ...
PROBE_LEAST = (1000, 500)  # ... unless it would have fewer than these (training, held out)
REFUSE_ERROR = 0.05  # above this one-step error, an emulator is refused ...
REFUSE_GAIN = 2.0  # ... as it is when it is not this many times below the linear baseline
# Below this one-step error an emulator is kept whatever the linear baseline does: a model that a linear
# map already predicts well (a small pendulum: 1.07e-5 against a linear 1.78e-5) is not a failed
# emulator, and a linear system (dm_control's LQR) is fitted exactly by both, with nothing to beat
ACCEPT_ERROR = 1e-3
CONSTRAINED_HIDDEN = (128, 128)  # the network of a model whose contacts or limits engage ...
CONSTRAINED_ACTIVATION = "silu"  # ... and its units
USER_HIDDEN = (128, 128, 128)  # the network of a model of the user's own (--mjcf) ...
USER_BATCH = 512  # ... and its batch
PROBE_BATCH = 256  # a probe's few thousand examples need more, smaller steps

_LIMIT_TYPES = (int(mujoco.mjtConstraint.mjCNSTR_LIMIT_JOINT), int(mujoco.mjtConstraint.mjCNSTR_LIMIT_TENDON))


class ModelOutOfReach(ModelError):
    """The trained emulator misses the acceptance bar: nothing is written."""


@dataclass(frozen=True)
class ConstraintActivity:
    """How often, over sampled super-steps of typical motion (``states`` of them), a contact or a limit
    engages within one (0..1)."""

    contact: float
    limit: float
    states: int

    @property
    def any(self) -> bool:
        return self.contact > 0 or self.limit > 0

    def describe(self) -> str:
        return (
            f"contacts in {self.contact:.0%} and limits engaged in {self.limit:.0%} of {self.states} sampled "
            "super-steps"
        )


@dataclass
class SuperStepChoice:
    """The chosen n, why, and the probe errors it was chosen from (n -> one-step relative error)."""

    substeps: int
    reason: str
    activity: ConstraintActivity
    probes: dict[int, float] = field(default_factory=dict)


def constraint_activity(
    model: PhysicalModel, *, seconds: float = 10.0, runs: int = 8, seed: int = 0, window: int = CANDIDATES[0]
) -> ConstraintActivity:
    """Simulate ``runs`` typical motions of ``seconds`` and count, over about 200 windows of ``window``
    physical steps (the longest super-step), whether a contact or a joint/tendon limit engages anywhere
    within each (``mj_fwdPosition`` at every step): a limit reached in the middle of a super-step kinks
    its map as much as one engaged at its start."""
    rng = np.random.default_rng(seed)
    if model.spec.episode_s < seconds:  # runs as long as the model's typical runs, as many more
        runs = math.ceil(runs * seconds / model.spec.episode_s)
        seconds = model.spec.episode_s
    steps = max(1, round(seconds / model.dt))
    traj = model.simulate(*model.typical_runs(rng, runs, steps))  # (R, T, S)
    width = max(1, min(window, steps))
    per_run = max(1, math.ceil(200 / runs))  # about 200 windows in all
    starts = np.arange(0, steps - width + 1, max(1, (steps - width + 1) // per_run))[:per_run]  # (W,)
    m = model.mj_model
    d = mujoco.MjData(m)
    contact = limit = 0
    for run in traj:
        for start in starts:
            touched = limited = False
            for row in model.to_physics(run[start : start + width]):
                mujoco.mj_setState(m, d, row, mujoco.mjtState.mjSTATE_FULLPHYSICS)
                mujoco.mj_fwdPosition(m, d)
                touched = touched or d.ncon > 0
                limited = limited or bool(np.isin(d.efc_type[: d.nefc], _LIMIT_TYPES).any())
                if touched and limited:
                    break
            contact += touched
            limit += limited
    n = len(traj) * len(starts)
    return ConstraintActivity(contact=contact / n, limit=limit / n, states=n)


def probe_config(cfg: TrainConfig, substeps: int, model: PhysicalModel | None = None) -> TrainConfig:
    """A short training at ``substeps``: at most 6,000 examples and 40 epochs, no rollout phase, no bars;
    with ``model``, no more examples than it simulates in ``PROBE_SAMPLING_S`` (a slow model: dm_control's
    quadruped took 280 s to sample a probe's 7,000 examples at n = 50).

    Bounded by epochs rather than seconds, so that a busy machine does not change the choice (a 60 s
    cap only guards against a very slow one)."""
    examples, test = min(cfg.examples or 6000, 6000), 1000
    if model is not None:
        plan = sampling.plan_within(
            model, substeps, examples, test, PROBE_SAMPLING_S, sampler=cfg.sampler, least=PROBE_LEAST
        )
        examples, test = plan.examples, plan.test_examples
    return replace(
        cfg,
        substeps=substeps,
        examples=examples,
        test_examples=test,
        max_epochs=min(cfg.max_epochs, 40),
        batch_size=min(cfg.batch_size, PROBE_BATCH),
        max_seconds=min(cfg.max_seconds, 60.0),
        rollout_steps=0,
        progress=False,
    )


def constrained_defaults(
    cfg: TrainConfig,
    activity: ConstraintActivity,
    *,
    hidden_given: bool,
    activation_given: bool,
    schedule_given: bool = False,
) -> tuple[TrainConfig, str | None]:
    """The config for a model whose contacts or limits engage (``activity.any``): two layers of 128
    SiLU units where the user gave no width or activation (see the module doc), the learning rate
    annealed over the budget, and why; unchanged, with None, for a smooth model or when the user
    chose both."""
    if not activity.any or (hidden_given and activation_given):
        return cfg, None
    changed = replace(
        cfg,
        hidden=cfg.hidden if hidden_given else CONSTRAINED_HIDDEN,
        activation=cfg.activation if activation_given else CONSTRAINED_ACTIVATION,
        # annealed over the time budget: a wider network does not converge within it, and a run cut
        # off at a large rate leaves the kinks' last digits unlearned
        schedule=cfg.schedule if schedule_given else "cosine",
    )
    width = "×".join(str(h) for h in changed.hidden)
    return changed, f"{width} {changed.activation} units, {changed.schedule} schedule: {activity.describe()}"


def user_defaults(
    cfg: TrainConfig,
    activity: ConstraintActivity,
    *,
    hidden_given: bool,
    activation_given: bool,
    schedule_given: bool = False,
    batch_given: bool = False,
) -> tuple[TrainConfig, str | None]:
    """The config for a model of the user's own (see the module doc): three layers of 128 SiLU units,
    the cosine schedule and batches of 512 where the user chose none of them, and why; unchanged, with
    None, when the user chose all four."""
    if hidden_given and activation_given and schedule_given and batch_given:
        return cfg, None
    changed = replace(
        cfg,
        hidden=cfg.hidden if hidden_given else USER_HIDDEN,
        activation=cfg.activation if activation_given else CONSTRAINED_ACTIVATION,
        schedule=cfg.schedule if schedule_given else "cosine",
        batch_size=cfg.batch_size if batch_given else USER_BATCH,
    )
    width = "×".join(str(h) for h in changed.hidden)
    return changed, (
        f"{width} {changed.activation} units, {changed.schedule} schedule, batches of {changed.batch_size}: "
        f"a model of one's own ({activity.describe()})"
    )


def choose_substeps(
    model: PhysicalModel,
    cfg: TrainConfig,
    *,
    candidates: tuple[int, ...] = CANDIDATES,
    activity: ConstraintActivity | None = None,
    motion: FastestMotion | None = None,
) -> SuperStepChoice:
    """The longest super-step in ``candidates`` that the model can be learned at (see the module doc);
    ``activity`` and ``motion``, when measured already, are not measured again. Candidates over which
    the fastest typical motion turns over half a turn are left out (``motion.bound_super_steps``: where
    none is left, the model's runs are cut short, and its operating record says so)."""
    from neuroanimator.training.train import train  # torch: only when probes are needed

    activity = activity or constraint_activity(model, seed=cfg.seed)
    motion = motion or fastest_motion(model, seed=cfg.seed)
    allowed, bound = bound_super_steps(model, candidates, motion)
    if bound:
        log.warning("%s: %s", model.name, bound)
    said = "; ".join(x for x in (activity.describe(), bound) if x)
    if len(allowed) == 1:
        return SuperStepChoice(allowed[0], f"n={allowed[0]}: {said}", activity)
    probes: dict[int, float] = {}
    skipped: list[str] = []
    slack = PROBE_SLACK * (SMOOTH_PROBE_SLACK if activity.contact == 0 else 1.0)
    for n in allowed:
        probe = probe_config(cfg, n, model)
        seconds = sampling.sampling_steps(model, n, probe.examples or 0, probe.test_examples, cfg.sampler) / (
            model.step_rate or model.measure_step_rate()
        )
        if seconds > 2 * PROBE_SAMPLING_S and n != allowed[-1]:  # the shortest is always probed
            skipped.append(f"n={n} ({seconds:.0f} s to simulate {probe.examples:,} examples)")
            log.info(
                "%s: no probe at n=%d: its examples would take %.0f s to simulate", model.name, n, seconds
            )
            continue
        err = float(train(model, probe).metrics["one_step_rel_error"])
        probes[n] = err
        log.info("%s: probe at n=%d: one-step relative error %.3g", model.name, n, err)
        if err <= slack * TARGET:
            break
    chosen, verdict = pick(probes, slack)
    tried = ", ".join(f"n={n}: {e:.3g}" for n, e in probes.items())
    slow = f"; too slow to probe: {', '.join(skipped)}" if skipped else ""
    reason = f"n={chosen}: {said}; probe one-step errors {tried}; {verdict}{slow}"
    return SuperStepChoice(chosen, reason, activity, probes)


def spin_up(model: PhysicalModel, cfg: TrainConfig, shortest: int = CANDIDATES[-1]) -> FastestMotion:
    """Measure how typical motion turns, cut the runs where it spins a body up (``motion.cut_spin_up``:
    logged, and noted in the model's operating record) and measure again over the runs kept."""
    motion = fastest_motion(model, seed=cfg.seed)
    said = cut_spin_up(model, motion, shortest)
    if said is None:
        return motion
    log.warning("%s: %s", model.name, said)
    op = model.spec.operating
    if op is not None:
        model.spec = model.spec.model_copy(update={"operating": op.model_copy(update={"spin_up": said})})
    return fastest_motion(model, seed=cfg.seed)


def pick(probes: dict[int, float], slack: float = PROBE_SLACK) -> tuple[int, str]:
    """The super-step to take from probe errors (n -> one-step relative error), and why: the longest
    whose probe reached the target (with ``slack``), else the longest within ``PROBE_TIE`` of the best
    probe (probes differ by their noise; among near ties the longer step is worth more)."""
    fits = [n for n, e in probes.items() if e <= slack * TARGET]
    if fits:
        return max(fits), f"the longest whose short probe reached {slack * TARGET:g}"
    best = min(probes.values())
    longest_tie = max(n for n, e in probes.items() if e <= PROBE_TIE * best)
    return (
        longest_tie,
        f"no probe reached {slack * TARGET:g}; the longest within {PROBE_TIE:g}× of the best",
    )


def check_useful(
    name: str, substeps: int, one_step: float, linear: float, sampling: str | None = None
) -> None:
    """Refuse an emulator far off the target or hardly better than a linear fit (``ModelOutOfReach``),
    unless its error is below ``ACCEPT_ERROR`` whatever the ratio. ``sampling``: why the training had
    fewer examples than it asked for (``training.sampling_plan``), the first thing to try then."""
    if math.isfinite(one_step) and one_step <= ACCEPT_ERROR:
        return
    if not math.isfinite(one_step) or one_step > REFUSE_ERROR or linear < REFUSE_GAIN * one_step:
        raise ModelOutOfReach(
            f"{name} n={substeps}: one-step relative error {one_step:.3g} (linear baseline {linear:.3g}) misses "
            f"the bar (≤ {ACCEPT_ERROR:g}, or ≤ {REFUSE_ERROR:g} and ≥ {REFUSE_GAIN:g}× below linear): nothing written. "
            + (f"The time budget cut its data: {sampling}. " if sampling else "")
            + "Try a shorter super-step (--substeps), more examples (--examples) or a wider network (--hidden); "
            "--force writes it anyway"
        )
