"""Writing a trained policy as a versioned artifact beside its emulator (``artifacts.policies`` reads it).

``<data>/policies/<model>/<name>/<version>/``: ``policy.onnx``, ``policy.pt`` (weights and the
network's shape, for the torch path) and ``policy.json`` (``PolicyManifest``); the ``latest`` pointer
moves to it. Versions are named ``p-<UTC time>``.

A reward policy (``reward_policy``: a suite task's) is stored the same way and served the same way:
its ``goal`` is its task's parameters (the reacher's target; none for most), the goal envelope the
range they were drawn from, its metrics returns instead of success shares; its ``policy.pt`` holds
its weights (its features are rebuilt from its task and emulator). The emulator a reward policy
fine-tuned while it learned is stored as a version of its own beside the model's (``Manifest.tuned``):
the policy's ``emulator_version`` names it, so its sessions run the emulator it learned through.
"""

from __future__ import annotations

import datetime as dt
from collections.abc import Mapping
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import torch
from numpy.typing import NDArray

from neuroanimator.artifacts.policies import POLICIES_DIR, POLICY_FILE, POLICY_ONNX, POLICY_WEIGHTS
from neuroanimator.artifacts.registry import LATEST, Root, read_manifest, resolve, writable, write_pointer
from neuroanimator.artifacts.store import save_tuned
from neuroanimator.control.policy import PolicyResult, Schedule
from neuroanimator.control.policy_net import PolicyNet, PolicyShape
from neuroanimator.control.reward_policy import RewardPolicy, RewardResult
from neuroanimator.control.suite_tasks import SuiteTask
from neuroanimator.core.manifest import Manifest, Tuning
from neuroanimator.core.policy_manifest import PolicyFall, PolicyManifest, PolicyMetrics
from neuroanimator.export.policy import policy_to_onnx


def _about(version: str, m: Manifest) -> dict[str, Any]:
    """A policy manifest's fields that say which version it is and which emulator it drives."""
    return {
        "version": version,
        "created": dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
        "model": m.model,
        "emulator_version": m.version,
        "substeps": m.substeps,
        "super_timestep": m.super_timestep,
        "state_size": m.state_size,
        "state_labels": list(m.state_labels),
        "control_names": [c.name for c in m.controls],
    }


def _how_it_ran(result: PolicyResult | RewardResult) -> dict[str, Any]:
    """A policy's metrics that either kind of training reports: its runs, steps, iterations, time."""
    return {
        "evaluate_runs": result.evaluate_runs,
        "mujoco_steps": result.mujoco_steps,
        "iterations": result.iterations,
        "refinements": result.refinements,
        "wall_s": round(result.wall_s, 2),
        "stop": result.stop,
    }


def policy_manifest(result: PolicyResult, version: str, goals: np.ndarray) -> PolicyManifest:
    """The manifest of a trained policy; ``goals`` (N, G) are those it was trained for."""
    task, m = result.task, result.manifest
    schedule = Schedule(task, m.super_timestep)
    default = np.median(goals, axis=0)
    return PolicyManifest(
        name=task.name,
        **_about(version, m),
        goal_variables=list(task.goal.variables),
        goal_low=[float(v) for v in goals.min(axis=0)],
        goal_high=[float(v) for v in goals.max(axis=0)],
        goal_default=[float(v) for v in default],
        timed=task.timed,
        goal_period_steps=schedule.per_goal,
        check_steps=schedule.check,
        description=task.summary,
        task=task.to_dict(),
        metrics=PolicyMetrics(
            success_physics=result.success_physics,
            success_emulator=result.success_emulator,
            **_how_it_ran(result),
        ),
    )


def reward_policy_manifest(result: RewardResult, emulator: Manifest, version: str) -> PolicyManifest:
    """The manifest of a trained reward policy through ``emulator``: its goal the task's parameters."""
    task = result.task
    params = result.params if result.params is not None else np.zeros((1, len(task.params)))
    low = list(task.param_low) or [float(v) for v in params.min(axis=0)]
    high = list(task.param_high) or [float(v) for v in params.max(axis=0)]
    return _task_manifest(
        task,
        emulator,
        version,
        low,
        high,
        [float(v) for v in np.median(params, axis=0)],
        PolicyMetrics(
            return_physics=round(result.return_physics, 2),
            return_emulator=round(result.return_emulator, 2),
            outside_envelope=round(result.outside_share, 4),
            root_drift_m=None if result.root_drift_m is None else round(result.root_drift_m, 4),
            falls=[PolicyFall(**f) for f in result.falls],
            seed_returns=[round(r, 2) for r in result.seed_returns],
            **_how_it_ran(result),
        ),
    )


def _task_manifest(
    task: SuiteTask,
    emulator: Manifest,
    version: str,
    low: list[float],
    high: list[float],
    default: list[float],
    metrics: PolicyMetrics,
) -> PolicyManifest:
    """The manifest of a policy of a reward task: its goal the task's parameters over [low, high]."""
    return PolicyManifest(
        name=task.name,
        **_about(version, emulator),
        goal_variables=list(task.params),
        goal_low=low,
        goal_high=high,
        goal_default=default,
        goal_period_steps=task.policy_steps,
        check_steps=task.policy_steps,
        description=task.summary,
        task=task.to_dict(),
        metrics=metrics,
    )


