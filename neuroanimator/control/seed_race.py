"""Reward policies trained from several seeds side by side, one process each, and the best kept.

Through a contact emulator the same settings give policies far apart by their seed alone: the walker
stood in every episode from two seeds and stayed on the floor in six of ten from a third
(docs/experiments/policies.md). The actor-critic's matrices are small, so a second core buys it more
as a second seed than as a second thread; value iteration's backups are wide matrices, and a task
may ask for threads instead (``SuiteTask.threads``, the acrobot's two: 1.5 times the iterations in
the same budget, measured), which a seed trained alone takes (``thread_count``). Each seed trains in
its own process (``spawn``: a fresh interpreter, nothing shared with the caller's PyTorch), every one
is judged at the end on the same MuJoCo episodes (``RewardSettings.final_seed``), and the highest
return is the result, every seed's return kept beside it (``RewardResult.seed_returns``).

Each seed's process imports the caller's main module, as every ``spawn`` does: a script that calls
this keeps its own code under ``if __name__ == "__main__":`` (a notebook, a service need nothing).

With ``RewardSettings.meet_at`` the seeds meet once, at their first check on MuJoCo past that share
of the budget (population-based training's exploit step): each sends its best return so far with the
policy that earned it and its critics; once every seed still training has met, the best keeps its
own and the others take its policy and critics, and train on from their own draws (a seed that ended
before meeting is not waited for). Each result says whose policy it took (``RewardResult.took_from``).
With value iteration's ``meet`` they meet instead once their values are fitted, and those behind take
the best one's value (``RewardTrainer.meet_over_values``).

Progress reaches the caller's ``on_progress`` as one stream (the best return so far, the MuJoCo steps
of all seeds together); ``should_stop`` stops them all, each keeping its best policy so far.
"""

from __future__ import annotations

import logging
import multiprocessing as mp
import os
import pickle
import queue
import time
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Any, cast

from neuroanimator.control.reward_policy import (
    Meeting,
    RewardProgress,
    RewardResult,
    RewardSettings,
    RewardTrainer,
    seeds_meet,
)
from neuroanimator.control.suite_tasks import SuiteTask
from neuroanimator.control.threads import torch_threads

log = logging.getLogger(__name__)

POLL_S = 0.5  # how often the caller's ``should_stop`` is asked while the seeds train


def seed_count(task: SuiteTask, settings: RewardSettings) -> int:
    """How many seeds train side by side: ``settings.seeds``, else the task's, at most the cores."""
    wanted = settings.seeds if settings.seeds is not None else task.seeds
    return max(1, min(wanted, os.cpu_count() or 1))


def thread_count(task: SuiteTask, settings: RewardSettings) -> int:
    """Torch threads of a seed trained alone: ``settings.threads``, else the task's, at most the cores."""
    wanted = settings.threads if settings.threads is not None else task.threads
    return max(1, min(wanted, os.cpu_count() or 1))


def cores_used(task: SuiteTask, settings: RewardSettings) -> int:
    """The cores a training takes: one a seed when several train side by side, else its threads."""
    seeds = seed_count(task, settings)
    return seeds if seeds > 1 else thread_count(task, settings)


def train_reward_policy(
    task: SuiteTask,
    path: Path,
    settings: RewardSettings | None = None,
    on_progress: Callable[[RewardProgress], None] | None = None,
    should_stop: Callable[[], bool] | None = None,
) -> RewardResult:
    """Train a policy for a reward task through the emulator artifact at ``path`` (``reward_policy``),
    from ``seed_count`` seeds side by side, and return the best; ``should_stop`` ends it early (``stop``
    is then ``cancelled``), the best policy so far kept."""
    settings = settings or RewardSettings(seconds=task.train_seconds)
    seeds = seed_count(task, settings)
    portable = _portable(task) if seeds > 1 else None
    if portable is None:
        if seeds > 1:
            log.info("%s: its task cannot be sent to another process; one seed trains", task.name)
        return _one_seed_here(task, path, settings, on_progress, should_stop)
    return _race(task, portable, path, settings, seeds, on_progress, should_stop)


