"""Control synthesis through the emulator against gradient-free search on MuJoCo (thesis 6.2, 6.3).

    python bench/control.py [--tasks a,b] [--gf-evals 3000] [--gf-methods sa,nm,cma] [--gf-seed 0]
                            [--curve-iterations 60] [--repeats 3]
                            [--out bench/results] [--artifacts artifacts] [--quick] [--json]

For each task (the thesis' pendulum-swing, lander-landing, truck-parking and dolphin-swim; by
default those whose model has an emulator in ``--artifacts``):

- ``run_job`` with the task's defaults: iterations until the success criterion holds on the
  emulator, the total gradient iterations (emulator phase, polishing and physics-refinement
  rounds), wall time per job (median of ``--repeats``, one thread), and the replay on MuJoCo of
  the emulator-only controller and of the one returned: success there, the final errors, the
  transfer error;
- simulated annealing, Nelder-Mead and CMA-ES (``neuroanimator.control.gradient_free``), each with
  a large and a small initial step (``--gf-steps``), on the *same* objective of the same control points evaluated on
  MuJoCo directly, from the same initial controller: objective evaluations (= physical
  simulations, 2,000 physical steps each) and wall time until they reach the objective value the gradient
  method's controller scores on MuJoCo, capped at ``--gf-evals`` per run ("not reached"
  otherwise, and the ratios are then lower bounds); the best of the runs is compared;
- gradient descent with and without momentum at fixed (η, α) (thesis 6.3.1, Figs. 6.13-6.15),
  each at its best learning rate of a small sweep, beside the default per-iteration (η, α) search:
  objective-vs-iteration curves written as ``control_<task>.png`` to ``--out``.

Prints a table; with ``--json`` the last line is one JSON object:
``{"tasks": [{"task", "iterations_to_success", "iterations", "wall_s", "success_emulator",
"success_physics", "final_error_emulator", "final_error_physics", "transfer_error",
"gradient_free_iterations", "gradient_free_method", "gradient_free_reached", "iteration_ratio",
"emulator_rollouts", "rollout_ratio", "wall_ratio", "bptt_networks", ...}], "settings": {...}}``;
a task without a criterion (dolphin-swim: as far as it can) has null success fields, and its
``forward_distance_m`` (emulator, MuJoCo) and ``transfer_ratio`` say how far the centre of mass
went and how close MuJoCo came to the emulator's distance.
"""

from __future__ import annotations

import argparse
import json
import logging
import statistics
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch

from neuroanimator.artifacts import registry
from neuroanimator.catalog.tasks import TASKS
from neuroanimator.contracts.controller import JobOutcome
from neuroanimator.control.gradient_free import Trace, cma_es, nelder_mead, simulated_annealing
from neuroanimator.control.job import load_problem, run_job
from neuroanimator.control.synthesis import Settings, optimize
from neuroanimator.control.validation import validate_job
from neuroanimator.goals.spec import JobSpec

log = logging.getLogger("bench.control")
# learning rates tried for the fixed-coefficient curves (raw gradients, so J's scale sets the rate)
SWEEP_RATES = (1.0, 0.3, 0.1, 0.03, 0.01, 3e-3, 1e-3, 3e-4, 1e-4, 3e-5, 1e-5)


def fixed_rate_curves(spec: JobSpec, root: Path, iterations: int, rates: tuple[float, ...]) -> dict[str, Any]:
    """Objective histories of the thesis' fixed-coefficient updates on the raw gradient (eqs. 6.2, 6.3):
    momentum (α = the task's) and plain gradient descent (α = 0), each at the rate of ``rates`` that
    ends lowest (the thesis took the largest rate that converged); plus the default search."""
    problem, _, _ = load_problem(spec, root)
    alpha = spec.optimizer.momentum
    out: dict[str, Any] = {}
    for label, a in (("momentum", alpha), ("gradient descent", 0.0)):
        best: tuple[float, float, list[float]] | None = None
        for eta in rates:
            run = optimize(
                lambda z: problem.value_and_grad(z)[:3],
                problem.initial_points(),
                Settings(
                    eta,
                    a,
                    iterations,
                    tolerance=0.0,
                    stop_on_success=False,
                    line_search=False,
                    normalize_gradient=False,
                ),
                project=problem.project,
            )
            final = run.history[-1] if run.history and run.stop != "diverged" else float("inf")
            if best is None or final < best[0]:
                best = (final, eta, run.history)
        assert best is not None
        out[label] = {"learning_rate": best[1], "momentum": a, "history": best[2]}
    search = optimize(
        lambda z: problem.value_and_grad(z)[:3],
        problem.initial_points(),
        Settings.from_spec(
            spec.optimizer.model_copy(
                update={"max_iterations": iterations, "stop_on_success": False, "tolerance": 0.0}
            )
        ),
        project=problem.project,
        evaluate=problem.evaluate,
    )
    out["momentum + (η, α) search (default)"] = {
        "learning_rate": spec.optimizer.learning_rate,
        "momentum": alpha,
        "history": search.history,
    }
    return out


