"""dm_control's suite tasks in ``bench/policies.py``: a policy learned through the emulator with the
suite's reward, beside Stable-Baselines3's SAC trained on MuJoCo itself for the same wall time.

For each task (``control.suite_tasks.SUITE_TASKS``), all in, on the same torch threads:

1. the emulator at the task's control period (``SuiteTask.substeps``): the one in ``--artifacts``
   (the data directory by default), else trained now (``neuro train --mjcf <domain>.xml --substeps
   n --time-budget s``, ``s`` the task's ``emulator_seconds``: 285, 900 for a body on the ground, the
   defaults otherwise), its time counted in the task's wall time and its simulated examples in its
   MuJoCo steps;
2. the policy (``seed_race.train_reward_policy``: the task's seeds side by side, one core each, the
   best kept) for what is left of the task's budget (``--suite-seconds``, default the task's
   ``train_seconds`` = 25 minutes, plus the emulator's);
3. SAC on MuJoCo (``SuiteEnv``: the same control period, the suite's starts and exact reward summed over
   each action's control steps, the state with angles as sine and cosine and the task's parameters as
   observation) for the same wall time, with as many torch threads as the policy had cores (its seeds,
   or its threads: ``seed_race.cores_used``);

then both run ``EPISODES`` episodes of 1,000 control steps on MuJoCo from the same held-out starts
(``HELD_OUT_SEED``), the return their mean. At the policy, the emulator's step agreement with MuJoCo
(``control.step_agreement``: whether it tells neighbouring policies apart as the physics does) is
reported beside its root's drift, its MuJoCo steps apart from the training's. ``--set KEY=VALUE``
changes one of the policy's ``RewardSettings`` for the run (``setting_overrides``): a variant
measured by the same command.

The model-based returns the field publishes for these tasks are in BENCHMARKS.md beside the results.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
import subprocess
import sys
import time
import typing
from pathlib import Path
from typing import Any

import gymnasium
import numpy as np
import torch
from _model_free import Deadline
from numpy.typing import NDArray
from stable_baselines3 import SAC

from neuroanimator.artifacts import registry
from neuroanimator.artifacts import store as artifacts
from neuroanimator.control.bptt import FastStep
from neuroanimator.control.policy_store import save_reward_policy
from neuroanimator.control.random_search import RandomSearch
from neuroanimator.control.reward_policy import (
    RewardSettings,
    draw_starts,
    falls,
    random_search_of,
    root_drift,
    run_on_mujoco,
)
from neuroanimator.control.seed_race import cores_used, train_reward_policy
from neuroanimator.control.step_agreement import StepAgreement, step_agreement
from neuroanimator.control.suite_tasks import SUITE_TASKS, Context, SuiteTask
from neuroanimator.sim.model import PhysicalModel

log = logging.getLogger("bench.suite")
FloatArray = NDArray[np.float64]
HELD_OUT_SEED = 90_210
EPISODES = 10


def suite_xml(domain: str) -> Path:
    from dm_control import suite

    return Path(suite.__file__).parent / f"{domain}.xml"


def emulator_for(task: SuiteTask, root: Path, seconds: float | None) -> tuple[Path, float, int, bool]:
    """The task's emulator in ``root`` (trained now if missing): its path, the seconds its training
    took (measured here, or as its manifest recorded them when it was found) and the MuJoCo steps of
    its training data, and whether it was trained now."""
    t0 = time.perf_counter()
    try:
        path = registry.resolve(root, task.domain, substeps=task.substeps)
        wall, here = 0.0, False
    except (FileNotFoundError, LookupError, ValueError):
        cmd = [sys.executable, "-m", "neuroanimator.cli", "train", "--mjcf", str(suite_xml(task.domain))]
        cmd += ["--name", task.domain, "--substeps", str(task.substeps), "--out", str(root), "--quiet"]
        # written whatever its one-step error: a contact model's is judged by the policy learned here
        cmd += ["--force"]
        if seconds is not None:
            cmd += ["--time-budget", str(seconds)]
        log.info("%s: training its emulator: %s", task.name, " ".join(cmd))
        subprocess.run(cmd, check=True)
        path = registry.resolve(root, task.domain, substeps=task.substeps)
        wall, here = time.perf_counter() - t0, True
    manifest = registry.read_manifest(path)
    metrics = manifest.metrics
    if metrics is None:
        return path, wall, 0, here
    examples = metrics.examples + metrics.test_examples
    return path, wall if here else metrics.total_seconds, examples * task.substeps, here


def observe(
    physical: PhysicalModel, states: FloatArray, params: FloatArray, skip: tuple[str, ...] = ()
) -> NDArray[np.float32]:
    """(N, S) states and (N, P) parameters → (N, D) observations: hinge angles as sine and cosine, the
    ``skip`` groups left out (the task's ``unobserved``: the suite's observations omit them too)."""
    parts: list[FloatArray] = []
    for g, at in zip(physical.layout.groups, physical.layout.offsets, strict=True):
        if g.name in skip:
            continue
        cols = states[:, at : at + g.size]
        parts += [np.sin(cols), np.cos(cols)] if g.kind in ("angle", "heading") else [cols]
    return np.concatenate([*parts, params], axis=1).astype(np.float32)


class SuiteEnv(gymnasium.Env[NDArray[np.float32], NDArray[np.float32]]):
    """A suite task on MuJoCo as a Gymnasium environment: one step is one policy step (``repeat``
    control steps with the action held), the reward the suite's summed over them."""

    def __init__(
        self, task: SuiteTask, physical: PhysicalModel, low: FloatArray, high: FloatArray, seed: int
    ) -> None:
        self.task, self.physical = task, physical
        self.ctx = Context(physical.mj_model, _layout(physical))
        self.rng = np.random.default_rng(seed)
        self.low, self.high = low, high
        self.action_space = gymnasium.spaces.Box(-1.0, 1.0, (len(self.low),), np.float32)
        s, p = draw_starts(task, physical, self.rng, 1)
        dim = observe(physical, s, p, task.unobserved).shape[1]
        self.observation_space = gymnasium.spaces.Box(-np.inf, np.inf, (dim,), np.float32)
        self.steps = 0
        self.k = 0

    def controls(self, actions: NDArray[Any]) -> FloatArray:
        a = np.clip(np.asarray(actions, dtype=np.float64), -1, 1)
        return 0.5 * (self.low + self.high) + 0.5 * (self.high - self.low) * a

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[NDArray[np.float32], dict[str, Any]]:
        super().reset(seed=seed)
        self.s, self.p = draw_starts(self.task, self.physical, self.rng, 1)
        self.k = 0
        return observe(self.physical, self.s, self.p, self.task.unobserved)[0], {}

    def step(
        self, action: NDArray[np.float32]
    ) -> tuple[NDArray[np.float32], float, bool, bool, dict[str, Any]]:
        u = self.controls(action)[None]
        total = 0.0
        for _ in range(self.task.repeat):
            self.s = self.physical.step_held(self.s, u, None, self.task.control_substeps)
            with torch.no_grad():
                r = self.task.reward(
                    self.ctx, torch.as_tensor(self.s), torch.as_tensor(u), torch.as_tensor(self.p), False
                )
            total += float(r[0])
        self.steps += 1
        self.k += 1
        truncated = self.k >= self.task.policy_steps
        return observe(self.physical, self.s, self.p, self.task.unobserved)[0], total, False, truncated, {}


