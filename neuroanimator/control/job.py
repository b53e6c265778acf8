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
from typing import Any, Literal, TypedDict

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
from neuroanimator.control.threads import torch_threads
from neuroanimator.control.validation import validate_job
from neuroanimator.core.manifest import Manifest
from neuroanimator.core.quaternion import wrap_angle
from neuroanimator.core.state import LayoutGroup, heading_columns
from neuroanimator.goals import criteria
from neuroanimator.goals.spec import JobSpec

log = logging.getLogger(__name__)


Phase = Literal["emulator", "physics_refinement"]  # the search on the emulator, then refinement on MuJoCo


class Progress(TypedDict):
    """What ``on_progress`` receives for an iteration (0: the initial controller) of the current phase:
    J and the best J so far (None where not finite), whether the controller meets the criterion on
    the emulator, and the seconds since the job started. The controller service streams it as its
    ``ProgressEvent`` (``contracts.controller``)."""

    iteration: int
    objective: float | None
    best_objective: float | None
    success_emulator: bool
    elapsed_s: float
    phase: Phase


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
    on_progress: Callable[[Progress], None] | None = None,
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
    with torch_threads(threads):
        return _run(spec, artifacts_root, on_progress, should_stop, t0)


def _run(
    spec: JobSpec,
    root: registry.Root,
    on_progress: Callable[[Progress], None] | None,
    should_stop: Callable[[], bool] | None,
    t0: float,
) -> JobOutcome:
    """The emulator phase (search, descent, Levenberg-Marquardt), its replay on MuJoCo, physics
    refinement, and the outcome of the controller kept."""
    job = _JobRun(spec, root, on_progress, should_stop, t0)
    outcome, searched = job.search_and_descend()
    replayed = job.replay(outcome.z, outcome.extra[1])
    emulator_phase = job.emulator_phase(outcome, replayed)
    refined = job.refine(outcome, replayed)
    return job.result(outcome, searched, refined, emulator_phase)


@dataclass
class _PhysicsReplay:
    """A controller z (M, U) replayed on MuJoCo: the controls it holds (K, U), the states (K+1, S),
    their J and whether they meet the criterion."""

    z: np.ndarray
    held: np.ndarray
    states: np.ndarray
    objective: float
    success: bool

    def rank(self) -> tuple[bool, float]:
        """What refinement keeps the highest of: meeting the criterion, then a lower J."""
        return self.success, -self.objective


@dataclass
class _Refined:
    """What physics refinement ended with: the job's stop and reason, the controller that did best
    on MuJoCo, the rounds and the updates they made."""

    stop: str
    reason: str | None
    best: _PhysicsReplay
    rounds: list[RefinementRound]
    iterations: int