def plot(
    task: str, curves: dict[str, Any], traces: list[Trace], target: float, grad_iters: int, out: Path
) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (a1, a2) = plt.subplots(1, 2, figsize=(12, 4.2), dpi=110)
    # a log scale where every J is positive (an error to drive to zero); a distance objective (the
    # dolphin's) is negative, and a log axis would draw nothing of it
    positive = all(v > 0 for c in curves.values() for v in c["history"])
    positive = positive and target > 0 and all(v > 0 for t in traces for v in t.best)
    for axis in (a1, a2):
        axis.set_yscale("log" if positive else "linear")
    for label, c in curves.items():
        a1.plot(
            range(len(c["history"])),
            c["history"],
            label=f"{label} (η={c['learning_rate']:g}, α={c['momentum']:g})",
        )
    a1.set_xlabel("iteration")
    a1.set_ylabel("objective J (emulator)")
    a1.set_title(f"{task}: gradient descent with and without momentum")
    a1.grid(alpha=0.3, which="both")
    a1.legend(fontsize=8)
    for t in traces:
        if t.evaluations:
            a2.plot(t.evaluations, t.best, label=f"{t.method} (MuJoCo)")
    a2.axhline(
        target, color="k", ls="--", lw=1, label=f"gradient method's J on MuJoCo ({grad_iters} iterations)"
    )
    a2.set_xlabel("objective evaluations (physical simulations)")
    a2.set_ylabel("best objective J (MuJoCo)")
    a2.set_title(f"{task}: gradient-free search on the physics")
    a2.grid(alpha=0.3, which="both")
    a2.legend(fontsize=8)
    fig.tight_layout()
    out.mkdir(parents=True, exist_ok=True)
    path = out / f"control_{task}.png"
    fig.savefig(path)
    plt.close(fig)
    return path


def distances(res: JobOutcome) -> dict[str, Any]:
    """A forward-distance task's distance in metres on the emulator and on MuJoCo: the direction-
    weighted displacement of its variables (for the dolphin, the nodes' centre of mass), and their ratio."""
    assert res.spec is not None and res.emulated is not None and res.physical is not None
    terms = [t for t in res.spec.terms if t.term == "forward_distance"]
    if not terms:
        return {"forward_distance_m": None, "transfer_ratio": None}
    (term,) = terms
    w = np.asarray(term.direction) / np.sum(term.direction)  # a weighted mean of the variables

    def moved(states: list[list[float | None]]) -> float:
        s = np.asarray(states, dtype=np.float64)[:, term.variables]
        return float(w @ (s[-1] - s[0]))

    emu, phys = moved(res.emulated.states), moved(res.physical.states)
    return {
        "forward_distance_m": {"emulator": emu, "mujoco": phys},
        "transfer_ratio": phys / emu if emu else None,
    }