def _portable(task: SuiteTask) -> SuiteTask | Callable[[], SuiteTask] | None:
    """What another process is sent to have the task: the task, else its ``rebuild`` call, else None."""
    if _sendable(task):
        return task
    if task.rebuild is not None and _sendable(task.rebuild):
        return task.rebuild
    return None


def _one_seed_here(
    task: SuiteTask,
    path: Path,
    settings: RewardSettings,
    on_progress: Callable[[RewardProgress], None] | None,
    should_stop: Callable[[], bool] | None,
    meet: Callable[[Meeting], Meeting | None] | None = None,
) -> RewardResult:
    with torch_threads(thread_count(task, settings)):
        return RewardTrainer(task, path, settings, on_progress, should_stop, meet).train()


def _sendable(thing: object) -> bool:
    """Whether ``thing`` pickles (a built-in task's functions do; a closure does not)."""
    try:
        pickle.dumps(thing)
    except (pickle.PicklingError, AttributeError, TypeError):
        return False
    return True


def _race(
    task: SuiteTask,
    portable: SuiteTask | Callable[[], SuiteTask],
    path: Path,
    settings: RewardSettings,
    seeds: int,
    on_progress: Callable[[RewardProgress], None] | None,
    should_stop: Callable[[], bool] | None,
) -> RewardResult:
    t0 = time.perf_counter()
    ctx = mp.get_context("spawn")
    messages = ctx.Queue()
    replies = [ctx.Queue() for _ in range(seeds)]  # each seed's answer when the seeds meet
    stop = ctx.Event()
    level = logging.getLogger().getEffectiveLevel()
    # every seed on one core, judged on the same final episodes
    each = replace(settings, threads=1, seeds=1, final_seed=settings.judged_on)
    workers = [
        ctx.Process(
            target=_seed_worker,
            args=(
                i,
                portable,
                path,
                replace(each, seed=settings.seed + i),
                messages,
                replies[i],
                stop,
                level,
                time.time(),
            ),
            name=f"{task.name}-seed-{settings.seed + i}",
            daemon=False,  # a seed's training may start processes of its own (MuJoCo's sampling)
        )
        for i in range(seeds)
    ]
    for w in workers:
        w.start()
    log.info(
        "%s: %d seeds side by side (%s)",
        task.name,
        seeds,
        ", ".join(str(settings.seed + i) for i in range(seeds)),
    )
    results: dict[int, RewardResult] = {}
    latest: dict[int, RewardProgress] = {}
    met: dict[int, Meeting] | None = {} if seeds_meet(task, settings) else None
    try:
        while len(results) < seeds:
            if should_stop is not None and should_stop():
                stop.set()
            if met and all(j in met or j in results for j in range(seeds)):
                _answer(task, met, replies)
                met = None
            try:
                kind, i, payload = messages.get(timeout=POLL_S)
            except queue.Empty:
                _check_alive(workers, results)
                continue
            if kind == "meet":
                if met is not None:
                    met[i] = pickle.loads(payload)
            elif kind == "progress":
                latest[i] = payload
                if on_progress is not None and i == 0:  # one report per iteration of the first seed
                    on_progress(_merged(latest))
            elif kind == "result":
                results[i] = pickle.loads(payload)
            else:  # "error": the seed's exception, raised here as it would be with one seed
                raise payload
    finally:
        stop.set()
        for w in workers:
            w.join(timeout=10)
            if w.is_alive():
                w.terminate()
    returns = [results[i].return_physics for i in range(seeds)]
    took = {settings.seed + i: r.took_from for i, r in results.items() if r.took_from is not None}
    best = max(range(seeds), key=lambda i: returns[i])
    log.info(
        "%s: seeds %s returned %s on the same MuJoCo episodes%s; seed %d kept",
        task.name,
        [settings.seed + i for i in range(seeds)],
        [round(r, 1) for r in returns],
        "".join(f" (seed {a} had taken seed {b}'s policy or value)" for a, b in took.items()),
        settings.seed + best,
    )
    return replace(
        results[best],
        task=task,
        seed_returns=returns,
        seed_took_from=[results[i].took_from for i in range(seeds)],
        mujoco_steps=sum(r.mujoco_steps for r in results.values()),
        wall_s=time.perf_counter() - t0,
    )


