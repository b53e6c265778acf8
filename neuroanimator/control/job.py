"""``run_job``: one control-synthesis job from spec to replayed result (what a job worker calls).

validate the spec (a ``JobSpec``) → load the artifact's torch emulator and its MJCF → search on the
emulator (``search.py``: a cross-entropy pass and ``optimizer.starts`` controllers descended at
once, batched) → optimise the best start further (``synthesis.optimize``) → replay it on MuJoCo →
a ``JobOutcome``. PyTorch is imported here, never by ``validate_job``. ``iterations`` counts the
batched descent steps and the single-start ones; ``emulator_rollouts`` every trajectory the
emulator scored (global search, starts, line-search candidates, gradients).

What the outcome claims is what happened: a job without success checks has ``success_*`` null,
no physics-refinement rounds (there is nothing for MuJoCo to miss) and its final errors as the
result; ``stop`` is ``success`` only when the returned controller meets the criterion on the
emulator or on MuJoCo (else ``missed_on_physics``: it held on the emulator during the search, and
refinement did not carry it to MuJoCo); ``reachable`` is false, with ``reachability`` naming the
checks the best controller misses and what was tried, when no controller found meets the
criterion on either.

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
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch

from neuroanimator.artifacts import registry
from neuroanimator.artifacts import store as artifacts
from neuroanimator.contracts.controller import (
    EmulatorPhase,
    GaussNewtonInfo,
    JobOutcome,
    Refinement,
    RefinementRound,
    SearchInfo,
    Trajectory,
)
from neuroanimator.control.bptt import ControlProblem
from neuroanimator.control.gauss_newton import levenberg_marquardt
from neuroanimator.control.replay import Replay, final_error, simulate_held
from neuroanimator.control.search import cross_entropy, descend_starts, starting_points
from neuroanimator.control.synthesis import Outcome, Settings, clean, elapsed, optimize
from neuroanimator.control.validation import validate_job
from neuroanimator.core.manifest import Manifest
from neuroanimator.core.quaternion import wrap_angle
from neuroanimator.core.state import LayoutGroup, heading_columns
from neuroanimator.goals import criteria
from neuroanimator.goals.spec import JobSpec

log = logging.getLogger(__name__)

REFINE_ITERATIONS = 10  # updates per physics-refinement round
REFINE_POLISH = 3
STATUS = {
    "success": "succeeded",
    "converged": "succeeded",
    "stalled": "succeeded",
    "max_iterations": "succeeded",
    "missed_on_physics": "succeeded",
    "diverged": "failed",
    "cancelled": "cancelled",
}


def reported(states: np.ndarray, layout: list[LayoutGroup]) -> np.ndarray:
    """States (K+1, S) as the emulator service reports them: a ``heading`` wrapped to [-π, π)
    (``state.heading_columns``), whatever turns the rollout made."""
    cols = heading_columns(layout)
    if not cols:
        return states
    out = np.array(states, dtype=np.float64, copy=True)
    out[:, cols] = wrap_angle(out[:, cols])
    return out


def load_problem(spec: JobSpec, artifacts_root: registry.Root) -> tuple[ControlProblem, Manifest, Path]:
    """The emulator objective of a validated spec, the artifact's manifest and its folder."""
    path = registry.resolve(artifacts_root, spec.model, spec.version)
    manifest = registry.read_manifest(path)
    return ControlProblem(artifacts.load_emulator(path), spec, manifest), manifest, path


