"""``run_job``: one control-synthesis job from spec to replayed result (what a job worker calls).

validate the spec (a ``JobSpec``) → load the artifact's torch emulator and its MJCF → optimise the
controller on the emulator (``synthesis.optimize``) → replay it on MuJoCo → a ``JobOutcome``.
PyTorch is imported here, never by ``validate_job``.

Physics refinement (``optimizer.physics_rounds``, default 3): an emulator's small systematic
errors add up over 40 super-steps (the lander's drifts ~4 m in 20 s at hover), so a controller that
meets the criterion on the emulator can miss on MuJoCo. When the replay misses, the emulator is
corrected along the replayed trajectory (``ControlProblem.set_correction``: a per-step additive
term that makes it reproduce the replay exactly) and the controller is optimised again for a few
iterations, then replayed; the controller that does best on MuJoCo is returned. The result keeps
the emulator-only controller's outcome (``emulator_phase``) beside the returned one's, and
``emulated`` is always the plain emulator's prediction, so a refined controller can show
``success_emulator`` false and ``success_physics`` true: the emulator's own error, made visible.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Mapping
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import torch

from neuroanimator import artifacts, registry
from neuroanimator.control import criteria
from neuroanimator.control.bptt import ControlProblem
from neuroanimator.control.replay import Replay, final_error, simulate_held
from neuroanimator.control.spec import JobSpec
from neuroanimator.control.synthesis import Settings, clean, elapsed, optimize
from neuroanimator.control.validation import validate_job
from neuroanimator.controller_schemas import (
    EmulatorPhase,
    JobOutcome,
    Refinement,
    RefinementRound,
    Trajectory,
)
from neuroanimator.manifest import Manifest

log = logging.getLogger(__name__)

REFINE_ITERATIONS = 10  # updates per physics-refinement round
REFINE_POLISH = 3
STATUS = {
    "success": "succeeded",
    "converged": "succeeded",
    "stalled": "succeeded",
    "max_iterations": "succeeded",
    "diverged": "failed",
    "cancelled": "cancelled",
}


def load_problem(spec: JobSpec, artifacts_root: Path) -> tuple[ControlProblem, Manifest, Path]:
    """The emulator objective of a validated spec, the artifact's manifest and its folder."""
    path = registry.resolve(Path(artifacts_root), spec.model, spec.version)
    manifest = registry.read_manifest(path)
    return ControlProblem(artifacts.load_torch(path), spec, manifest), manifest, path


def run_job(
    job: JobSpec | Mapping[str, Any],
    artifacts_root: Path,
    on_progress: Callable[[dict[str, Any]], None] | None = None,
    should_stop: Callable[[], bool] | None = None,
    threads: int = 1,
) -> JobOutcome:
    """Synthesise a controller for a job and replay it on MuJoCo.

    ``job`` (a ``JobSpec``, or a request's JSON) is validated first against these artifacts
    (``JobSpecError`` for a bad one). ``on_progress`` receives
    ``{"iteration", "objective", "best_objective", "success_emulator", "elapsed_s"}`` for the
    initial controller (iteration 0) and after every update; ``should_stop()`` returning True
    cancels the run at the next iteration. ``threads`` is PyTorch's intra-op thread count for the
    duration of the job.

    ``status`` is ``"succeeded"`` when the optimisation ended normally (criterion met, converged,
    or the iteration cap; ``success_emulator`` says whether the criterion was met), ``"failed"``
    when it diverged (``reason`` says where; the best finite controller is returned) and
    ``"cancelled"``. The outcome's fields are described in ``controller_schemas.JobOutcome``; its
    numbers that were not finite are None.
    """
    t0 = time.perf_counter()
    spec = validate_job(job, Path(artifacts_root))
    previous_threads = torch.get_num_threads()
    torch.set_num_threads(max(1, int(threads)))
    try:
        return _run(spec, Path(artifacts_root), on_progress, should_stop, t0)
    finally:
        torch.set_num_threads(previous_threads)


