"""The registry of built-in control-synthesis tasks: every task of every system in the physics catalog.

Each task is defined beside its physical model, as dm_control's suite does (``physics/pendulum.py``:
``pendulum-swing``, ``lander.py``: ``lander-landing``, ``truck.py``: ``truck-parking``; thesis 6.2)
in a module-level ``TASKS`` tuple, with its state labels taken from that model's layout. A new
system's tasks are listed here by adding the system to ``catalog.SYSTEMS``.

The thesis' tasks are 20 s long: 40 super-steps of the n = 50 emulator (Δt = 0.5 s), with one
control point every two super-steps, i.e. 20 points per control: 60 variables for the pendulum, 80
for the lander and 40 for the truck. Each states its success criterion as checks on the final state
(``criteria.py``); the same checks are evaluated on the emulated trajectory and on the MuJoCo
replay, and their text is part of the task's description. Numpy only: no torch, no MuJoCo.
"""

from __future__ import annotations

from neuroanimator import catalog
from neuroanimator.goals.policy_task import PolicyTask
from neuroanimator.goals.spec import Task


def collect() -> dict[str, Task]:
    """Every catalog system's tasks by name, in catalog order; a name used twice, or a task on a model
    the catalog does not have, is an error."""
    found: dict[str, Task] = {}
    for system in catalog.SYSTEMS:
        for task in getattr(system, "TASKS", ()):
            if task.name in found:
                raise ValueError(f"task {task.name!r} is defined twice (again in {system.__name__})")
            if task.model not in catalog.CATALOG:
                raise ValueError(f"task {task.name!r} runs on {task.model!r}, which is not in the catalog")
            found[task.name] = task
    return found


def collect_policy_tasks() -> dict[str, PolicyTask]:
    """Every catalog system's policy tasks (``POLICY_TASKS``: feedback controllers over many starts and
    goals) by name, in catalog order, checked as ``collect`` checks tasks."""
    found: dict[str, PolicyTask] = {}
    for system in catalog.SYSTEMS:
        for task in getattr(system, "POLICY_TASKS", ()):
            if task.name in found:
                raise ValueError(f"policy task {task.name!r} is defined twice (again in {system.__name__})")
            if task.model not in catalog.CATALOG:
                raise ValueError(
                    f"policy task {task.name!r} runs on {task.model!r}, which is not in the catalog"
                )
            found[task.name] = task
    return found


TASKS: dict[str, Task] = collect()
POLICY_TASKS: dict[str, PolicyTask] = collect_policy_tasks()

__all__ = ["POLICY_TASKS", "TASKS", "PolicyTask", "Task", "collect", "collect_policy_tasks"]