def bench_task(name: str, args: argparse.Namespace) -> dict[str, Any]:
    root = Path(args.artifacts)
    spec = validate_job({"task": name}, root)
    results = [run_job(spec, root, threads=1) for _ in range(args.repeats)]
    res = results[-1]
    assert res.iterations is not None and res.refinement is not None and res.emulator_phase is not None
    wall = statistics.median(r.wall_s or 0.0 for r in results)
    # every gradient iteration counts: the emulator phase's and the physics-refinement rounds'
    iterations = res.iterations + res.refinement.iterations
    target = float(res.objective_physics if res.objective_physics is not None else np.inf)

    problem, _, path = load_problem(spec, root)
    physical = registry.load_physical_model(path)
    shape = problem.initial_points().shape
    low = np.broadcast_to(problem.z_low, shape).ravel()
    high = np.broadcast_to(problem.z_high, shape).ravel()
    x0 = problem.initial_points().ravel()

    def on_physics(xs: np.ndarray) -> np.ndarray:
        return problem.evaluate_physics(physical, xs.reshape(-1, *shape), threads=args.threads)

    # each method with a large and a small initial step (in units of the controls' half-ranges): the
    # lander needs small ones, the pendulum large ones; the best run is the one compared
    traces = []
    for step in args.gf_steps:
        if "sa" in args.gf_methods:
            tr = simulated_annealing(
                on_physics, x0, low=low, high=high, step=step, target=target, budget=args.gf_evals,
                seed=args.gf_seed,
            )  # fmt: skip
            tr.method = f"simulated_annealing(step={step:g})"
            traces.append(tr)
        if "nm" in args.gf_methods:
            tr = nelder_mead(
                on_physics, x0, low=low, high=high, step=step, target=target, budget=args.gf_evals
            )
            tr.method = f"nelder_mead(step={step:g})"
            traces.append(tr)
        if "cma" in args.gf_methods:
            tr = cma_es(
                on_physics, x0, low=low, high=high, sigma=step, target=target, budget=args.gf_evals,
                seed=args.gf_seed,
            )  # fmt: skip
            tr.method = f"cma_es(sigma={step:g})"
            traces.append(tr)
    reached = [t for t in traces if t.evaluations_to_target is not None]
    if reached:
        gf = min(reached, key=lambda t: t.evaluations_to_target or 0)
        gf_iters: int | None = gf.evaluations_to_target
        gf_wall = float(gf.wall_to_target_s or 0.0)
        ratio_iters = (gf_iters or 0) / max(iterations, 1)
    else:
        gf = min(traces, key=lambda t: t.best[-1] if t.best else np.inf)
        gf_iters, gf_wall = None, min(t.wall_s for t in traces)
        ratio_iters = args.gf_evals / max(iterations, 1)  # a lower bound: neither got there
    curves = fixed_rate_curves(spec, root, args.curve_iterations, args.rates)
    # what the default reached on the emulator
    target_emu = float(res.emulator_phase.objective if res.emulator_phase.objective is not None else np.inf)
    png = plot(name, curves, traces, target, iterations, Path(args.out))
    fixed = {
        label: {
            "learning_rate": c["learning_rate"],
            "momentum": c["momentum"],
            "final_objective": c["history"][-1] if c["history"] else None,
            "iterations_to_target": next((i for i, v in enumerate(c["history"]) if v <= target_emu), None),
        }
        for label, c in curves.items()
    }
    return {
        "task": name,
        "model": res.model,
        "control_variables": int(np.prod(shape)),
        "iterations_to_success": res.iterations_to_success,
        "iterations": iterations,
        "emulator_phase_iterations": res.iterations,
        "refinement_iterations": res.refinement.iterations,
        "physics_replays": res.refinement.physics_replays,
        "success_physics_emulator_phase": res.emulator_phase.success_physics,
        "final_error_physics_emulator_phase": res.emulator_phase.final_error_physics,
        "emulator_rollouts": res.emulator_rollouts,
        "bptt_networks": res.bptt_networks,
        **distances(res),
        "wall_s": wall,
        "success_emulator": res.success_emulator,
        "success_physics": res.success_physics,
        "final_error_emulator": res.final_error_emulator,
        "final_error_physics": res.final_error_physics,
        "transfer_error": res.transfer_error,
        "objective_emulator": res.objective,
        "objective_physics": target,
        "gradient_free_iterations": gf_iters,
        "gradient_free_method": gf.method,
        "gradient_free_reached": gf_iters is not None,
        "gradient_free_budget": args.gf_evals,
        "gradient_free_wall_s": gf_wall,
        "gradient_free": [t.to_dict() for t in traces],
        "iteration_ratio": ratio_iters,
        # MuJoCo simulations of the gradient-free search per emulator trajectory of the gradient
        # method (its global search, starts, line-search candidates and gradients all count)
        "rollout_ratio": (gf_iters or args.gf_evals) / max(res.emulator_rollouts or 0, 1),
        "wall_ratio": gf_wall / wall if wall > 0 else None,
        "fixed_rate": fixed,
        "plot": str(png),
    }


