"""Writing a trained policy as a versioned artifact beside its emulator (``artifacts.policies`` reads it).

``<data>/policies/<model>/<name>/<version>/``: ``policy.onnx``, ``policy.pt`` (weights and the
network's shape, for the torch path) and ``policy.json`` (``PolicyManifest``); the ``latest`` pointer
moves to it. Versions are named ``p-<UTC time>``.
"""

from __future__ import annotations

import datetime as dt
from pathlib import Path

import numpy as np
import torch

from neuroanimator.artifacts.policies import POLICIES_DIR, POLICY_FILE, POLICY_ONNX, POLICY_WEIGHTS
from neuroanimator.artifacts.registry import LATEST, Root, writable, write_pointer
from neuroanimator.control.policy import PolicyResult, Schedule
from neuroanimator.control.policy_net import PolicyNet, PolicyShape
from neuroanimator.core.policy_manifest import PolicyManifest, PolicyMetrics
from neuroanimator.export.policy import policy_to_onnx


def policy_manifest(result: PolicyResult, version: str, goals: np.ndarray) -> PolicyManifest:
    """The manifest of a trained policy; ``goals`` (N, G) are those it was trained for."""
    task, m = result.task, result.manifest
    schedule = Schedule(task, m.super_timestep)
    default = np.median(goals, axis=0)
    return PolicyManifest(
        name=task.name,
        version=version,
        created=dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
        model=m.model,
        emulator_version=m.version,
        substeps=m.substeps,
        super_timestep=m.super_timestep,
        state_size=m.state_size,
        state_labels=list(m.state_labels),
        control_names=[c.name for c in m.controls],
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
            evaluate_runs=result.evaluate_runs,
            mujoco_steps=result.mujoco_steps,
            iterations=result.iterations,
            refinements=result.refinements,
            wall_s=round(result.wall_s, 2),
            stop=result.stop,
        ),
    )


def save_policy(root: Root, result: PolicyResult, goals: np.ndarray, when: dt.datetime | None = None) -> Path:
    """Write the policy under the data directory of ``root`` and point ``latest`` at it."""
    when = when or dt.datetime.now(dt.UTC)
    base = writable(root) / POLICIES_DIR / result.manifest.model / result.task.name
    version = "p-" + when.strftime("%Y%m%dT%H%M%S")
    n = 1
    while (base / version).exists():
        n += 1
        version = "p-" + when.strftime("%Y%m%dT%H%M%S") + f"-{n}"
    folder = base / version
    folder.mkdir(parents=True)
    shape = result.net.shape
    manifest = policy_manifest(result, version, goals)
    (folder / POLICY_ONNX).write_bytes(
        policy_to_onnx(result.net, shape.state_size, shape.goal_size, shape.timed)
    )
    torch.save({"shape": shape.to_dict(), "state_dict": result.net.state_dict()}, folder / POLICY_WEIGHTS)
    (folder / POLICY_FILE).write_text(manifest.model_dump_json(indent=2))
    write_pointer(base, LATEST, version)
    return folder


def load_policy_net(folder: Path) -> PolicyNet:
    """The torch policy of a stored version."""
    data = torch.load(folder / POLICY_WEIGHTS, weights_only=True)
    net = PolicyNet(PolicyShape.from_dict(data["shape"]))
    net.load_state_dict(data["state_dict"])
    return net.eval()
