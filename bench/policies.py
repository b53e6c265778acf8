"""Feedback policies learned through the emulator, side by side with open-loop synthesis and with
model-free reinforcement learning on MuJoCo, on the same held-out starts and goals.

    python bench/policies.py [--tasks a,b] [--seconds S] [--suite-seconds S] [--artifacts DIR]
                             [--held-out 100] [--open-loop-runs 10] [--algorithm sac|ppo] [--seed 0]
                             [--seeds K] [--threads N] [--no-baseline | --baseline-only] [--quick]
                             [--set KEY=VALUE ...] [--json]

With no ``--tasks``, every task: the catalog's policy tasks, then dm_control's suite tasks
(``control.suite_tasks.SUITE_TASKS``: cartpole-swingup, pendulum-swingup, reacher-hard,
point_mass-easy, ball_in_cup-catch, acrobot-swingup), each of those measured as ``_suite.py`` says:
its emulator at the task's control period (found in ``--artifacts`` or trained), a reward policy
learned through it (``control.reward_policy``) and SAC on MuJoCo for the same wall time, all in
within ``--suite-seconds`` (default 30 minutes), both judged by the suite's reward over 10 episodes
of 1,000 steps on MuJoCo; their rows carry ``return_physics``, ``return_emulator`` and
``model_free.return_physics`` instead of success shares.

For each catalog policy task (``catalog.tasks.POLICY_TASKS``; ``--tasks`` some of them), through the
emulator of the task's super-step (``policy_job.emulator_for``, the data directory over the committed
defaults):

1. the policy learned through the emulator (``PolicyTrainer``: what ``neuro policy`` trains, for the
   task's ``train_seconds`` or ``--seconds``), then run on ``--held-out`` starts and goals drawn with a
   seed of their own (``HELD_OUT_SEED``, never the training's): the starts from the task's box, the
   goals from a goal pool of their own (``policy_data.reached_goals``, the same distribution as the
   training's pool, other samples); success on MuJoCo and on the served emulator as the task's checks
   judge it (``PolicyTrainer.successes``); its MuJoCo steps (the goal pool, its checks on MuJoCo) and
   wall time are the training's;
2. ``open_loop``: the control-synthesis job (``control.job.run_job``) for each of the first
   ``--open-loop-runs`` held-out pairs: the start, the task's target with the goal written in, its
   weights and checks, a horizon of the run's super-steps on the same emulator, and where the job
   catalog has a task of the same name and model, that task's effort weights, initial controls,
   optimizer settings and control spacing (its points per super-step scaled to the emulator's
   super-step); the job's controller replayed on MuJoCo (after its physics refinement) is judged by
   the same checks. A job checks only its final state, so a task whose goal moves or whose checks
   hold before the end of a goal's period (quadrotor-follow) is reported as not applicable, with the
   reason; the policy's success on the same pairs is given beside the job's;
3. ``model_free``: Stable-Baselines3 SAC (``--algorithm ppo`` for PPO) trained on MuJoCo itself
   (``_model_free.PolicyTaskEnv``: the same control period, the policy's own input features, the
   actions scaled to each control's range, reward minus the policy's loss plus a bonus while the
   checks hold, the task's episodes, goals from the policy's own training pool) for the same wall time
   the emulator's policy took, on the same torch threads (``--threads``, as the policy's training
   and the jobs), then run deterministically on the held-out
   set on MuJoCo; its MuJoCo steps are its env steps × the task's substeps plus the goal pool's.
   ``--no-baseline`` leaves it out (``model_free`` null, its columns "-"): the policy's side alone,
   in half a suite task's time; ``--baseline-only`` (suite tasks) is the other half, SAC alone for
   the task's budget (``--suite-seconds``) on ``--threads`` threads, the policy's columns "-".

``--set KEY=VALUE`` (suite tasks; repeatable) changes one of the policy's ``RewardSettings`` for the
run (``noise=0.4``, ``hidden=[256,256]``, ``value_iteration={"candidates": 64}`` for settings of their
own, built from their defaults; echoed as the JSON's ``settings.set``): a variant measured by the
bench's own command, on the same held-out starts.

Prints a table; with ``--json`` the last line is one JSON object ``{"seed", "held_out", "settings",
"tasks": [{"task", "success_physics", "success_emulator", "mujoco_steps", "wall_s", "iterations",
"held_out", "open_loop": {"applicable", "reason", "runs", "success_physics", "policy_success_physics",
"wall_s", "wall_s_per_job", "mujoco_steps"}, "model_free": {"algorithm", "success_physics",
"mujoco_steps", "wall_s", "env_steps", "episodes"}}]}``; success values are shares in [0, 1].
``--quick`` trains for a few seconds on tiny batches, with 16 held-out runs, one short open-loop job:
a smoke test.
"""