def table(rows: list[dict[str, Any]]) -> str:
    def f(x: Any, fmt: str = ".3g") -> str:
        return "–" if x is None else format(x, fmt)

    lines = [
        "| task | vars | iterations to success (total) | wall s | MuJoCo success / error, emulator-only controller"
        " | success emulator / MuJoCo | final error emulator / MuJoCo | transfer error"
        " | emulator rollouts | gradient-free evals to the same J | iteration ratio | rollout ratio"
        " | wall ratio |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        reached = r["gradient_free_reached"]
        gf = (
            f"{r['gradient_free_iterations']} ({r['gradient_free_method']})"
            if reached
            else f"not reached in {r['gradient_free_budget']}"
        )
        bound = "" if reached else "> "
        lines.append(
            f"| {r['task']} | {r['control_variables']} | {f(r['iterations_to_success'], 'd')} ({r['iterations']}) | {r['wall_s']:.2f}"
            f" | {'yes' if r['success_physics_emulator_phase'] else 'no'} / {f(r['final_error_physics_emulator_phase'])}"
            f" | {'yes' if r['success_emulator'] else 'no'} / {'yes' if r['success_physics'] else 'no'}"
            f" | {f(r['final_error_emulator'])} / {f(r['final_error_physics'])} | {f(r['transfer_error'])}"
            f" | {r['emulator_rollouts']} | {gf} | {bound}{r['iteration_ratio']:.0f}×"
            f" | {bound}{r['rollout_ratio']:.2f}× | {bound}{f(r['wall_ratio'], '.1f')}× |"
        )
    moving = [r for r in rows if r["forward_distance_m"]]
    if moving:
        lines += [
            "",
            "| task | BPTT through | distance on the emulator m | on MuJoCo m | MuJoCo / emulator |",
        ]
        lines.append("|---|---|---|---|---|")
        for r in moving:
            d = r["forward_distance_m"]
            lines.append(
                f"| {r['task']} | {r['bptt_networks']} networks | {d['emulator']:.3f} | {d['mujoco']:.3f}"
                f" | {f(r['transfer_ratio'], '.2f')} |"
            )
    lines.append("")
    lines.append(
        "| task | update | η | α | final J after the curve's iterations | iterations to the default's J |"
    )
    lines.append("|---|---|---|---|---|---|")
    for r in rows:
        for label, c in r["fixed_rate"].items():
            lines.append(
                f"| {r['task']} | {label} | {c['learning_rate']:g} | {c['momentum']:g} | {f(c['final_objective'], '.4g')}"
                f" | {f(c['iterations_to_target'], 'd')} |"
            )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument(
        "--tasks", default=None, help="comma-separated (default: those with an emulator in --artifacts)"
    )
    p.add_argument(
        "--threads", type=int, default=1, help="MuJoCo threads of a batch of gradient-free evaluations"
    )
    p.add_argument("--artifacts", default="artifacts")
    p.add_argument(
        "--gf-evals", type=int, default=3000, help="evaluation budget of each gradient-free method"
    )
    p.add_argument(
        "--gf-steps",
        default="0.3,0.03",
        help="initial steps (simplex edge, CMA-ES sigma) of the gradient-free runs",
    )
    p.add_argument(
        "--gf-methods",
        default="sa,nm,cma",
        help="gradient-free methods: sa (simulated annealing), nm (Nelder-Mead), cma (CMA-ES)",
    )
    p.add_argument("--gf-seed", type=int, default=0, help="random seed of annealing and CMA-ES")
    p.add_argument("--curve-iterations", type=int, default=60, help="iterations of the fixed-rate curves")
    p.add_argument("--repeats", type=int, default=3, help="run_job repeats for the wall time (median)")
    p.add_argument("--out", default="bench/results", help="folder for the PNG curves")
    p.add_argument("--quick", action="store_true", help="tiny settings for a smoke test")
    p.add_argument("--json", action="store_true")
    args = p.parse_args(argv)
    args.rates = SWEEP_RATES
    args.gf_steps = [float(x) for x in args.gf_steps.split(",")]
    args.gf_methods = args.gf_methods.split(",")
    if not args.gf_methods or set(args.gf_methods) - {"sa", "nm", "cma"}:
        p.error(f"--gf-methods takes sa, nm and cma, comma-separated; got {','.join(args.gf_methods)!r}")
    if args.quick:
        args.gf_evals, args.curve_iterations, args.repeats, args.rates = 40, 3, 1, (0.01,)
    logging.basicConfig(level=logging.WARNING)
    torch.set_num_threads(1)
    t0 = time.perf_counter()
    rows = []
    served = [t for t in TASKS if (Path(args.artifacts) / TASKS[t].model).is_dir()]
    for name in (args.tasks or ",".join(served)).split(","):
        if name not in TASKS:
            p.error(f"unknown task {name!r}; tasks are {sorted(TASKS)}")
        rows.append(bench_task(name, args))
        print(f"{name}: done ({time.perf_counter() - t0:.0f} s)", file=sys.stderr, flush=True)
    print(table(rows))
    if args.json:
        settings = {
            k: getattr(args, k)
            for k in ("gf_evals", "gf_steps", "gf_methods", "gf_seed", "curve_iterations", "repeats", "quick")
        }
        settings["rates"] = list(args.rates)
        print(json.dumps({"tasks": rows, "settings": settings}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
