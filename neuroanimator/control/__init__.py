"""Control synthesis through neural-network emulators (thesis chapter 5, sections 6.2-6.3, App. G).

A *job* asks for a controller: a task (``TASKS``) or a model with a goal, an objective, and the
optimiser's settings. ``validate_job`` turns a request (``controller_schemas.JobCreate``, or its
JSON) into a ``JobSpec`` without importing PyTorch or MuJoCo (an API process calls it on
submission); ``run_job`` validates again (against the worker's artifacts), optimises the controller
by backpropagation through time in the artifact's torch emulator, with momentum, replays it on
MuJoCo and, if it misses there, refines it on an emulator corrected along the replay (``runner``).

    JobCreate (the API body) --validate_job--> JobSpec (queued, run) --run_job--> JobOutcome
    (stored with the job's id as ``controller_schemas.JobResult``)

Modules: ``spec`` (``JobSpec``, ``OptimizerSettings``, ``Task``), ``tasks`` (the registry of the
tasks defined beside each physical model), ``terms`` (the objective-term catalogue and its types,
torch-free), ``criteria`` (success checks, numpy), ``validation`` (``validate_job``), ``splines``
(Catmull-Rom controls in torch), ``objectives`` (J in torch), ``bptt`` (the emulator objective and
its gradient), ``synthesis`` (the momentum optimiser), ``replay`` (MuJoCo replay),
``gradient_free`` (Nelder-Mead and CMA-ES baselines), ``runner`` (``run_job``).

``TASKS`` and ``validate_job`` are loaded on first use: the task registry reads the physics catalog,
whose modules define their tasks with this package's types.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import TYPE_CHECKING, Any

from neuroanimator import registry
from neuroanimator.control.errors import JobSpecError
from neuroanimator.control.spec import JobSpec, Task

if TYPE_CHECKING:
    from neuroanimator.control.tasks import TASKS
    from neuroanimator.control.validation import validate_job
    from neuroanimator.controller_schemas import JobOutcome

_LAZY = {"TASKS": "neuroanimator.control.tasks", "validate_job": "neuroanimator.control.validation"}


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        import importlib

        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def run_job(
    spec: JobSpec | Mapping[str, Any],
    artifacts_root: registry.Root,
    on_progress: Callable[[dict[str, Any]], None] | None = None,
    should_stop: Callable[[], bool] | None = None,
    threads: int = 1,
) -> JobOutcome:
    """Synthesise and replay a controller (``runner.run_job``; imports PyTorch on first call)."""
    from neuroanimator.control.runner import run_job as _run_job

    return _run_job(spec, artifacts_root, on_progress=on_progress, should_stop=should_stop, threads=threads)


__all__ = ["TASKS", "JobSpec", "JobSpecError", "Task", "run_job", "validate_job"]
