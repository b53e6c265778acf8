"""Control synthesis through neural-network emulators (thesis chapter 5, sections 6.2-6.3, App. G).

A *job* asks for a controller: a task (``TASKS``) or a model with a goal, an objective, and the
optimiser's settings. ``validate_job`` checks and normalises a spec without importing PyTorch (an
API process calls it on submission); ``run_job`` optimises the controller by backpropagation
through time in the artifact's torch emulator, with momentum, replays it on MuJoCo and, if it misses
there, refines it on an emulator corrected along the replay (``runner``).

Modules: ``tasks`` (the thesis' tasks, plain data), ``terms`` (the objective-term catalogue,
torch-free), ``criteria`` (success checks, numpy), ``jobs`` (``validate_job``), ``splines``
(Catmull-Rom controls in torch), ``objectives`` (J in torch), ``bptt`` (the emulator objective and
its gradient), ``synthesis`` (the momentum optimiser), ``replay`` (MuJoCo replay),
``gradient_free`` (Nelder-Mead and CMA-ES baselines), ``runner`` (``run_job``).

``run_job(spec, artifacts_root, on_progress=None, should_stop=None, threads=1) -> dict``; the
result holds ``status`` ("succeeded" | "failed" | "cancelled"), ``reason``, ``task``, ``model``,
``version``, ``substeps``, ``iterations``, ``iterations_to_success``, ``objective_history``,
``control_points`` (M×U), ``control_spacing_s``, ``times`` (K super-step starts), ``controls``
(K×U held values), ``emulated``/``physical`` ``{"states": (K+1)×S}``, ``final_error_emulator``,
``final_error_physics``, ``success_emulator``, ``success_physics``, ``target_state``,
``initial_state``, ``wall_s``, ``state_labels``, and more detail (``stop``, ``transfer_error``,
``checks_emulator``/``checks_physics``, ``success_criterion``, ``emulator_phase``, ``refinement``,
``objective_physics``, ``control_names``, ``spec``...).
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

from neuroanimator.control.errors import JobSpecError
from neuroanimator.control.jobs import validate_job
from neuroanimator.control.tasks import TASKS, Task


def run_job(
    spec: dict[str, Any],
    artifacts_root: Path,
    on_progress: Callable[[dict[str, Any]], None] | None = None,
    should_stop: Callable[[], bool] | None = None,
    threads: int = 1,
) -> dict[str, Any]:
    """Synthesise and replay a controller (``runner.run_job``; imports PyTorch on first call)."""
    from neuroanimator.control.runner import run_job as _run_job

    return _run_job(spec, artifacts_root, on_progress=on_progress, should_stop=should_stop, threads=threads)


__all__ = ["TASKS", "JobSpecError", "Task", "run_job", "validate_job"]