def _answer(task: SuiteTask, met: dict[int, Meeting], replies: list[Any]) -> None:
    """Every seed still training has met (``seeds_meet``): the best one keeps its own, the others
    are sent what it brought (its policy and critics, or its value)."""
    top = max(met.values(), key=lambda m: m.best_return)
    log.info(
        "%s: the seeds met (best returns %s); seed %d's goes on in all",
        task.name,
        {m.seed: round(m.best_return, 1) for m in met.values()},
        top.seed,
    )
    sent = pickle.dumps(top)
    for i, m in met.items():
        replies[i].put(None if m.seed == top.seed else sent)


def _check_alive(workers: list[Any], results: dict[int, RewardResult]) -> None:
    """A seed's process that ended without a result (killed, out of memory) fails the training."""
    for i, w in enumerate(workers):
        if i not in results and not w.is_alive() and w.exitcode is not None:
            raise RuntimeError(
                f"seed {i}'s process ended with exit code {w.exitcode} before its result (its error is "
                "on stderr; a script that trains from several seeds keeps its own code under "
                "`if __name__ == '__main__':`, as each seed's process imports it)"
            )


def _merged(latest: dict[int, RewardProgress]) -> RewardProgress:
    """The seeds' progress as one: the first seed's iteration and loss, the best return on MuJoCo so
    far, every seed's MuJoCo steps, the longest elapsed time."""
    first = latest[0]
    returns = [p["return_physics"] for p in latest.values() if p["return_physics"] is not None]
    return {
        "iteration": first["iteration"],
        "loss": first["loss"],
        "return_physics": max(returns) if returns else None,
        "mujoco_steps": sum(p["mujoco_steps"] for p in latest.values()),
        "elapsed_s": max(p["elapsed_s"] for p in latest.values()),
    }


def _seed_worker(
    index: int,
    portable: SuiteTask | Callable[[], SuiteTask],
    path: Path,
    settings: RewardSettings,
    messages: Any,
    reply: Any,
    stop: Any,
    level: int,
    started: float,
) -> None:
    """One seed's training in its own process: progress, then the result (or the error) on ``messages``;
    it logs at the caller's ``level``, each line naming its seed. Its budget counts from ``started``
    (the caller's wall clock when it started the seeds), the process's start and imports included."""
    settings = replace(settings, seconds=max(1.0, settings.seconds - (time.time() - started)))
    logging.basicConfig(
        level=level, format=f"%(asctime)s seed {settings.seed} %(levelname)s %(name)s: %(message)s"
    )
    parent = os.getppid()

    def should_stop() -> bool:  # told to, or the caller is gone (its seeds do not outlive it)
        return bool(stop.is_set()) or os.getppid() != parent

    def meet(mine: Meeting) -> Meeting | None:  # waits for the other seeds (``_answer``)
        messages.put(("meet", index, pickle.dumps(mine)))
        while not should_stop():
            try:
                answer = reply.get(timeout=POLL_S)
            except queue.Empty:
                continue
            return None if answer is None else cast(Meeting, pickle.loads(answer))
        return None

    try:
        task = portable if isinstance(portable, SuiteTask) else portable()
        result = _one_seed_here(
            task,
            path,
            settings,
            lambda p: messages.put(("progress", index, p)),
            should_stop,
            meet if seeds_meet(task, settings) else None,
        )
    except Exception as e:  # sent back whole, so the caller raises what one seed would have raised
        messages.put(("error", index, e if _sendable(e) else RuntimeError(f"{type(e).__name__}: {e}")))
        return
    # as bytes: a queue would hand the tensors over as shared memory that ends with this process; the
    # task stays here (the caller has it, and a user's task does not pickle)
    messages.put(("result", index, pickle.dumps(replace(result, task=cast(SuiteTask, None)))))
