"""Evaluation of an artifact against MuJoCo: one-step error on held-out data, rollout error curves
(thesis Fig. 6.6) and rollout errors in physical units, all from the artifact alone (its ONNX graph,
weights and MJCF).
"""

from __future__ import annotations

import importlib
import logging
from pathlib import Path

import numpy as np
import torch
from numpy.typing import NDArray

from neuroanimator.artifacts import registry
from neuroanimator.artifacts import store as artifacts
from neuroanimator.core.manifest import Manifest
from neuroanimator.core.results import PhysicalErrors, RolloutCurve
from neuroanimator.emulator.hierarchy import HierarchicalEmulator
from neuroanimator.evaluation import physical_errors
from neuroanimator.export.runtime import OnnxEmulator
from neuroanimator.sim import sampling
from neuroanimator.sim.driver import check_params, load_driver
from neuroanimator.sim.model import PhysicalModel
from neuroanimator.training.hierarchy import fit_linear, network_data
from neuroanimator.training.train import (
    apply_linear,
    held_out_examples,
    held_out_seed,
    relative_error,
    to_tensors,
)

log = logging.getLogger(__name__)
EVAL_SEED = 20_000  # rollout trials use the same initial states and control functions for every n


def one_step_errors(
    path: Path, model: PhysicalModel, manifest: Manifest, count: int | None = None
) -> dict[str, float]:
    """Relative one-step error of the emulator and of the linear baseline on fresh held-out data (of
    a hierarchy: its worst network's, ``hierarchy_one_step_errors``)."""
    cfg = manifest.train_config
    simulated = manifest.metrics.examples if not cfg.mirror else (manifest.metrics.examples + 1) // 2
    test = held_out_examples(
        model,
        manifest.substeps,
        count or cfg.test_examples,
        held_out_seed(cfg.seed),
        progress=False,
        sampler=cfg.sampler,
        like=simulated,
    )
    if manifest.emulator.parts:
        errors = hierarchy_one_step_errors(path, model, test)
        worst = max(errors, key=lambda n: errors[n]["one_step_rel_error"])
        return errors[worst]
    emu = artifacts.load_torch(path)
    linear = np.load(path / registry.LINEAR_FILE)
    s, u, f, nxt = to_tensors(test)
    with torch.no_grad():
        x = emu.network_inputs(s, u, f)
        y = emu.network_targets(s, nxt)
        return {
            "one_step_rel_error": relative_error(emu.network(x), y),
            "linear_baseline_rel_error": relative_error(apply_linear(linear, x), y),
        }


def hierarchy_one_step_errors(
    path: Path, model: PhysicalModel, test: sampling.Examples
) -> dict[str, dict[str, float]]:
    """Each network's relative one-step error on held-out transitions ``test``, on its own targets (the
    global network on the frames, each local network on its part given the true next frames), beside
    a linear model of the same inputs fitted to those same transitions: the best any linear model
    does there, so the ratio to it is a conservative one. Keys: the networks' names."""
    emu = artifacts.load_emulator(path)
    assert isinstance(emu, HierarchicalEmulator)
    s, u, _, nxt = to_tensors(test)
    out: dict[str, dict[str, float]] = {}
    with torch.no_grad():
        for (name, net), d in zip(emu.networks, network_data(emu, s, u, nxt), strict=True):
            x = net.network_inputs(d.state, d.controls, d.extra)
            y = net.network_targets(d.state, d.next_state)
            out[name] = {
                "one_step_rel_error": relative_error(net.network(x), y),
                "linear_baseline_rel_error": relative_error(apply_linear(fit_linear(x, y), x), y),
            }
    return out