def _layout(physical: PhysicalModel) -> list[Any]:
    from neuroanimator.core.state import LayoutGroup

    return [
        LayoutGroup(**g.model_dump(), offset=o)
        for g, o in zip(physical.layout.groups, physical.layout.offsets, strict=True)
    ]


def sac_baseline(
    task: SuiteTask,
    physical: PhysicalModel,
    ctx: Context,
    low: FloatArray,
    high: FloatArray,
    seed: int,
    quick: bool,
    wall: float,
    cores: int,
    starts: FloatArray,
    params: FloatArray,
) -> dict[str, Any]:
    """SAC trained on MuJoCo for ``wall`` seconds on ``cores`` torch threads, then run from the
    held-out ``starts`` (module doc, step 3): a row's ``model_free``."""
    torch.set_num_threads(cores)  # SAC on the cores the policy's seeds had
    env = SuiteEnv(task, physical, low, high, seed)
    agent = SAC(
        "MlpPolicy", env, seed=seed, device="cpu", buffer_size=300_000,
        learning_starts=50 if quick else 1000, batch_size=64 if quick else 256, verbose=0,
    )  # fmt: skip
    f0 = time.perf_counter()
    agent.learn(total_timesteps=10**9, callback=Deadline(f0 + (6.0 if quick else wall)))
    free_wall = time.perf_counter() - f0

    def free_act(states: FloatArray, p: FloatArray) -> FloatArray:
        actions, _ = agent.predict(observe(physical, states, p, task.unobserved), deterministic=True)
        return env.controls(actions)

    theirs = run_on_mujoco(task, physical, ctx, free_act, starts, params)
    return {
        "algorithm": "sac",
        "return_physics": round(float(theirs.returns.mean()), 1),
        "mujoco_steps": env.steps * task.substeps,
        "env_steps": env.steps,
        "wall_s": round(free_wall, 1),
        "threads": cores,
    }