class _JobRun:
    """One job being run: its emulator objective, the MuJoCo model it is replayed on, and what
    progress reports (``phase`` names the stage, ``offset`` counts the iterations before it)."""

    def __init__(
        self,
        spec: JobSpec,
        root: registry.Root,
        on_progress: Callable[[Progress], None] | None,
        should_stop: Callable[[], bool] | None,
        t0: float,
    ) -> None:
        self.problem, self.manifest, path = load_problem(spec, root)
        self.physical = registry.load_physical_model(path, self.manifest)
        self.spec = spec
        self.labels = self.manifest.state_labels
        self.layout = self.manifest.layout
        self.target = np.asarray(spec.target_state, dtype=np.float64)
        self.s0 = np.asarray(spec.initial_state, dtype=np.float64)
        self.on_progress = on_progress
        self.should_stop = should_stop
        self.t0 = t0
        self.phase: Phase = "emulator"
        self.offset = 0
        self.settings = Settings.from_spec(spec.optimizer)
        self.gauss_newton = GaussNewtonInfo()

    def meets(self, states: np.ndarray) -> bool:
        """Whether states (K+1, S) end meeting the job's criterion (never, for a job without one)."""
        spec = self.spec
        return bool(spec.success) and criteria.evaluate(spec.success, states[-1], self.target, self.labels)[0]

    def is_success(self, extra: tuple[np.ndarray, np.ndarray]) -> bool:
        """``meets`` for what the objective returned beside J: the states and the held controls."""
        return self.meets(extra[0])

    def value_and_grad(self, z: np.ndarray) -> tuple[float, np.ndarray, tuple[np.ndarray, np.ndarray]]:
        """J, ∇J (M, U) and (states (K+1, S), held controls (K, U)) of a controller z (M, U)."""
        j, g, states, held = self.problem.value_and_grad(z)
        return j, g, (states, held)

    def values_and_grads(self, zs: np.ndarray) -> tuple[np.ndarray, np.ndarray, list[Any]]:
        """``value_and_grad`` of a batch zs (B, M, U): J (B,), ∇J (B, M, U) and B (states, held)."""
        j, g, states, held = self.problem.values_and_grads(zs)
        return j, g, list(zip(states, held, strict=True))

    def report(self, iteration: int, j: float, best: float, ok: bool) -> None:
        """Logs an iteration of the current phase and hands it to ``on_progress``."""
        it = iteration + self.offset
        log.debug("%s iteration %d: J=%.6g best=%.6g success=%s", self.phase, it, j, best, ok)
        if self.on_progress is not None:
            self.on_progress(
                {
                    "iteration": it,
                    "objective": clean(j),
                    "best_objective": clean(best),
                    "success_emulator": ok,
                    "elapsed_s": elapsed(self.t0),
                    "phase": self.phase,
                }
            )

    def replay(self, z: np.ndarray, held: np.ndarray) -> _PhysicsReplay:
        """The controller z (M, U), holding ``held`` (K, U), replayed on MuJoCo."""
        states = simulate_held(self.physical, self.s0[None], held[None], self.spec.substeps)[0]
        return _PhysicsReplay(z, held, states, self.problem.score(states, held), self.meets(states))

    def descend(
        self, z0: np.ndarray, settings: Settings, on_iteration: Callable[[int, float, float, bool], None]
    ) -> Outcome:
        """Gradient descent on the emulator from z0 (M, U) (``synthesis.optimize``)."""
        return optimize(
            self.value_and_grad,
            z0,
            settings,
            project=self.problem.project,
            evaluate=self.problem.evaluate,
            is_success=self.is_success,
            on_iteration=on_iteration,
            should_stop=self.should_stop,
        )

    def finish_with_levenberg_marquardt(self, out: Outcome, budget: int) -> Outcome:
        """Levenberg-Marquardt from a descent that ended short of the criterion on the emulator
        (``gauss_newton.py``); the better of the two (meets the criterion, else lower J) is kept."""
        spec = self.spec
        if not spec.success or out.success or out.stop in ("diverged", "cancelled") or budget <= 0:
            return out
        done = out.iterations
        lm = levenberg_marquardt(
            self.problem.residual_jacobian,
            self.problem.evaluate,
            out.z,
            max_iterations=budget,
            project=self.problem.project,
            is_success=self.is_success,
            polish_iterations=self.settings.polish_iterations,
            on_iteration=lambda i, j, b, ok: self.report(done + i, j, b, ok),
            should_stop=self.should_stop,
        )
        gauss_newton = self.gauss_newton
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

    def search_and_descend(self) -> tuple[Outcome, SearchSummary]:
        """The emulator phase: the search when the job asks for one (several starts or a global
        search), descent from the controller it chose, then Levenberg-Marquardt. The outcome counts
        the search's iterations, rollouts and history."""
        spec, settings, problem = self.spec, self.settings, self.problem
        z0 = problem.initial_points()
        searched = SearchSummary()
        if spec.optimizer.starts > 1 or spec.optimizer.global_generations > 0:
            j_init, ok_init = _initial(problem, z0, self.is_success)
            self.report(0, j_init, j_init, ok_init)
            z0, searched = _search(
                problem,
                spec,
                settings,
                self.values_and_grads,
                self.is_success,
                self.report,
                self.should_stop,
                [c.name for c in self.manifest.controls],
            )
            self.offset = searched.iterations
            # the history is what progress reported: the initial controller, then the best start's J
            searched.history = [j_init, *searched.history]
            searched.rollouts += 1
        outcome = self.descend(
            z0,
            replace(settings, max_iterations=max(1, settings.max_iterations - searched.iterations)),
            lambda i, j, b, ok: self.report(i, j, b, ok) if i > 0 or not searched.ran else None,
        )
        outcome = self.finish_with_levenberg_marquardt(outcome, spec.optimizer.gauss_newton_iterations)
        _count_search(outcome, searched)
        return outcome, searched

    def emulator_phase(self, outcome: Outcome, replayed: _PhysicsReplay) -> EmulatorPhase:
        """The controller found on the emulator alone, before any physics refinement, and how it
        ends on the emulator and on MuJoCo."""
        spec = self.spec
        emu = Replay.of(outcome.extra[0], spec, self.layout, self.labels)
        phys = Replay.of(replayed.states, spec, self.layout, self.labels)
        return EmulatorPhase(
            objective=clean(outcome.objective),
            success_emulator=emu.success if spec.success else None,
            success_physics=phys.success if spec.success else None,
            final_error_emulator=clean(emu.final_error),
            final_error_physics=clean(phys.final_error),
        )

    def refine(self, outcome: Outcome, replayed: _PhysicsReplay) -> _Refined:
        """Physics refinement: rounds of optimisation on the emulator corrected along the last
        replay, each replayed, until a controller meets the criterion on MuJoCo, a round diverges or
        is cancelled, or ``physics_rounds`` are done; the controller best on MuJoCo is kept."""
        stop, reason = outcome.stop, outcome.reason
        best = last = replayed
        rounds: list[RefinementRound] = []
        iterations = 0
        # without a criterion there is nothing for MuJoCo to miss: no refinement rounds
        rounds_allowed = self.spec.optimizer.physics_rounds if self.spec.success else 0
        for r in range(1, rounds_allowed + 1):
            if stop in ("diverged", "cancelled") or best.success:
                break
            if self.should_stop is not None and self.should_stop():
                stop, reason = "cancelled", f"cancelled during physics refinement round {r}"
                break
            self.phase, self.offset = "physics_refinement", outcome.iterations + iterations
            out_r = self.refine_round(last)
            iterations += out_r.iterations
            if out_r.stop == "diverged":
                rounds.append(
                    RefinementRound(
                        round=r, iterations=out_r.iterations, stop=out_r.stop, reason=out_r.reason
                    )
                )
                break
            _, held = self.problem.trajectory(out_r.z)
            last = self.replay(out_r.z, held)
            rounds.append(
                RefinementRound(
                    round=r,
                    iterations=out_r.iterations,
                    stop=out_r.stop,
                    objective_physics=clean(last.objective),
                    success_physics=last.success,
                )
            )
            if last.rank() > best.rank():
                best = last
            if out_r.stop == "cancelled":
                stop, reason = "cancelled", f"cancelled during physics refinement round {r}"
                break
        return _Refined(stop, reason, best, rounds, iterations)

    def refine_round(self, last: _PhysicsReplay) -> Outcome:
        """A few updates from the last replayed controller on the emulator corrected to reproduce
        that replay exactly (``ControlProblem.set_correction``), then Levenberg-Marquardt."""
        settings = self.settings
        self.problem.set_correction(last.states, last.held)
        refine = replace(
            settings,
            max_iterations=min(REFINE_ITERATIONS, settings.max_iterations),
            polish_iterations=min(settings.polish_iterations, REFINE_POLISH),
        )
        out = self.descend(last.z, refine, lambda i, j, b, ok: self.report(i, j, b, ok) if i > 0 else None)
        out = self.finish_with_levenberg_marquardt(
            out, min(REFINE_ITERATIONS, self.spec.optimizer.gauss_newton_iterations)
        )
        self.problem.set_correction(None)
        return out

    def result(
        self, outcome: Outcome, searched: SearchSummary, refined: _Refined, emulator_phase: EmulatorPhase
    ) -> JobOutcome:
        """The job's outcome for the controller refinement kept, on the plain emulator and on MuJoCo."""
        spec, problem, layout, labels = self.spec, self.problem, self.layout, self.labels
        best = refined.best
        emulated, _ = problem.trajectory(best.z)  # the plain emulator's prediction for the chosen controller
        emu = Replay.of(emulated, spec, layout, labels)
        phys = Replay.of(best.states, spec, layout, labels)
        # how far the physics ends from where the emulator said it would, in the goal's own metric
        transfer, _ = final_error(best.states[-1], emulated[-1].tolist(), spec.state_weights, layout)
        stop, reason = _missed_on_physics(refined, emu, phys, outcome)
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
            objective=clean(problem.score(emulated, best.held)),
            objective_physics=clean(best.objective),
            objective_history=clean(outcome.history),
            control_names=[c.name for c in self.manifest.controls],
            control_points=clean(problem.to_physical(best.z)),
            control_spacing_s=problem.spline.spacing,
            super_timestep=problem.super_dt,
            times=problem.spline.times(),
            controls=clean(best.held),
            emulated=Trajectory(states=clean(reported(emulated, layout))),
            physical=Trajectory(states=clean(reported(best.states, layout))),
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
            gauss_newton=self.gauss_newton,
            emulator_phase=emulator_phase,
            refinement=Refinement(
                rounds=refined.rounds, iterations=refined.iterations, physics_replays=len(refined.rounds) + 1
            ),
            target_state=spec.target_state,
            initial_state=spec.initial_state,
            state_labels=labels,
            spec=spec,
            wall_s=elapsed(self.t0),
        )
        log.info(
            "control job %s/%s: %s after %d iterations (+%d refining), success emulator=%s physics=%s, %.2fs",
            spec.task or "-",
            spec.model,
            stop,
            outcome.iterations,
            refined.iterations,
            emu.success,
            phys.success,
            result.wall_s,
        )
        return result