def held_controls(
    model: PhysicalModel, rng: np.random.Generator, trials: int, steps: int, substeps: int
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Typical control and force functions sampled at super-step starts: (trials, M, U), (trials, M, F).

    The functions depend only on the generator and the duration, so every n sees the same ones.
    """
    times = np.arange(steps, dtype=np.float64) * model.dt
    u = model.typical_controls(rng, trials, times)
    f = model.typical_forces(rng, trials, times)
    starts = np.arange(0, steps, substeps)
    return u[:, starts], f[:, starts]


def driven_rollouts(
    model: PhysicalModel, emu: OnnxEmulator, substeps: int, trials: int, steps: int, seed: int
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """For a model with a driver (``ModelSpec.driver``, the runner's running controller) at its default
    parameters: from the driver's start with every velocity perturbed by N(0, 0.01), the driver closes
    its loop through the emulator and, from the same start, through MuJoCo, a driver instance per run
    and side. Returns the starts (trials, S), the emulated and the physical states after each of the
    M super-steps (trials, M, S); a run whose emulated state stops being finite stays where it was."""
    spec = model.spec.driver
    assert spec is not None
    params = check_params(spec, model.name, {})
    rng = np.random.default_rng(seed)
    start = load_driver(spec, model, substeps, params).start()
    full = model.to_physics(np.repeat(start[None], trials, axis=0))
    m_ = model.mj_model
    full[:, 1 + m_.nq : 1 + m_.nq + m_.nv] += rng.normal(0.0, 0.01, (trials, m_.nv))
    s0 = np.asarray(model.from_physics(full))
    on_emu = [load_driver(spec, model, substeps, params) for _ in range(trials)]
    on_mj = [load_driver(spec, model, substeps, params) for _ in range(trials)]
    forces = np.zeros((trials, model.num_forces))
    m = steps // substeps
    pred, phys = np.zeros((trials, m, model.state_size)), np.zeros((trials, m, model.state_size))
    se, sm = s0.copy(), s0.copy()
    for k in range(m):
        ue = np.stack([d.act(x) for d, x in zip(on_emu, se, strict=True)])
        um = np.stack([d.act(x) for d, x in zip(on_mj, sm, strict=True)])
        nxt = np.asarray(
            emu.step(se, ue, forces if model.num_forces else None, validate=False), dtype=np.float64
        )
        broken = ~np.isfinite(nxt).all(axis=1)
        nxt[broken] = se[broken]
        se = nxt
        sm = model.step_held(sm, um, forces if model.num_forces else None, substeps)
        pred[:, k], phys[:, k] = se, sm
    return s0, pred, phys


def source_windows(
    model: PhysicalModel, source: str, substeps: int, trials: int, steps: int, seed: int
) -> tuple[NDArray[np.float64], ...]:
    """For a model whose motion comes from its data source (the runner's running controller): windows
    of that motion (``sequences``), as long as the source's runs allow, and the controls that replay
    them exactly on MuJoCo: starts (trials, S), controls (trials, M, U), forces (trials, M, F) and the
    recorded states (trials, M, S) after each super-step. The emulator replays the same controls open
    loop, as it does the typical controls of other models."""
    module = importlib.import_module(source)
    horizon = min(steps // substeps, int(module.longest_window(model, substeps)))
    seqs = module.sequences(model, substeps, trials, horizon, seed, progress=False)
    return seqs.states[:, 0], seqs.controls, seqs.forces, seqs.states[:, 1:]


def rollout_curve(
    path: Path,
    model: PhysicalModel,
    substeps: int,
    trials: int = 30,
    steps: int = 6000,
    seed: int = EVAL_SEED,
) -> RolloutCurve:
    """Mean absolute error between emulator and MuJoCo rollouts from the same initial states under the
    same held controls, over trials and state variables, each normalised by its standard deviation."""
    return rollout_errors(path, model, substeps, trials, steps, seed)[0]


def rollout_errors(
    path: Path,
    model: PhysicalModel,
    substeps: int,
    trials: int = 30,
    steps: int = 6000,
    seed: int = EVAL_SEED,
) -> tuple[RolloutCurve, PhysicalErrors]:
    """The normalised rollout curve (``rollout_curve``) and the same rollouts' errors in physical units
    (root position in metres, attitude in degrees, joints in radians) at 1, 5, 10 and 20 s."""
    source = model.spec.data_source
    emu = OnnxEmulator(path / registry.ONNX_FILE, threads=2)
    pred: NDArray[np.float64] | None = None
    if model.spec.driver is not None:  # its own controller closes the loop on both sides
        s0, pred, phys = driven_rollouts(model, emu, substeps, trials, steps, seed)
        u = np.zeros((trials, phys.shape[1], model.num_controls))
    elif source is not None:  # a model driven by a controller: windows of its own motion, replayed
        s0, u, f, phys = source_windows(model, source, substeps, trials, steps, seed)
    else:
        rng = np.random.default_rng(seed)
        s0 = model.initial_states(rng, trials)
        u, f = held_controls(model, rng, trials, steps, substeps)
        # physics: every held value repeated for its n physical steps
        phys = model.simulate(
            s0,
            np.repeat(u, substeps, axis=1),
            np.repeat(f, substeps, axis=1) if model.num_forces else None,
        )[:, substeps - 1 :: substeps]  # (trials, M, S) at the super-step boundaries
    m = u.shape[1]
    if pred is None:
        controls, pushes = (u if model.num_controls else None), (f if model.num_forces else None)
        pred = np.asarray(emu.rollout(s0, controls, pushes, steps=m)[:, 1:], dtype=np.float64)
    std = np.concatenate([s0[:, None], phys], axis=1).reshape(-1, model.state_size).std(axis=0)
    std = np.where(std > 1e-9, std, 1.0)
    err = np.abs(pred - phys) / std
    err = np.where(np.isfinite(err), err, 1e6)  # a diverged emulator shows as a huge error, not NaN
    curve = np.concatenate([[0.0], err.mean(axis=(0, 2))])
    t = np.arange(m + 1) * substeps * model.dt
    series = physical_errors.error_series(model.layout, pred, phys)
    return (
        RolloutCurve(t=[round(float(x), 6) for x in t], error=[float(e) for e in curve]),
        physical_errors.summarize(series, substeps * model.dt),
    )


def plot_curves(curves: dict[int, RolloutCurve], title: str, out: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4), dpi=110)
    styles = {25: "-", 50: "--", 100: "-."}
    for n, c in sorted(curves.items()):
        ax.plot(c.t, c.error, styles.get(n, ":"), label=f"N^{n}")
    ax.set_xlabel("simulated time (s)")
    ax.set_ylabel("mean |emulator − MuJoCo| / std")
    ax.set_title(title)
    ax.grid(alpha=0.3)
    ax.legend()
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out)
    plt.close(fig)