from __future__ import annotations

import argparse
import json
import logging
import statistics
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch
from _model_free import ALGORITHMS, run_agent, train_model_free
from _suite import bench_suite_baseline, bench_suite_task, overrides_echo, setting_overrides
from numpy.typing import NDArray

from neuroanimator.artifacts import registry
from neuroanimator.artifacts import store as artifacts
from neuroanimator.catalog.tasks import POLICY_TASKS, TASKS
from neuroanimator.control import policy_job
from neuroanimator.control.job import run_job
from neuroanimator.control.policy import PolicyResult, PolicySettings, PolicyTrainer, frozen_step
from neuroanimator.control.policy_data import reached_goals, sample_starts
from neuroanimator.control.policy_store import save_policy
from neuroanimator.control.suite_tasks import SUITE_TASKS
from neuroanimator.goals.policy_task import PolicyTask

log = logging.getLogger("bench.policies")
FloatArray = NDArray[np.float64]
HELD_OUT_SEED = 90_210  # the held-out starts and goals (training draws with PolicySettings.seed)
QUICK_SECONDS = 60.0  # a cap; --quick stops after QUICK_ITERATIONS updates
QUICK_ITERATIONS = 4
QUICK_HELD_OUT = 16
NO_BASELINE = "- | - | -"  # a row measured with --no-baseline: no model-free columns
QUICK_OPTIMIZER = {
    "max_iterations": 3,
    "starts": 1,
    "global_generations": 0,
    "gauss_newton_iterations": 0,
    "physics_rounds": 1,
}


def policy_settings(task: PolicyTask, args: argparse.Namespace) -> PolicySettings:
    """The task's training: its own budget unless ``--seconds``; tiny batches and no emulator
    refinement with ``--quick``."""
    seconds = args.seconds if args.seconds is not None else task.train_seconds
    if args.quick:
        return PolicySettings(  # a few updates, whatever the machine's load (the budget counts loading)
            seconds=args.seconds or QUICK_SECONDS,
            max_iterations=QUICK_ITERATIONS,
            batch=16,
            refine=False,
            refine_runs=8,
            evaluate_runs=8,
            seed=args.seed,
            threads=args.threads,
        )
    return PolicySettings(seconds=seconds, seed=args.seed, threads=args.threads)


def held_out(judge: PolicyTrainer, task: PolicyTask, runs: int, index: int) -> tuple[FloatArray, FloatArray]:
    """Starts (N, S) and goals (N, P, G) of the held-out set: the task's start box and a goal pool of
    its own, from ``HELD_OUT_SEED`` (one stream per task); a moving goal moves as in training."""
    rng = np.random.default_rng([HELD_OUT_SEED, index])
    pool = reached_goals(judge.physical, task, judge.substeps, rng)
    starts = sample_starts(judge.physical, task, rng, runs)
    return starts, pool.draw_moving(rng, runs, judge.schedule.goals, task.goal.max_move)


# ---------------------------------------------------------------------------- open-loop synthesis
def open_loop_reason(task: PolicyTask) -> str | None:
    """Why a job cannot be judged as the task is (None when it can): a job checks its final state."""
    if task.goals_per_run > 1:
        return (
            f"the goal moves every {task.period_s:g} s and is checked {task.check_s:g} s after each move; "
            "an open-loop job reaches one target, checked at its final state"
        )
    if task.check_s < task.period_s:
        return f"the checks hold {task.check_s:g} s into the run, a job checks its final state"
    return None


