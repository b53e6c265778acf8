"""``perform_policy``: one run of a policy job, inside the worker's forked job process (``execution.perform``
starts the run and hands a policy job over to this).

``run_policy_job`` trains the task's policy (a built-in task by name, a user's task built from the
job's spec) through its emulator and stores it beside the emulator, under the service's data
directory; meanwhile the job's ``Watch`` keeps its lease and reads its flags, which ``should_stop``
returns, and each iteration's ``PolicyProgress`` goes to Redis as a ``progress`` event. PyTorch is loaded here, after the fork, as for a control job.

How a run ends:
- trained for its budget: succeeded, the result naming the stored policy (its manifest);
- cancelled by DELETE: cancelled; the best policy so far is stored (``train_policy`` returns it and
  ``run_policy_job`` stores it) and the result names it (``policy.metrics.stop`` is ``cancelled``),
  unless it was cancelled before its first check on MuJoCo: then nothing is stored;
- past its budget plus ``POLICY_OVERHEAD_S``: failed ("time limit"), the best policy so far stored;
- its worker is shutting down: back on the queue, without counting as a failure;
- ``PolicyJobError`` (no emulator at the task's super-step), ``GoalsUnreachable`` (MuJoCo reached no
  goal of the task) or ``TaskDefinitionError`` (a user's task that no longer builds): failed with the
  message, nothing stored;
- any other exception: back on the queue while ``JOB_RETRIES`` allows, else failed.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from typing import TYPE_CHECKING, Any, Literal

from neuroanimator.artifacts import registry
from neuroanimator.artifacts.policies import read_policy
from neuroanimator.catalog.suite import SUITE_TASK_INFO
from neuroanimator.contracts.controller import HistoryPoint, PolicyOutcome, RewardTaskSpec
from neuroanimator.core.policy_manifest import PolicyManifest
from neuroanimator.goals.policy_task import PolicyTask
from services.common.job_worker import Watch
from services.common.jobs import JobRecord
from services.controller.custom_policy import TaskDefinitionError, build_task
from services.controller.execution import Deadline, ProgressRecorder
from services.controller.policies import PolicyJobSpec, thin
from services.controller.settings import Settings
from services.controller.store import JobStore

if TYPE_CHECKING:  # (PyTorch is loaded in the job process only)
    from neuroanimator.control.suite_tasks import SuiteTask

log = logging.getLogger(__name__)
Ending = Literal["succeeded", "failed", "cancelled"]


class PolicyRecorder(ProgressRecorder):
    """``on_progress`` of a policy's training: each ``PolicyProgress`` into Redis (best effort), and
    every iteration's loss kept for the result."""

    def __init__(self, store: JobStore, job_id: str, attempt: int) -> None:
        super().__init__(store, job_id, attempt)
        self.losses: list[float | None] = []

    def record(self, p: Mapping[str, object]) -> None:
        loss = p.get("loss")
        self.losses.append(float(loss) if isinstance(loss, (int, float)) else None)
        self.store.policy_progress(self.job_id, self.attempt, p)


def for_a_reward(spec: PolicyJobSpec) -> bool:
    """Whether the job trains a policy for a reward (``RewardSettings``): a suite task's, or a user's
    reward task's."""
    if spec.definition is None:
        return spec.task in SUITE_TASK_INFO
    return isinstance(spec.definition, RewardTaskSpec)


def training_settings(spec: PolicyJobSpec, threads: int | None) -> dict[str, Any]:
    """``PolicySettings``'s arguments for a job (a suite task's: ``RewardSettings``'s, its batch the
    episodes run side by side): what the spec sets (None: the trainer's default). ``threads`` are the
    operator's (``WORKER_THREADS``); None: the task's own (``SuiteTask.threads``) for a reward, one
    otherwise."""
    reward = for_a_reward(spec)
    given = {
        "seed": spec.seed,
        "envs" if reward else "batch": spec.batch,
        **({"seeds": spec.seeds} if reward else {}),
    }
    return {
        "seconds": spec.seconds,
        "refine": spec.refine,
        "hidden": tuple(spec.hidden),
        **({"threads": threads} if threads is not None else {}),
        **{k: v for k, v in given.items() if v is not None},
    }


def _task(spec: PolicyJobSpec, root: registry.Root) -> PolicyTask | SuiteTask | str:
    """A user's task built from its queued definition (a reward task on the model of the emulator it
    was queued for), else the built-in task's name."""
    if spec.definition is None:
        return spec.task
    if isinstance(spec.definition, RewardTaskSpec):
        from neuroanimator.control.reward_terms import RewardTaskError, reward_task_at

        try:
            emulator = registry.resolve(root, spec.model, spec.emulator_version)
            return reward_task_at(spec.definition, emulator)
        except registry.ArtifactError as exc:
            raise TaskDefinitionError("", f"policy task {spec.task!r}: {exc}") from exc
        except RewardTaskError as exc:  # a body the model lacks: the API cannot read the MJCF
            raise TaskDefinitionError("", f"policy task {spec.task!r}: task.{exc}") from exc
    try:
        return build_task(spec.definition, spec.labels or [])
    except ValueError as exc:  # checked when queued: only a change of the code since gets here
        raise TaskDefinitionError("", f"policy task {spec.task!r} does not build: {exc}") from exc