def bench_suite_baseline(
    name: str, seconds: float | None, seed: int, quick: bool, threads: int
) -> dict[str, Any]:
    """SAC alone on one suite task (``--baseline-only``): the task's MuJoCo model and its controls'
    range as ``neuro train --mjcf`` reads them (the emulator's, at its defaults), the task's budget
    (or ``seconds``; a full row gives SAC the policy's measured wall time) on ``threads`` torch
    threads (a full row gives it the policy's cores), judged on the same held-out starts as a row's
    ``model_free``; no emulator and no policy (their columns None)."""
    from neuroanimator.sim.mjcf import load_mjcf

    task = SUITE_TASKS[name]
    budget = seconds if seconds is not None else task.train_seconds + 300.0
    physical = load_mjcf(suite_xml(task.domain), substeps=task.substeps)
    ctx = Context(physical.mj_model, _layout(physical))
    low, high = physical.control_range[:, 0], physical.control_range[:, 1]
    episodes = 2 if quick else EPISODES
    starts, params = draw_starts(task, physical, np.random.default_rng(HELD_OUT_SEED), episodes)
    model_free = sac_baseline(task, physical, ctx, low, high, seed, quick, budget, threads, starts, params)
    return {
        "task": name,
        "substeps": task.substeps,
        "target_return": task.target_return,
        "episodes": episodes,
        "return_physics": None,
        "return_emulator": None,
        "mujoco_steps": None,
        "wall_s": None,
        "emulator_wall_s": None,
        "model_free": model_free,
    }


# settings the bench's own flags set (--suite-seconds, --seed, --seeds), not --set
BENCH_OWNED = ("seconds", "seed", "seeds")


def _nested_settings(key: str) -> type | None:
    """The settings class a ``RewardSettings`` field holds (``value_iteration`` → ``ValueIteration``,
    ``exploring`` → ``ExploringRuns``, ``copying`` → ``CopySettings``), None for a plain field."""
    hint = typing.get_type_hints(RewardSettings)[key]
    kinds = typing.get_args(hint) or (hint,)
    return next((k for k in kinds if isinstance(k, type) and dataclasses.is_dataclass(k)), None)


def _as_settings(key: str, kind: type, given: dict[str, Any]) -> Any:
    """A JSON object → ``kind`` built from its defaults and the object's fields (lists as tuples);
    ValueError naming a field ``kind`` has not."""
    known = {f.name for f in dataclasses.fields(kind)}
    unknown = sorted(set(given) - known)
    if unknown:
        raise ValueError(f"{key} has no field {', '.join(unknown)}: one of {', '.join(sorted(known))}")
    return kind(**{k: tuple(v) if isinstance(v, list) else v for k, v in given.items()})