def job_request(
    task: PolicyTask, version: str, steps: int, start: FloatArray, goal: FloatArray, quick: bool
) -> dict[str, Any]:
    """The control-synthesis request for one held-out pair (module doc, 2.)."""
    request: dict[str, Any] = {
        "model": task.model,
        "version": version,
        "initial_state": [float(v) for v in start],
        "target_state": task.target_with([float(v) for v in goal]),
        "state_weights": list(task.state_weights),
        "horizon": steps,
        "success": [c.model_dump() for c in task.success],
    }
    optimizer: dict[str, Any] = {}
    same = TASKS.get(task.name)
    if same is not None and same.model == task.model and not same.terms:
        request |= {
            "points_per_step": min(1.0, same.points_per_step * task.substeps / same.substeps),
            "mu_u": same.mu_u,
            "mu_s": same.mu_s,
            "initial_controls": list(same.initial_controls),
        }
        optimizer |= same.optimizer
    if quick:
        optimizer |= QUICK_OPTIMIZER
    if optimizer:
        request["optimizer"] = optimizer
    return request


def open_loop(
    task: PolicyTask,
    judge: PolicyTrainer,
    root: registry.Root,
    version: str,
    starts: FloatArray,
    goals: FloatArray,
    policy_ok: NDArray[np.bool_],
    args: argparse.Namespace,
) -> dict[str, Any]:
    """Jobs on the first ``--open-loop-runs`` held-out pairs, replayed on MuJoCo and judged by the
    task's checks, beside the policy's success on the same pairs."""
    reason = open_loop_reason(task)
    runs = min(1 if args.quick else args.open_loop_runs, len(starts))
    if reason is not None or runs == 0:
        return {"applicable": reason is None, "reason": reason, "runs": 0}
    sch = judge.schedule
    ok: list[bool] = []
    walls: list[float] = []
    mujoco = 0
    for i in range(runs):
        request = job_request(task, version, sch.steps, starts[i], goals[i, 0], args.quick)
        r = run_job(request, root, threads=judge.settings.threads)
        if r.physical is None:  # no controller came back to replay
            ok.append(False)
        else:
            replayed = np.array(r.physical.states, dtype=np.float64)  # None (not finite) becomes nan
            ok.append(bool(judge.successes(replayed[None], goals[i : i + 1])[0]))
        walls.append(r.wall_s or 0.0)
        replays = r.refinement.physics_replays if r.refinement is not None else 1
        mujoco += replays * sch.steps * task.substeps
        log.info("%s open loop %d: %s, %.1f s", task.name, i, "success" if ok[-1] else "missed", walls[-1])
    return {
        "applicable": True,
        "reason": None,
        "runs": runs,
        "success_physics": round(sum(ok) / runs, 4),
        "policy_success_physics": round(float(policy_ok[:runs].mean()), 4),
        "wall_s": round(sum(walls), 2),
        "wall_s_per_job": round(statistics.median(walls), 2),
        "mujoco_steps": mujoco,
    }


# ---------------------------------------------------------------------------- one task
def bench_task(name: str, index: int, root: registry.Root, args: argparse.Namespace) -> dict[str, Any]:
    task = POLICY_TASKS[name]
    path = policy_job.emulator_for(root, task)
    settings = policy_settings(task, args)
    torch.set_num_threads(max(1, settings.threads))  # the same cores for all three
    trainer = PolicyTrainer(task, path, settings)
    result: PolicyResult = trainer.train()
    log.info("%s: trained for %.1f s, %d iterations", name, result.wall_s, result.iterations)
    if args.save_to:  # the policy measured here, stored (the committed defaults are these)
        goals_seen = result.goals if result.goals is not None else trainer.pool.goals
        log.info("%s: stored in %s", name, save_policy(Path(args.save_to), result, goals_seen))

    runs = QUICK_HELD_OUT if args.quick else args.held_out
    starts, goals = held_out(trainer, task, runs, index)
    physics = trainer.run(starts, goals, physics=True)
    trainer.step = frozen_step(artifacts.load_emulator(path))  # the served emulator, not a refined copy
    emulator = trainer.run(starts, goals, physics=False)

    looped = open_loop(task, trainer, root, path.name, starts, goals, physics.success, args)

    model_free = None
    if args.baseline:
        free = train_model_free(
            args.algorithm, trainer, result.net.shape, result.wall_s, args.seed, args.quick
        )
        free_states = run_agent(free.agent, trainer, result.net.shape, starts, goals)
        model_free = {
            "algorithm": free.algorithm,
            "success_physics": round(float(trainer.successes(free_states, goals).mean()), 4),
            "mujoco_steps": free.env_steps * task.substeps + trainer.pool.mujoco_steps,
            "wall_s": round(free.wall_s, 2),
            "env_steps": free.env_steps,
            "episodes": free.episodes,
        }
    return {
        "task": name,
        "held_out": runs,
        "success_physics": round(physics.rate, 4),
        "success_emulator": round(emulator.rate, 4),
        "mujoco_steps": result.mujoco_steps,
        "wall_s": round(result.wall_s, 2),
        "iterations": result.iterations,
        "open_loop": looped,
        "model_free": model_free,
    }