def run_job(
    job: JobSpec | Mapping[str, Any],
    artifacts_root: registry.Root,
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
    spec = validate_job(job, artifacts_root)
    previous_threads = torch.get_num_threads()
    torch.set_num_threads(max(1, int(threads)))
    try:
        return _run(spec, artifacts_root, on_progress, should_stop, t0)
    finally:
        torch.set_num_threads(previous_threads)


def _run(
    spec: JobSpec,
    root: registry.Root,
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

    def values_and_grads(zs: np.ndarray) -> tuple[np.ndarray, np.ndarray, list[Any]]:
        j, g, states, held = problem.values_and_grads(zs)
        return j, g, list(zip(states, held, strict=True))

    settings = Settings.from_spec(spec.optimizer)
    gauss_newton = GaussNewtonInfo()

    def finish(out: Outcome, budget: int) -> Outcome:
        """Levenberg-Marquardt from a descent that ended short of the criterion on the emulator
        (``gauss_newton.py``); the better of the two (meets the criterion, else lower J) is kept."""
        if not spec.success or out.success or out.stop in ("diverged", "cancelled") or budget <= 0:
            return out
        done = out.iterations
        lm = levenberg_marquardt(
            problem.residual_jacobian,
            problem.evaluate,
            out.z,
            max_iterations=budget,
            project=problem.project,
            is_success=is_success,
            polish_iterations=settings.polish_iterations,
            on_iteration=lambda i, j, b, ok: report(done + i, j, b, ok),
            should_stop=should_stop,
        )
        gauss_newton.runs += 1
        gauss_newton.iterations += lm.iterations
        gauss_newton.rollouts += lm.rollouts
        gauss_newton.success = gauss_newton.success or lm.success
        out.iterations += lm.iterations
        out.rollouts += lm.rollouts
        out.history = out.history + lm.history[1:]
        if (lm.success, -lm.objective) > (out.success, -out.objective):
            out.z, out.objective, out.success, out.extra = lm.z, lm.objective, lm.success, lm.extra
        if lm.success and lm.iterations_to_success is not None:
            out.stop, out.reason = "success", None
            out.iterations_to_success = done + lm.iterations_to_success
        elif lm.stop == "cancelled":
            out.stop, out.reason = "cancelled", f"cancelled after {out.iterations} iterations"
        return out

    z0 = problem.initial_points()
    searched = SearchSummary()
    if spec.optimizer.starts > 1 or spec.optimizer.global_generations > 0:
        j_init, ok_init = _initial(problem, z0, is_success)
        report(0, j_init, j_init, ok_init)
        z0, searched = _search(
            problem,
            spec,
            settings,
            values_and_grads,
            is_success,
            report,
            should_stop,
            [c.name for c in manifest.controls],
        )
        phase["offset"] = searched.iterations
        # the history is what progress reported: the initial controller, then the best start's J
        searched.history = [j_init, *searched.history]
        searched.rollouts += 1
    outcome = optimize(
        value_and_grad,
        z0,
        replace(settings, max_iterations=max(1, settings.max_iterations - searched.iterations)),
        project=problem.project,
        evaluate=problem.evaluate,
        is_success=is_success,
        on_iteration=lambda i, j, b, ok: report(i, j, b, ok) if i > 0 or not searched.ran else None,
        should_stop=should_stop,
    )
    outcome = finish(outcome, spec.optimizer.gauss_newton_iterations)
    outcome.iterations += searched.iterations
    if outcome.stop == "cancelled":
        outcome.reason = f"cancelled after {outcome.iterations} iterations"
    outcome.rollouts += searched.rollouts
    if searched.ran:  # the descent's first entry is the search's last
        outcome.history = searched.history + outcome.history[1:]
    if outcome.iterations_to_success is not None:
        outcome.iterations_to_success += searched.iterations
    elif searched.success:
        outcome.iterations_to_success = searched.iterations
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
    # without a criterion there is nothing for MuJoCo to miss: no refinement rounds
    rounds_allowed = spec.optimizer.physics_rounds if spec.success else 0
    for r in range(1, rounds_allowed + 1):
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
        out_r = finish(out_r, min(REFINE_ITERATIONS, spec.optimizer.gauss_newton_iterations))
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
    if stop == "success" and not (emu.success or phys.success):
        # the criterion held on the emulator during the search, but the controller returned (the one
        # best on MuJoCo after refinement) meets it on neither
        stop = "missed_on_physics"
        reason = (
            f"the criterion held on the emulator after {outcome.iterations_to_success} iterations but "
            f"not on MuJoCo, and {len(rounds)} physics-refinement rounds did not reach it"
        )
    reachable, reachability = _reachability(spec, emu, phys, outcome, searched)
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
        bptt_networks=problem.networks,
        objective=clean(problem.score(emulated, held)),
        objective_physics=clean(-neg_j_phys),
        objective_history=clean(outcome.history),
        control_names=[c.name for c in manifest.controls],
        control_points=clean(problem.to_physical(z)),
        control_spacing_s=problem.spline.spacing,
        super_timestep=problem.super_dt,
        times=problem.spline.times(),
        controls=clean(held),
        emulated=Trajectory(states=clean(reported(emulated, layout))),
        physical=Trajectory(states=clean(reported(phys_states, layout))),
        final_error_emulator=clean(emu.final_error),
        final_error_physics=clean(phys.final_error),
        final_errors_emulator=clean(emu.final_errors),
        final_errors_physics=clean(phys.final_errors),
        transfer_error=clean(transfer),
        success_criterion=criteria.describe(spec.success, spec.target_state, labels),
        success_emulator=emu.success if spec.success else None,
        success_physics=phys.success if spec.success else None,
        checks_emulator=clean(emu.checks),
        checks_physics=clean(phys.checks),
        reachable=reachable,
        reachability=reachability,
        search=searched.to_info(),
        gauss_newton=gauss_newton,
        emulator_phase=EmulatorPhase(
            objective=clean(outcome.objective),
            success_emulator=phase_emu.success if spec.success else None,
            success_physics=phase_phys.success if spec.success else None,
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


GLOBAL_POPULATION = 128  # controllers per cross-entropy generation
START_ITERATIONS = 6  # batched descent steps from all starts before the best one continues alone


@dataclass
class SearchSummary:
    """What the global search and the batched starts did before single-start descent."""

    ran: bool = False
    starts: int = 1
    global_rollouts: int = 0
    iterations: int = 0
    rollouts: int = 0
    success: bool = False
    chosen: str = "initial controls"
    history: list[float] = field(default_factory=list)

    def to_info(self) -> SearchInfo:
        return SearchInfo(
            starts=self.starts,
            global_rollouts=self.global_rollouts,
            start_iterations=self.iterations,
            chosen=self.chosen,
        )


def _initial(
    problem: ControlProblem, z0: np.ndarray, is_success: Callable[[Any], bool]
) -> tuple[float, bool]:
    """J of the job's initial controller (M, U) on the emulator, and whether it meets the criterion."""
    with torch.no_grad():
        states, held = problem.trajectory(z0)
    return problem.score(states, held), is_success((states, held))


def _search(
    problem: ControlProblem,
    spec: JobSpec,
    settings: Settings,
    values_and_grads: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray, list[Any]]],
    is_success: Callable[[Any], bool],
    report: Callable[[int, float, float, bool], None],
    should_stop: Callable[[], bool] | None,
    control_names: list[str],
) -> tuple[np.ndarray, SearchSummary]:
    """The cross-entropy pass and the batched starts (``search.py``): the controller to refine (M, U)."""
    opt = spec.optimizer
    fixed = starting_points(problem.initial_points(), problem.project)
    names = ["initial controls"] + [
        f"initial controls with {c} {sign}" for c in control_names for sign in ("up", "down")
    ]
    candidates: list[tuple[str, np.ndarray]] = []
    global_rollouts = 0
    if opt.global_generations > 0:
        found = cross_entropy(
            problem.evaluate,
            fixed,
            problem.project,
            generations=opt.global_generations,
            population=GLOBAL_POPULATION,
        )
        global_rollouts = found.rollouts
        candidates.append(("global search", found.best[0]))
        order = np.argsort(found.start_values, kind="stable")
    else:
        order = np.arange(len(fixed))
    for i in order:
        if not any(np.allclose(fixed[i], z) for _, z in candidates):
            candidates.append((names[i] if i < len(names) else f"start {i}", fixed[i]))
    candidates = candidates[: opt.starts]
    out = descend_starts(
        values_and_grads,
        problem.evaluate,
        np.stack([z for _, z in candidates]),
        settings,
        min(START_ITERATIONS, settings.max_iterations - 1),  # at least one left for the chosen start
        project=problem.project,
        is_success=is_success,
        on_iteration=report,
        should_stop=should_stop,
    )
    return out.z, SearchSummary(
        ran=True,
        starts=len(candidates),
        global_rollouts=global_rollouts,
        iterations=out.iterations,
        rollouts=global_rollouts + out.rollouts,
        success=out.success,
        chosen=candidates[out.index][0],
        history=out.history,
    )


def _reachability(
    spec: JobSpec,
    emu: Replay,
    phys: Replay,
    outcome: Outcome,
    searched: SearchSummary,
) -> tuple[bool | None, str]:
    """Whether the goal was reached, and in words why not: the checks the best controller failed on
    the emulator after the whole search (a goal no controller reaches within the horizon and the
    controls' limits ends here as unreachable, with how close it came)."""
    if not spec.success:
        return None, "no success criterion: the final errors are the result"
    if emu.success or phys.success:
        return True, "the criterion holds " + ("on MuJoCo" if phys.success else "on the emulator only")
    missed = [f"{c['check']} (measured {c['value']:.3g})" for c in emu.checks if not c["passed"]]
    tried = (
        f"{searched.starts} starts, {searched.global_rollouts} controllers of a global search and "
        f"{outcome.iterations} gradient iterations"
    )
    return False, (
        f"unreachable as found: no controller among {tried} meets the criterion on the emulator "
        f"within the horizon ({spec.horizon} super-steps) and the controls' limits; the best misses "
        + "; ".join(missed)
    )