def setting_overrides(pairs: list[str]) -> dict[str, Any]:
    """``KEY=VALUE`` strings → ``RewardSettings`` fields for one run, each VALUE read as JSON (a number,
    ``true``, ``null``, a list for a tuple of layers, an object for a field that holds settings of its
    own: ``value_iteration={"candidates": 64}`` is ``ValueIteration(candidates=64)``, the rest its
    defaults, not the task's), else as a string. ValueError naming the pair for a field that is not
    one, one the bench's own flags set, or a value the settings refuse."""
    fields = [f.name for f in dataclasses.fields(RewardSettings)]
    defaults = RewardSettings()
    out: dict[str, Any] = {}
    for pair in pairs:
        key, eq, text = pair.partition("=")
        key = key.strip()
        if not eq or key not in fields:
            raise ValueError(f"--set {pair!r}: expected KEY=VALUE with KEY one of {', '.join(fields)}")
        if key in BENCH_OWNED:
            raise ValueError(f"--set {pair!r}: {key} is set by the bench's own flag")
        try:
            value = json.loads(text)
        except json.JSONDecodeError:
            value = text
        default = getattr(defaults, key)
        if isinstance(value, list):
            value = tuple(value)
        if isinstance(value, dict):
            nested = _nested_settings(key)
            if nested is None:
                raise ValueError(f"--set {pair!r}: {key} holds no settings of its own")
            try:
                value = _as_settings(key, nested, value)
            except (TypeError, ValueError) as refused:
                raise ValueError(f"--set {pair!r}: {refused}") from refused
        number = isinstance(value, (int, float)) and not isinstance(value, bool)
        if isinstance(default, (int, float)) and not isinstance(default, bool) and not number:
            raise ValueError(f"--set {pair!r}: {key} is a number")
        out[key] = value
    try:
        dataclasses.replace(defaults, **out)
    except ValueError as refused:
        raise ValueError(f"--set: {refused}") from refused
    return out


def overrides_echo(overrides: dict[str, Any]) -> dict[str, Any]:
    """``setting_overrides``' result as JSON can write it: settings of their own as their fields."""
    return {
        k: dataclasses.asdict(v) if dataclasses.is_dataclass(v) and not isinstance(v, type) else v
        for k, v in overrides.items()
    }


def agreement_row(agreement: StepAgreement | None) -> dict[str, Any] | None:
    """The step agreement as the row's JSON: rounded, an undefined value (every policy tried earned
    the same on MuJoCo) null."""
    if agreement is None:
        return None
    row = dataclasses.asdict(agreement)
    return {
        k: (None if math.isnan(v) else round(v, 3)) if isinstance(v, float) else v for k, v in row.items()
    }