def table(rows: list[dict[str, Any]]) -> str:
    head = (
        "| task | held-out | policy: MuJoCo | policy: emulator | policy: MuJoCo steps | policy: wall s | "
        "open loop: MuJoCo (runs) | policy on those runs | open loop: s per job | model-free: MuJoCo | "
        "model-free: MuJoCo steps | model-free: wall s |"
    )
    lines = [head, "|" + "---|" * 12]
    for r in rows:
        ol, mf = r["open_loop"], r["model_free"]
        if ol["applicable"] and ol["runs"]:
            ol_cells = f"{ol['success_physics']:.2f} ({ol['runs']}) | {ol['policy_success_physics']:.2f} | {ol['wall_s_per_job']}"
        else:
            ol_cells = "n/a | - | -"
        mf_cells = (
            f"{mf['success_physics']:.2f} ({mf['algorithm']}) | {mf['mujoco_steps']:,} | {mf['wall_s']}"
            if mf
            else NO_BASELINE
        )
        lines.append(
            f"| {r['task']} | {r['held_out']} | {r['success_physics']:.2f} | {r['success_emulator']:.2f} | "
            f"{r['mujoco_steps']:,} | {r['wall_s']} | {ol_cells} | {mf_cells} |"
        )
    notes = [
        f"{r['task']}: open loop not applicable: {r['open_loop']['reason']}"
        for r in rows
        if r["open_loop"]["reason"]
    ]
    return "\n".join(lines + notes)