def _new_folder(root: Root, model: str, name: str, when: dt.datetime | None) -> tuple[Path, str]:
    """A new, empty version folder of a model's policy and its version name."""
    when = when or dt.datetime.now(dt.UTC)
    base = writable(root) / POLICIES_DIR / model / name
    version = "p-" + when.strftime("%Y%m%dT%H%M%S")
    n = 1
    while (base / version).exists():
        n += 1
        version = "p-" + when.strftime("%Y%m%dT%H%M%S") + f"-{n}"
    folder = base / version
    folder.mkdir(parents=True)
    return folder, version


def _write(folder: Path, graph: bytes, weights: Mapping[str, object], manifest: PolicyManifest) -> Path:
    """The version's files, then the ``latest`` pointer (last: a reader never sees a half-written one)."""
    (folder / POLICY_ONNX).write_bytes(graph)
    torch.save(dict(weights), folder / POLICY_WEIGHTS)
    (folder / POLICY_FILE).write_text(manifest.model_dump_json(indent=2))
    write_pointer(folder.parent, LATEST, folder.name)
    return folder


def _emulator_it_names(root: Root, base: Path, result: PolicyResult | RewardResult) -> Path:
    """The version folder a policy trained through the version at ``base`` names: the emulator it
    fine-tuned while it learned, stored first as a version of its own (``store.save_tuned``), else
    ``base``."""
    if result.emulator is None:
        return base
    tuning = Tuning(from_version=base.name, task=result.task.name, refinements=max(1, result.refinements))
    return save_tuned(root, base, result.emulator, tuning, result.envelope)


def save_policy(root: Root, result: PolicyResult, goals: np.ndarray, when: dt.datetime | None = None) -> Path:
    """Write the policy under the data directory of ``root`` and point ``latest`` at it; the emulator
    it refined while it learned (``PolicyResult.emulator``) first, as a version of its own that it names
    (``store.save_tuned``; the version it was refined from is found in ``root``)."""
    if result.emulator is not None:
        m = result.manifest
        result = replace(
            result,
            manifest=read_manifest(_emulator_it_names(root, resolve(root, m.model, m.version), result)),
        )
    folder, version = _new_folder(root, result.manifest.model, result.task.name, when)
    shape = result.net.shape
    graph = policy_to_onnx(result.net, shape.state_size, shape.goal_size, shape.timed)
    weights = {"shape": shape.to_dict(), "state_dict": result.net.state_dict()}
    return _write(folder, graph, weights, policy_manifest(result, version, goals))


def save_reward_policy(root: Root, result: RewardResult, base: Path, when: dt.datetime | None = None) -> Path:
    """Write a reward policy trained through the emulator version at ``base`` under the data directory
    of ``root``. An emulator it fine-tuned while it learned (``RewardResult.emulator``) is stored first,
    as a version of its own (``store.save_tuned``): the one the policy names and its sessions run."""
    emulator = read_manifest(_emulator_it_names(root, base, result))
    folder, version = _new_folder(root, emulator.model, result.task.name, when)
    manifest = reward_policy_manifest(result, emulator, version)
    graph = policy_to_onnx(result.policy, manifest.state_size, manifest.goal_size, False, reads_time=False)
    weights = {"kind": "reward", "task": result.task.name, "state_dict": result.policy.state_dict()}
    return _write(folder, graph, weights, manifest)


def save_commanded_policy(
    root: Root,
    task: SuiteTask,
    policy: RewardPolicy,
    emulator: Manifest,
    metrics: PolicyMetrics,
    when: dt.datetime | None = None,
    starts: NDArray[np.floating] | None = None,
) -> Path:
    """Write a policy of ``task`` whose goal is a command (its parameters: the runner's speed), learned
    otherwise than by ``reward_policy`` (``runner_policy``), with the ``metrics`` it was judged by and
    the (K, S) ``starts`` its sessions begin at; served as a reward policy is."""
    folder, version = _new_folder(root, emulator.model, task.name, when)
    low, high = list(task.param_low), list(task.param_high)
    default = [(lo + hi) / 2 for lo, hi in zip(low, high, strict=True)]
    manifest = _task_manifest(task, emulator, version, low, high, default, metrics)
    if starts is not None:
        manifest = manifest.model_copy(update={"starts": np.asarray(starts, float).round(6).tolist()})
    graph = policy_to_onnx(policy, manifest.state_size, manifest.goal_size, False, reads_time=False)
    weights = {"kind": "commanded", "task": task.name, "state_dict": policy.state_dict()}
    return _write(folder, graph, weights, manifest)


def load_policy_net(folder: Path) -> PolicyNet:
    """The torch policy of a stored version."""
    data = torch.load(folder / POLICY_WEIGHTS, weights_only=True)
    net = PolicyNet(PolicyShape.from_dict(data["shape"]))
    net.load_state_dict(data["state_dict"])
    return net.eval()