def _count_search(outcome: Outcome, searched: SearchSummary) -> None:
    """Counts the search's iterations, rollouts and J history into the outcome of the descent that
    followed it (the descent's first entry is the search's last)."""
    outcome.iterations += searched.iterations
    if outcome.stop == "cancelled":
        outcome.reason = f"cancelled after {outcome.iterations} iterations"
    outcome.rollouts += searched.rollouts
    if searched.ran:
        outcome.history = searched.history + outcome.history[1:]
    if outcome.iterations_to_success is not None:
        outcome.iterations_to_success += searched.iterations
    elif searched.success:
        outcome.iterations_to_success = searched.iterations


def _missed_on_physics(
    refined: _Refined, emu: Replay, phys: Replay, outcome: Outcome
) -> tuple[str, str | None]:
    """The job's stop and reason: ``missed_on_physics`` when the criterion held on the emulator
    during the search but the controller returned (the one best on MuJoCo after refinement) meets
    it on neither."""
    if refined.stop == "success" and not (emu.success or phys.success):
        return "missed_on_physics", (
            f"the criterion held on the emulator after {outcome.iterations_to_success} iterations but "
            f"not on MuJoCo, and {len(refined.rounds)} physics-refinement rounds did not reach it"
        )
    return refined.stop, refined.reason


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