def suite_table(rows: list[dict[str, Any]]) -> str:
    head = (
        "| task | n | return: MuJoCo | return: emulator | target | MuJoCo steps | wall s (emulator) | "
        "SAC: MuJoCo | SAC: MuJoCo steps | SAC: wall s |"
    )
    lines = [head, "|" + "---|" * 10]
    for r in rows:
        mf = r["model_free"]
        mf_cells = (
            f"{mf['return_physics']:.1f} | {mf['mujoco_steps']:,} | {mf['wall_s']}" if mf else NO_BASELINE
        )
        ours = (  # a row of --baseline-only has no policy
            f"{r['return_physics']:.1f} | {r['return_emulator']:.1f}"
            if r["return_physics"] is not None
            else "- | -"
        )
        spent = (
            f"{r['mujoco_steps']:,} | {r['wall_s']} ({r['emulator_wall_s']})"
            if r["wall_s"] is not None
            else "- | -"
        )
        lines.append(
            f"| {r['task']} | {r['substeps']} | {ours} | {r['target_return']:g} | {spent} | {mf_cells} |"
        )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--tasks", default=",".join([*POLICY_TASKS, *SUITE_TASKS]))
    p.add_argument(
        "--seconds", type=float, default=None, help="each policy's training budget (default: the task's)"
    )
    p.add_argument(
        "--suite-seconds",
        type=float,
        default=None,
        help="a suite task's budget, all in: its emulator and its policy (default: 30 minutes)",
    )
    p.add_argument(
        "--artifacts",
        help="where the suite tasks' emulators are found, or trained and kept (default: the data directory)",
    )
    p.add_argument("--held-out", type=int, default=100, help="held-out starts and goals per task")
    p.add_argument("--open-loop-runs", type=int, default=10, help="held-out pairs given to open-loop jobs")
    p.add_argument("--algorithm", choices=ALGORITHMS, default="sac", help="the model-free baseline")
    p.add_argument(
        "--no-baseline",
        dest="baseline",
        action="store_false",
        help="no model-free baseline: the policy's side alone (each row's model_free null)",
    )
    p.add_argument(
        "--baseline-only",
        action="store_true",
        help="suite tasks: the model-free baseline alone for the task's budget on --threads threads, no policy",
    )
    p.add_argument("--seed", type=int, default=0, help="the training's seed (policy and model-free)")
    p.add_argument(
        "--seeds",
        type=int,
        default=None,
        help="a suite task's policy seeds side by side, one core each (default: the task's)",
    )
    p.add_argument(
        "--threads",
        type=int,
        default=PolicySettings().threads,
        help="torch threads for all three (the policy's training default)",
    )
    p.add_argument("--quick", action="store_true", help="seconds of training, 16 held-out runs: a smoke test")
    p.add_argument("--save-to", help="also store each trained policy in this artifact folder")
    p.add_argument(
        "--set",
        dest="overrides",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help=(
            "suite tasks: one of the policy's RewardSettings for this run (noise=0.4, hidden=[256,256],"
            ' value_iteration={"candidates": 64}); repeatable'
        ),
    )
    p.add_argument("--json", action="store_true")
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="%(name)s: %(message)s")
    logging.getLogger("bench").setLevel(logging.INFO)
    names = args.tasks.split(",")
    unknown = [n for n in names if n not in POLICY_TASKS and n not in SUITE_TASKS]
    if unknown:
        p.error(f"--tasks: unknown policy tasks {unknown}; expected some of {[*POLICY_TASKS, *SUITE_TASKS]}")
    if args.baseline_only and (not args.baseline or [n for n in names if n not in SUITE_TASKS]):
        p.error("--baseline-only measures suite tasks' baseline: no --no-baseline, and suite --tasks only")
    if args.seeds is not None and args.seeds < 1:
        p.error(f"--seeds must be >= 1, got {args.seeds}")
    if args.held_out < 1 or args.open_loop_runs < 0 or args.threads < 1:
        p.error(
            "--held-out and --threads must be >= 1 and --open-loop-runs >= 0, got "
            f"{args.held_out}, {args.threads} and {args.open_loop_runs}"
        )
    try:
        overrides = setting_overrides(args.overrides)
    except ValueError as refused:
        p.error(str(refused))
    if overrides and (args.baseline_only or [n for n in names if n not in SUITE_TASKS]):
        p.error("--set changes a suite task's policy settings: suite --tasks only, and not --baseline-only")
    root = registry.Roots.default()
    t0 = time.perf_counter()
    rows = []
    suite_root = Path(args.artifacts) if args.artifacts else registry.writable(root)
    for name in names:
        if args.baseline_only:
            rows.append(bench_suite_baseline(name, args.suite_seconds, args.seed, args.quick, args.threads))
        elif name in SUITE_TASKS:
            save_to = Path(args.save_to) if args.save_to else None
            rows.append(
                bench_suite_task(
                    name,
                    suite_root,
                    args.suite_seconds,
                    args.seed,
                    args.quick,
                    save_to,
                    args.seeds,
                    args.baseline,
                    overrides,
                )
            )
        else:
            rows.append(bench_task(name, list(POLICY_TASKS).index(name), root, args))
        log.info("%s: done (%.0f s)", name, time.perf_counter() - t0)
    catalog_rows = [r for r in rows if r["task"] in POLICY_TASKS]
    suite_rows = [r for r in rows if r["task"] in SUITE_TASKS]
    if catalog_rows:
        print(table(catalog_rows))
    if suite_rows:
        print(suite_table(suite_rows))
    if args.json:
        settings = {
            "seconds": args.seconds,
            "algorithm": args.algorithm,
            "threads": args.threads,
            "seeds": args.seeds,
            "baseline": args.baseline,
            "baseline_only": args.baseline_only,
            "quick": args.quick,
            "set": overrides_echo(overrides),  # (a tuple of layers is written as a JSON list)
        }
        held = QUICK_HELD_OUT if args.quick else args.held_out
        print(json.dumps({"seed": HELD_OUT_SEED, "held_out": held, "settings": settings, "tasks": rows}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