def _run(
    spec: JobSpec,
    root: Path,
    on_progress: Callable[[dict[str, Any]], None] | None,
    should_stop: Callable[[], bool] | None,
    t0: float,
) -> JobOutcome:
    problem, manifest, path = load_problem(spec, root)
    physical = registry.load_physical_model(path, manifest)
    labels = manifest.state_labels
    layout = manifest.layout
    target = np.asarray(spec.target_state, dtype=np.float64)
    s0 = np.asarray(spec.initial_state, dtype=np.float64)
    n = spec.substeps
    phase: dict[str, Any] = {"name": "emulator", "offset": 0}

    def is_success(extra: tuple[np.ndarray, np.ndarray]) -> bool:
        states = extra[0]
        return bool(spec.success) and criteria.evaluate(spec.success, states[-1], target, labels)[0]

    def value_and_grad(z: np.ndarray) -> tuple[float, np.ndarray, tuple[np.ndarray, np.ndarray]]:
        j, g, states, held = problem.value_and_grad(z)
        return j, g, (states, held)

    def report(iteration: int, j: float, best: float, ok: bool) -> None:
        it = iteration + phase["offset"]
        log.debug("%s iteration %d: J=%.6g best=%.6g success=%s", phase["name"], it, j, best, ok)
        if on_progress is not None:
            on_progress(
                {
                    "iteration": it,
                    "objective": clean(j),
                    "best_objective": clean(best),
                    "success_emulator": ok,
                    "elapsed_s": elapsed(t0),
                    "phase": phase["name"],
                }
            )

    def replay(held: np.ndarray) -> tuple[np.ndarray, float, bool]:
        states = simulate_held(physical, s0[None], held[None], n)[0]
        ok = bool(spec.success) and criteria.evaluate(spec.success, states[-1], target, labels)[0]
        return states, problem.score(states, held), ok

    settings = Settings.from_spec(spec.optimizer)
    outcome = optimize(
        value_and_grad,
        problem.initial_points(),
        settings,
        project=problem.project,
        evaluate=problem.evaluate,
        is_success=is_success,
        on_iteration=report,
        should_stop=should_stop,
    )
    stop, reason = outcome.stop, outcome.reason
    _, held = outcome.extra
    phys_states, j_phys, ok_phys = replay(held)
    # the controller found on the emulator alone, before any physics refinement
    phase_emu = Replay.of(outcome.extra[0], spec, layout, labels)
    phase_phys = Replay.of(phys_states, spec, layout, labels)

    # Physics refinement: correct the emulator along the replayed trajectory and optimise again, a
    # few iterations per round, keeping the controller that does best on MuJoCo itself.
    z = outcome.z
    best = (ok_phys, -j_phys, z, held, phys_states)
    rounds: list[RefinementRound] = []
    refine_iterations = 0
    for r in range(1, spec.optimizer.physics_rounds + 1):
        if stop in ("diverged", "cancelled") or best[0]:
            break
        if should_stop is not None and should_stop():
            stop, reason = "cancelled", f"cancelled during physics refinement round {r}"
            break
        phase.update(name="physics_refinement", offset=outcome.iterations + refine_iterations)
        problem.set_correction(phys_states, held)
        refine = replace(
            settings,
            max_iterations=min(REFINE_ITERATIONS, settings.max_iterations),
            polish_iterations=min(settings.polish_iterations, REFINE_POLISH),
        )
        out_r = optimize(
            value_and_grad,
            z,
            refine,
            project=problem.project,
            evaluate=problem.evaluate,
            is_success=is_success,
            on_iteration=lambda i, j, b, ok: report(i, j, b, ok) if i > 0 else None,
            should_stop=should_stop,
        )
        problem.set_correction(None)
        refine_iterations += out_r.iterations
        if out_r.stop == "diverged":
            rounds.append(
                RefinementRound(round=r, iterations=out_r.iterations, stop=out_r.stop, reason=out_r.reason)
            )
            break
        z = out_r.z
        _, held = problem.trajectory(z)
        phys_states, j_phys, ok_phys = replay(held)
        rounds.append(
            RefinementRound(
                round=r,
                iterations=out_r.iterations,
                stop=out_r.stop,
                objective_physics=clean(j_phys),
                success_physics=ok_phys,
            )
        )
        if (ok_phys, -j_phys) > best[:2]:
            best = (ok_phys, -j_phys, z, held, phys_states)
        if out_r.stop == "cancelled":
            stop, reason = "cancelled", f"cancelled during physics refinement round {r}"
            break
    _, neg_j_phys, z, held, phys_states = best
    emulated, _ = problem.trajectory(z)  # the plain emulator's prediction for the chosen controller
    emu = Replay.of(emulated, spec, layout, labels)
    phys = Replay.of(phys_states, spec, layout, labels)
    # how far the physics ends from where the emulator said it would, in the goal's own metric
    transfer, _ = final_error(phys_states[-1], emulated[-1].tolist(), spec.state_weights, layout)
    result = JobOutcome(
        status=STATUS[stop],
        reason=reason,
        stop=stop,
        task=spec.task,
        model=spec.model,
        version=spec.version,
        substeps=spec.substeps,
        iterations=outcome.iterations,
        iterations_to_success=outcome.iterations_to_success,
        emulator_rollouts=outcome.rollouts,
        objective=clean(problem.score(emulated, held)),
        objective_physics=clean(-neg_j_phys),
        objective_history=clean(outcome.history),
        control_names=[c.name for c in manifest.controls],
        control_points=clean(problem.to_physical(z)),
        control_spacing_s=problem.spline.spacing,
        super_timestep=problem.super_dt,
        times=problem.spline.times(),
        controls=clean(held),
        emulated=Trajectory(states=clean(emulated)),
        physical=Trajectory(states=clean(phys_states)),
        final_error_emulator=clean(emu.final_error),
        final_error_physics=clean(phys.final_error),
        final_errors_emulator=clean(emu.final_errors),
        final_errors_physics=clean(phys.final_errors),
        transfer_error=clean(transfer),
        success_criterion=criteria.describe(spec.success, spec.target_state, labels),
        success_emulator=emu.success,
        success_physics=phys.success,
        checks_emulator=clean(emu.checks),
        checks_physics=clean(phys.checks),
        emulator_phase=EmulatorPhase(
            objective=clean(outcome.objective),
            success_emulator=phase_emu.success,
            success_physics=phase_phys.success,
            final_error_emulator=clean(phase_emu.final_error),
            final_error_physics=clean(phase_phys.final_error),
        ),
        refinement=Refinement(rounds=rounds, iterations=refine_iterations, physics_replays=len(rounds) + 1),
        target_state=spec.target_state,
        initial_state=spec.initial_state,
        state_labels=labels,
        spec=spec,
        wall_s=elapsed(t0),
    )
    log.info(
        "control job %s/%s: %s after %d iterations (+%d refining), success emulator=%s physics=%s, %.2fs",
        spec.task or "-",
        spec.model,
        stop,
        outcome.iterations,
        refine_iterations,
        emu.success,
        phys.success,
        result.wall_s,
    )
    return result