def perform_policy(store: JobStore, s: Settings, rec: JobRecord, delivery: int, worker: str) -> str:
    """Run a started delivery of a policy job (``store.start`` made ``rec`` running); returns how it
    ended (for RQ's log)."""
    spec = PolicyJobSpec.model_validate_json(rec.spec)
    job_id = rec.id
    watch = Watch(store, job_id, delivery, worker)
    watch.start()
    limit_s = spec.seconds + s.policy_overhead_s
    clock = Deadline(watch, limit_s)
    recorder = PolicyRecorder(store, job_id, rec.attempt)
    log.info("policy job started", extra={"job": job_id, "attempt": rec.attempt, "policy_task": spec.task})
    try:
        from neuroanimator.control.policy import PolicySettings
        from neuroanimator.control.policy_data import GoalsUnreachable
        from neuroanimator.control.policy_job import PolicyJobError, run_policy_job, worth_storing
        from neuroanimator.control.reward_policy import RewardSettings

        how = training_settings(spec, s.worker_threads)

        def should_store(result: Any) -> tuple[bool, str]:
            """Nothing is stored by a run that hands its job back (shutdown, taken over by another)."""
            if watch.yielding or watch.superseded:
                return False, "the run handed its job back"
            return worth_storing(result)

        try:
            done = run_policy_job(
                _task(spec, s.roots()),
                s.roots(),
                RewardSettings(**how) if for_a_reward(spec) else PolicySettings(**how),
                on_progress=recorder,
                should_stop=clock.should_stop,
                emulator_version=spec.emulator_version,
                should_store=should_store,
            )
        except (PolicyJobError, GoalsUnreachable, TaskDefinitionError) as exc:
            # a re-run would fail the same way
            failed = PolicyOutcome(
                status="failed",
                reason=str(exc),
                iterations=len(recorder.losses),
                loss_history=thin(recorder.losses),
            )
            store.finish(job_id, delivery, failed)
            return "failed"
    except Exception as exc:
        then = store.requeue_or_fail(job_id, delivery, f"{type(exc).__name__}: {exc}", count_failure=True)
        log.exception("policy job raised", extra={"job": job_id, "outcome": then})
        raise
    finally:
        watch.stop()
    stopped = done.result.stop == "cancelled"  # should_stop said so: cancel, shutdown, superseded or time
    if stopped and not watch.cancelled:
        if watch.superseded:  # another run of this job took over (this worker had seemed dead)
            return "superseded"
        if watch.yielding:
            store.requeue_or_fail(job_id, delivery, f"worker {worker} shut down", count_failure=False)
            return "requeued"
    if done.folder is None:  # cancelled before its first check on MuJoCo: nothing worth keeping
        why = (
            f"time limit of {limit_s:g} s (the budget plus POLICY_OVERHEAD_S) reached"
            if clock.timed_out
            else ""
        )
        cancelled = PolicyOutcome(
            status="cancelled" if watch.cancelled else "failed",
            reason=f"{why + ': ' if why else ''}{done.stored_reason}; nothing stored",
            iterations=done.result.iterations,
            loss_history=thin(recorder.losses),
        )
        store.finish(job_id, delivery, cancelled)
        return cancelled.status
    manifest = read_policy(done.folder)
    status, reason = _ending(stopped and watch.cancelled, clock.timed_out, limit_s, manifest)
    outcome = PolicyOutcome(
        status=status,
        reason=reason,
        policy=manifest,
        iterations=done.result.iterations,
        loss_history=thin(recorder.losses),
        success_history=[
            HistoryPoint(iteration=i, value=v) for i, v in getattr(done.result, "success_history", [])
        ],
        return_history=[
            HistoryPoint(iteration=i, value=v) for i, _, v in getattr(done.result, "return_history", [])
        ],
    )
    store.finish(job_id, delivery, outcome)
    return status


def _ending(
    cancelled: bool, timed_out: bool, limit_s: float, policy: PolicyManifest
) -> tuple[Ending, str | None]:
    """(status, reason) of a run that stored ``policy``: cancelled by DELETE, past its time limit, or done."""
    kept = (
        f"after {policy.metrics.iterations} iterations; the best policy so far is stored as "
        f"{policy.model}/{policy.name} version {policy.version}"
    )
    if cancelled:
        return "cancelled", f"cancelled {kept}"
    if timed_out:
        return "failed", f"time limit of {limit_s:g} s (the budget plus POLICY_OVERHEAD_S) reached {kept}"
    return "succeeded", None