def bench_suite_task(
    name: str,
    root: Path,
    seconds: float | None,
    seed: int,
    quick: bool,
    save_to: Path | None = None,
    seeds: int | None = None,
    baseline: bool = True,
    overrides: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """One suite task's row (module doc); with ``save_to``, the policy measured is stored there as
    ``neuro policy`` stores one (``policy_store.save_reward_policy``); ``seeds`` side by side instead
    of the task's (``SuiteTask.seeds``); without ``baseline``, no SAC (``model_free`` is None): the
    policy's side alone, in half the time; ``overrides``, ``RewardSettings`` fields changed for this
    run (``setting_overrides``)."""
    task = SUITE_TASKS[name]
    budget = seconds if seconds is not None else task.train_seconds + 300.0
    t0 = time.perf_counter()
    path, emu_wall, emu_steps, trained_here = emulator_for(
        task, root, 60.0 if quick else task.emulator_seconds
    )
    if not trained_here:  # all in: an emulator trained before counts the seconds its training took
        t0 -= emu_wall
    settings = RewardSettings(seconds=max(5.0, budget - (time.perf_counter() - t0)), seed=seed, seeds=seeds)
    if quick:
        settings = RewardSettings(
            seconds=120.0,
            max_iterations=4,
            envs=8,
            horizon=4,
            eval_episodes=2,
            final_episodes=2,
            seed=seed,
            seeds=seeds,
            refine=False,
        )
    settings = dataclasses.replace(settings, **(overrides or {}))
    cores = cores_used(task, settings)
    result = train_reward_policy(task, path, settings)
    wall = time.perf_counter() - t0
    log.info("%s: return on MuJoCo %.1f after %.0f s all in", name, result.return_physics, wall)
    if save_to is not None:
        log.info("%s: stored in %s", name, save_reward_policy(save_to, result, path))

    manifest = registry.read_manifest(path)
    physical = registry.load_physical_model(path, manifest)
    ctx = Context(physical.mj_model, list(manifest.layout))
    low = np.array([c.low for c in manifest.controls])
    high = np.array([c.high for c in manifest.controls])
    episodes = 2 if quick else EPISODES
    starts, params = draw_starts(task, physical, np.random.default_rng(HELD_OUT_SEED), episodes)
    ours = run_on_mujoco(task, physical, ctx, result.policy.act, starts, params)
    # the root's drift on these episodes too, on the emulator the policy is served with
    served = result.emulator if result.emulator is not None else artifacts.load_emulator(path)
    drift = root_drift(FastStep(served), result.policy, ctx, ours, manifest.super_timestep)  # type: ignore[arg-type]
    agreement = step_agreement(
        task, physical, ctx, manifest.substeps, FastStep(served), result.policy, HELD_OUT_SEED,  # type: ignore[arg-type]
        directions=4 if quick else 32, episodes=1 if quick else 4,
        noise=(random_search_of(task, settings) or RandomSearch()).noise,  # the search's own where it searched
    )  # fmt: skip

    model_free = (
        sac_baseline(task, physical, ctx, low, high, seed, quick, wall, cores, starts, params)
        if baseline
        else None
    )
    return {
        "task": name,
        "return_physics": round(float(ours.returns.mean()), 1),
        "return_emulator": round(result.return_emulator, 1),
        "outside_envelope": round(result.outside_share, 4),  # emulated states outside its envelope
        "falls_physics": falls(task, ctx, ours, manifest.super_timestep),
        # metres between the emulator's root and MuJoCo's 1 s into the final episodes, each under the policy
        "root_drift_1s_m": None if result.root_drift_m is None else round(result.root_drift_m, 3),
        # the same on the held-out episodes the return is measured on
        "root_drift_1s_m_held_out": None if drift is None else round(drift, 3),
        # ARS's step at the policy from the emulator's returns against MuJoCo's (None: a policy
        # choosing among candidates)
        "step_agreement": agreement_row(agreement),
        "returns_physics": [round(float(x), 1) for x in ours.returns],
        "target_return": task.target_return,
        "episodes": episodes,
        "mujoco_steps": result.mujoco_steps + emu_steps,
        "mujoco_steps_emulator_data": emu_steps,
        "wall_s": round(wall, 1),
        "emulator_wall_s": round(emu_wall, 1),
        "emulator_trained_here": trained_here,
        "iterations": result.iterations,
        # value iteration's copy beside the greedy policy it copies (None for the actor-critic)
        "greedy_agreement": None if result.greedy_agreement is None else round(result.greedy_agreement, 3),
        "greedy_regret": None if result.greedy_regret is None else round(result.greedy_regret, 4),
        # every seed's return on the training's own final episodes (the kept one the highest), and
        # whose policy or value it took when they met (None: its own)
        "seeds": [
            {"seed": seed + i, "return_physics": round(r, 1), "took_from": took}
            for i, (r, took) in enumerate(zip(result.seed_returns, result.seed_took_from, strict=True))
        ],
        "cores": cores,
        "refinements": result.refinements,
        "history": [
            [t, round(r, 1)] for _, t, r in result.return_history
        ],  # (s, return on MuJoCo) while training
        "substeps": task.substeps,
        "open_loop": {
            "applicable": False,
            "reason": "a reward over whole episodes has no single goal to synthesise for",
        },
        "model_free": model_free,
    }
