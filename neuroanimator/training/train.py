"""Training an emulator, top to bottom: simulate examples, fit T^σ, train N^σ, fit the linear baseline.

Read ``train`` from the top: it is the whole recipe. The configuration is one dataclass
(``neuroanimator.core.train_config``), saved in full with every artifact.
"""

from __future__ import annotations

import dataclasses
import importlib
import logging
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import mujoco
import numpy as np
import torch
from torch import Tensor
from tqdm import tqdm

from neuroanimator.core.manifest import EnvelopeGroup
from neuroanimator.core.train_config import TrainConfig
from neuroanimator.emulator import proximity
from neuroanimator.emulator.articulated import ArticulatedCore, articulated_core, make_articulated, ridge_fit
from neuroanimator.emulator.clearance import (
    Clearance,
    floor_contact,
    geom_name,
    ground_geoms,
    limited_site_tendons,
    near_geoms,
)
from neuroanimator.emulator.regularizer import regularization
from neuroanimator.emulator.structured import FrameConfig, JointLimit, StructuredEmulator
from neuroanimator.sim import sampling
from neuroanimator.sim.mirror import check_mirror, mirror_map, with_mirror_images
from neuroanimator.sim.model import PhysicalModel
from neuroanimator.training.data_cache import cached
from neuroanimator.training.envelope import examples_envelope
from neuroanimator.training.loop_choice import LoopChoice, loop_choice
from neuroanimator.training.metrics import HeldOutErrors, RolloutMetrics, TrainingExtras, TrainingMetrics
from neuroanimator.training.trim import trim

log = logging.getLogger(__name__)


class _Network(torch.nn.Module):
    """N^σ as one module (the MLP and the linear path) for the optimiser: (B, D) -> (B, S)."""

    def __init__(self, emu: StructuredEmulator) -> None:
        super().__init__()
        self.core = emu.core
        self.skip = emu.skip

    def forward(self, x: Tensor) -> Tensor:
        y = self.core(x)
        return y + self.skip(x) if self.skip is not None else y

    def loss(self, x: Tensor, y: Tensor) -> Tensor:
        """The training loss of a batch x (B, D), y (B, S): the mean squared error, or an articulated
        hierarchy's own (``ArticulatedCore.training_loss``: each member of an ensembled network alone)."""
        if isinstance(self.core, ArticulatedCore) and self.core.members > 1:
            return self.core.training_loss(x, y)
        return torch.mean((self(x) - y) ** 2)


class TrainingDiverged(RuntimeError):
    """Training produced a non-finite loss; no artifact is written."""


@dataclass
class TrainResult:
    emulator: StructuredEmulator
    config: TrainConfig
    metrics: TrainingMetrics
    linear: np.ndarray  # (D + 1, S) least-squares baseline in the network's normalised space
    data_sha256: str
    envelope: list[EnvelopeGroup] | None = None  # per state group, the range of the training states


def frame_config(model: PhysicalModel, frame: str = "auto") -> FrameConfig:
    """The emulator's symmetries for a model; external forces on a body are rotated together.

    ``frame``: ``"body"`` (the default, ``"auto"``, for a root with a quaternion) rotates world vectors
    into the root's body frame, gravity entering as the body-frame up vector; ``"heading"`` removes
    only the rotation about the gravity axis.
    """
    if frame not in ("auto", "body", "heading"):
        raise ValueError(f"frame must be 'auto', 'body' or 'heading', got {frame!r}")
    fr = model.frame
    body = frame in ("auto", "body") and model.layout.find("quaternion") is not None
    pairs: list[tuple[int, ...]] = []
    rotate = fr.rotate
    if rotate and model.num_forces:
        by_body: dict[tuple[str, int], dict[int, int]] = {}
        for i, f in enumerate(model.spec.forces):
            by_body.setdefault((f.body, f.component // 3), {})[f.component % 3] = i
        for comps in by_body.values():
            if 0 in comps and 1 in comps:
                pairs.append((comps[0], comps[1], comps[2]) if body and 2 in comps else (comps[0], comps[1]))
            elif 0 in comps or 1 in comps:
                rotate = False  # a lone horizontal component is not rotation-invariant: keep world frame
    controls = [v if body else v[:2] for v in (model.world_control_vectors or ())]
    return FrameConfig(
        translate=fr.translate,
        rotate=rotate,
        force_pairs=tuple(pairs) if rotate else (),
        body=body and rotate,
        control_pairs=tuple(controls) if rotate else (),
        slides=fr.slides,
    )


def joint_limits(model: PhysicalModel) -> list[JointLimit]:
    """The limited hinge and slide joints of ``model`` whose angle (or position) is a state column,
    with the column of their rate when the state has it."""
    m = model.mj_model
    columns: dict[tuple[str, int], int] = {}
    for g, sl in model.layout.group_slices():
        if g.size == 1 and g.kind in ("angle", "scalar"):
            columns[(g.source, g.address)] = sl.start
    kinds = (int(mujoco.mjtJoint.mjJNT_HINGE), int(mujoco.mjtJoint.mjJNT_SLIDE))
    limits = []
    for j in range(m.njnt):
        if not m.jnt_limited[j] or int(m.jnt_type[j]) not in kinds:
            continue
        pos = columns.get(("qpos", int(m.jnt_qposadr[j])))
        if pos is None:
            continue
        low, high = (float(v) for v in m.jnt_range[j])
        limits.append(JointLimit(pos, columns.get(("qvel", int(m.jnt_dofadr[j]))), low, high))
    return limits


def build_emulator(
    model: PhysicalModel,
    cfg: TrainConfig,
    states: np.ndarray | None = None,
    near: Sequence[str] | None = None,
) -> StructuredEmulator:
    """The emulator ``cfg`` describes for ``model``: one network, or, for a model with branches, an
    articulated hierarchy (``neuroanimator.emulator.articulated``): a trunk network ``cfg.hidden`` wide and limb
    networks ``cfg.branch_hidden`` wide.
    With ``cfg.clearance``, the geoms probed are those that come near the floor in ``states`` (N, S)
    (every geom that can touch it when none are given; ``near``: those geoms, already found); with
    ``cfg.proximity``, the pairs of geoms that touch each other in ``states`` (a hierarchy's networks
    read none)."""
    branches = model.spec.branches
    emu = StructuredEmulator(
        model.layout,
        model.num_controls,
        model.num_forces,
        frame_config(model, cfg.frame),
        cfg.hidden,
        cfg.activation,
        skip=cfg.skip and cfg.preset != "thesis" and not branches,
        limits=joint_limits(model) if cfg.limits else (),
        horizon=model.dt * cfg.substeps,
        clearance=contact_features(
            model,
            model.dt * cfg.substeps,
            states,
            floor=bool(cfg.clearance),  # None: none until the data decide (``with_contact_features``)
            pairs=cfg.proximity and not branches,
            tendons=cfg.limits and not branches,
            near=near,
        ),
    )
    if branches:
        make_articulated(
            emu, branches, model.control_names, cfg.hidden, cfg.branch_hidden or cfg.hidden, cfg.members
        )
    elif cfg.members != 1:
        raise ValueError(
            f"{model.name}: members ({cfg.members}) ensemble the networks of an articulated hierarchy; "
            "this model has one network"
        )
    return emu


PAIR_PROBE_STATES = 2000  # states searched for touching pairs of geoms


def contact_features(
    model: PhysicalModel,
    horizon: float,
    states: np.ndarray | None,
    *,
    floor: bool,
    pairs: bool,
    tendons: bool = False,
    near: Sequence[str] | None = None,
) -> Clearance | None:
    """With ``floor``, the clearance features of the geoms of ``model`` that come near its floor in
    ``states`` (every geom that can touch it when None); with ``pairs``, the distances between the pairs
    of geoms that touch each other in ``states`` (``neuroanimator.emulator.proximity``; none when None); with
    ``tendons``, the slack of each limited tendon through sites (a string); over ``horizon`` seconds;
    ``near``: the geoms near the floor in ``states``, when already found. None when there are none."""
    geoms: list[str] = []
    if floor and near is not None:
        geoms = list(near)
    elif floor:
        geoms = ground_geoms(model.mj_model) if states is None else near_geoms(model, states, horizon)
    touching = touching_pairs(model, states) if pairs and states is not None else []
    strings = limited_site_tendons(model.mj_model) if tendons else []
    return Clearance(model, geoms, horizon, touching, strings) if geoms or touching or strings else None


def touching_pairs(model: PhysicalModel, states: np.ndarray) -> list[tuple[str, str]]:
    """The pairs of geoms, by name, that touch each other (not the floor) in some of ``states`` (N, S)."""
    m = model.mj_model
    picked = states[:: max(1, len(states) // PAIR_PROBE_STATES)]
    qpos = model.to_physics(picked)[:, 1 : 1 + m.nq]  # full physics rows: time, qpos, ...
    floors = {
        g for g in range(m.ngeom) if m.geom_bodyid[g] == 0 and m.geom_type[g] == mujoco.mjtGeom.mjGEOM_PLANE
    }
    return [(geom_name(m, a), geom_name(m, b)) for a, b in proximity.touching_pairs(m, qpos, floors)]


def generate_examples(
    model: PhysicalModel, substeps: int, count: int, seed: int, progress: bool, sampler: str = "runs"
) -> sampling.Examples:
    """``count`` training transitions of ``model``: from its own data source (``ModelSpec.data_source``,
    a model whose motion comes from a controller) or else ``sampler``'s runs under typical controls."""
    source = model.spec.data_source
    if source is None:
        return sampling.generate(model, substeps, count, seed, progress=progress, sampler=sampler)
    data: sampling.Examples = importlib.import_module(source).examples(
        model, substeps, count, seed, progress=progress
    )
    data.check_finite(f"training data from {source}")
    return data


def held_out_examples(
    model: PhysicalModel,
    substeps: int,
    count: int,
    seed: int,
    progress: bool,
    sampler: str = "runs",
    *,
    like: int,
) -> sampling.Examples:
    """``count`` held-out transitions of ``model``, drawn as its training set of ``like`` examples is
    (``sampling.generate_held_out``), or from its own data source as ``generate_examples``."""
    if model.spec.data_source is not None:
        return generate_examples(model, substeps, count, seed, progress, sampler)
    return sampling.generate_held_out(
        model, substeps, count, seed, like=like, progress=progress, sampler=sampler
    )


def held_out_key(model: PhysicalModel, cfg: TrainConfig, like: int) -> str:
    """The data cache's name for a held-out set drawn like ``like`` training examples (``held_out_examples``;
    a data source's held-out set is its own, whatever the training count)."""
    return cfg.sampler if model.spec.data_source is not None else f"{cfg.sampler}, held out like {like}"


def cached_examples(
    data_cache: Path | None, model: PhysicalModel, cfg: TrainConfig, count: int
) -> sampling.Examples:
    """``generate_examples`` for ``cfg``'s super-step, seed and sampler, through the data cache."""
    return cached(
        data_cache, model, cfg.substeps, count, cfg.seed, cfg.sampler,
        lambda: generate_examples(model, cfg.substeps, count, cfg.seed, cfg.progress, cfg.sampler),
        sampling.Examples,
    )  # fmt: skip


def cached_held_out(
    data_cache: Path | None, model: PhysicalModel, cfg: TrainConfig, count: int, *, like: int
) -> sampling.Examples:
    """``held_out_examples`` (seed ``held_out_seed(cfg.seed)``) through the data cache."""
    seed = held_out_seed(cfg.seed)
    return cached(
        data_cache, model, cfg.substeps, count, seed, held_out_key(model, cfg, like),
        lambda: held_out_examples(model, cfg.substeps, count, seed, cfg.progress, cfg.sampler, like=like),
        sampling.Examples,
    )  # fmt: skip


def to_tensors(ex: sampling.Examples) -> tuple[Tensor, Tensor | None, Tensor | None, Tensor]:
    s = torch.from_numpy(ex.states).float()
    u = torch.from_numpy(ex.controls).float() if ex.controls.shape[1] else None
    f = torch.from_numpy(ex.forces).float() if ex.forces.shape[1] else None
    return s, u, f, torch.from_numpy(ex.next_states).float()


LOCAL_CHUNK = 100_000  # examples transformed at a time


def local_examples(
    emu: StructuredEmulator, s: Tensor, u: Tensor | None, f: Tensor | None, nxt: Tensor
) -> tuple[Tensor, Tensor]:
    """T'_x and (T'_y T^Δ_y)^-1 of N examples: inputs (N, D) and targets (N, S) in the local frame,
    before T^σ. In chunks: the clearance's forward kinematics holds about 8 kB an example while it runs
    (12 GB for the runner's 1.6 million), the results a few hundred bytes."""
    xs, ys = [], []
    for i in range(0, s.shape[0], LOCAL_CHUNK):
        part = slice(i, i + LOCAL_CHUNK)
        xs.append(emu.local_inputs(s[part], None if u is None else u[part], None if f is None else f[part]))
        ys.append(emu.delta_to_local(s[part], nxt[part] - s[part]))
    return torch.cat(xs), torch.cat(ys)


def relative_error(pred: Tensor, target: Tensor) -> float:
    """‖ŷ − y‖² / ‖y − mean(y)‖² over all rows and outputs (1 − R²), in the normalised target space."""
    num = ((pred - target) ** 2).sum()
    den = ((target - target.mean(dim=0)) ** 2).sum()
    return float(num / den.clamp_min(1e-12))


def fit_linear(x: Tensor, y: Tensor) -> np.ndarray:
    """Least-squares affine map (D+1, S) from normalised inputs to normalised targets."""
    xa = torch.cat([x, torch.ones(x.shape[0], 1)], dim=1).double()
    sol = torch.linalg.lstsq(xa, y.double()).solution
    return sol.numpy()


def apply_linear(w: np.ndarray, x: Tensor) -> Tensor:
    xa = torch.cat([x, torch.ones(x.shape[0], 1)], dim=1).double()
    return (xa @ torch.from_numpy(w)).float()


def held_out_seed(seed: int) -> int:
    """The seed of the held-out test set: a different stream from the training data's."""
    return seed + 1_000_003


def train(
    model: PhysicalModel, cfg: TrainConfig, spent: float = 0.0, data_cache: Path | None = None
) -> TrainResult:
    """Simulate data, fit normalisation, train N^σ with early stopping, evaluate on held-out data.

    ``spent``: seconds of ``cfg.time_budget`` used before the call (``neuro train``: loading the model,
    its contact check and super-step probes), so that the whole command keeps to the budget.
    ``data_cache``: a directory where simulated examples are kept and read back
    (``neuroanimator.training.data_cache``; None: simulate every time)."""
    # the configuration, the network it describes (built before sampling: its size sets how many
    # examples to simulate), and the clock the time budget counts from
    cfg = cfg.resolved()
    torch.manual_seed(cfg.seed)
    torch.set_num_threads(cfg.threads)
    t_start = time.perf_counter()
    t_budget = t_start - max(spent, 0.0)  # the phases' caps count from here
    if spent > 0 and cfg.time_budget is not None:
        log.info("time budget %.0f s: %.0f s spent before the training", cfg.time_budget, spent)
    emu = build_emulator(model, cfg)
    choice = loop_choice(model, cfg)  # before sampling: a model without a loop check fails at once
    weights = sum(p.numel() for p in emu.parameters())
    plan = examples_plan(model, cfg, weights, time.perf_counter() - t_budget)
    count = plan.examples

    # 1. data: training (+ validation) and an independent held-out test set
    runs, data, test = training_data(model, cfg, plan, data_cache)
    t_data = time.perf_counter() - t_start
    emu, cfg, clearance_reason = with_contact_features(model, cfg, emu, data)

    # 2. T^σ from the training data (transformed by T'_x and (T'_y T^Δ_y)^-1 first, thesis 4.5.2)
    x_tr, y_tr, x_val, y_val = normalized_examples(emu, data, cfg)

    # 3. the linear baseline, fitted on the training inputs; it also starts the network's linear path
    linear = fit_linear(x_tr, y_tr)
    composed = articulated_core(emu)
    if composed is not None:
        composed.start_from_linear(x_tr, y_tr)
    elif emu.skip is not None:
        start_from_linear(emu, linear)

    # 4. the core network
    core_cfg = dataclasses.replace(cfg, max_seconds=one_step_seconds(cfg, time.perf_counter() - t_budget))
    final_lr = train_core(emu, x_tr, y_tr, x_val, y_val, core_cfg, choice)

    # 5. training over rollouts, from the one-step solution
    rollout_metrics = rollout_phase(
        model, emu, cfg, count, runs, t_budget, final_lr, (x_tr, y_tr, x_val, y_val)
    )

    # 6. trimmed at the model's operating point (a hover), then held-out evaluation, and the result
    trimmed = trim(model, emu, cfg.substeps) if articulated_core(emu) is None else None
    errors, per_network = held_out_errors(emu, linear, test, (x_tr, y_tr, x_val, y_val))
    metrics: TrainingMetrics = {
        "weights": weights,
        "examples": count,
        "test_examples": len(test),
        **errors,
        **rollout_metrics,
        **training_extras(choice, per_network, plan.reason, clearance_reason),
        "data_seconds": round(t_data, 2),
        "train_seconds": round(time.perf_counter() - t_start - t_data, 2),
        "total_seconds": round(time.perf_counter() - t_start, 2),
    }
    if trimmed:
        metrics["operating_residual"] = trimmed
    log.info(
        "%s n=%d: one-step relative error %.3g (linear %.3g), %.0f s",
        model.name,
        cfg.substeps,
        errors["one_step_rel_error"],
        errors["linear_baseline_rel_error"],
        metrics["total_seconds"],
    )
    emu.regularizer = regularization(
        model.layout, model.spec.regularizer, model.num_controls, cfg.regularizer_steps
    )
    return TrainResult(emu, cfg, metrics, linear, data.sha256(), examples_envelope(model, data))


def examples_plan(
    model: PhysicalModel, cfg: TrainConfig, weights: int, elapsed: float
) -> sampling.SamplingPlan:
    """The training and held-out examples to simulate for an emulator of ``weights`` weights after
    ``elapsed`` seconds of the budget: ``cfg.examples``, or ``cfg.examples_per_weight`` per weight
    (times ``cfg.budget_scale()``: a larger budget buys more data), as ``sampling_plan`` cuts it."""
    count = cfg.examples or math.ceil(cfg.examples_per_weight * cfg.budget_scale() * weights)
    plan = sampling_plan(model, cfg, count, elapsed)
    if plan.reason:
        log.info("%s: %s", model.name, plan.reason)
    log.info("%s n=%d: %d weights, %d examples", model.name, cfg.substeps, weights, plan.examples)
    return plan


def training_data(
    model: PhysicalModel, cfg: TrainConfig, plan: sampling.SamplingPlan, data_cache: Path | None
) -> tuple[sampling.Sequences | None, sampling.Examples, sampling.Examples]:
    """The runs the training examples were cut from (None when they were not drawn as runs), the
    ``plan.examples`` training examples (half of them mirror images with ``cfg.mirror``) and the
    ``plan.test_examples`` held-out ones, drawn as the training runs are: the same stretch of each
    run, not only its start."""
    count = plan.examples
    mirror = mirror_map(model.mj_model, model.layout, model.spec.forces) if cfg.mirror else None
    simulated = count if mirror is None else (count + 1) // 2
    runs = own_runs(model, cfg, simulated, data_cache)
    data = (
        runs.examples(simulated, cfg.seed)
        if runs is not None
        else cached_examples(data_cache, model, cfg, simulated)
    )
    if mirror is not None:
        check_mirror(mirror, model, data, cfg.substeps)  # what the names and masses do not show
        data = with_mirror_images(mirror, data).subset(slice(0, count))
    test = cached_held_out(data_cache, model, cfg, plan.test_examples, like=simulated)
    return runs, data, test


def with_contact_features(
    model: PhysicalModel, cfg: TrainConfig, emu: StructuredEmulator, data: sampling.Examples
) -> tuple[StructuredEmulator, TrainConfig, str | None]:
    """``emu``, or with ``cfg.clearance`` or ``cfg.proximity`` the emulator built anew to probe the geoms
    that come near the floor or touch each other in ``data`` (the pairs are known only from data:
    ``contact_features`` searches them there); the config with ``clearance`` decided where it was left
    to the data (None: on when ``data`` touch the floor, ``FloorContact.touches``), and why (None when
    the user chose)."""
    reason, near = None, None
    if cfg.clearance is None:
        contact = floor_contact(model, data.states, model.dt * cfg.substeps)
        near = contact.geoms  # found once: building the emulator needs them too
        cfg = dataclasses.replace(cfg, clearance=contact.touches)
        if contact.floor:  # a model without a floor has nothing to say
            reason = (
                f"contact-aware (the floor's clearance as input): {contact.describe()}"
                if contact.touches
                else f"no clearance input: {contact.describe()}"
            )
            log.info("%s: %s", model.name, reason)
    if not (cfg.clearance or (cfg.proximity and not model.spec.branches)):
        return emu, cfg, reason
    emu = build_emulator(model, cfg, data.states, near)
    if emu.clearance is not None:
        clr = emu.clearance
        log.info(
            "%s: ground clearance of %s; distances between %s; slack of %s",
            model.name,
            ", ".join(clr.geoms) or "no geom",
            ", ".join(f"{a} and {b}" for a, b in clr.pairs) or "no pair of geoms",
            ", ".join(clr.tendons) or "no tendon",
        )
    return emu, cfg, reason


def normalized_examples(
    emu: StructuredEmulator, data: sampling.Examples, cfg: TrainConfig
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Fit ``emu``'s T^σ (and its limits' margins) to ``data`` and return its examples as the network
    sees them, split: training inputs (N, D) and targets (N, S), then the validation rows (the first
    ``cfg.val_fraction``)."""
    s, u, f, nxt = to_tensors(data)
    if emu.limits:  # predicted positions kept within a margin of each limit that the data never pass
        emu.set_limit_margins(torch.cat([s, nxt]))
    with torch.no_grad():
        x_local, y_local = local_examples(emu, s, u, f, nxt)
        emu.set_normalization(x_local, y_local, cfg.normalization)
        x = emu.normalize_inputs(x_local)
        y = (y_local - emu.y_mean) / emu.y_std
    n_val = max(1, int(len(data) * cfg.val_fraction))
    return x[n_val:], y[n_val:], x[:n_val], y[:n_val]


def rollout_phase(
    model: PhysicalModel,
    emu: StructuredEmulator,
    cfg: TrainConfig,
    count: int,
    runs: sampling.Sequences | None,
    t_budget: float,
    lr: float,
    one_step: tuple[Tensor, Tensor, Tensor, Tensor],
) -> RolloutMetrics:
    """Training over rollouts (``train_over_rollouts``) when ``cfg.rollout_steps`` asks for it, from
    ``lr`` and the one-step phase's data ``one_step`` (train x, y, validation x, y), on the
    ``rollout_sequences`` for ``count`` examples, for what the budget that started at ``t_budget``
    leaves (``rollout_seconds``); its metrics ({} without the phase)."""
    if cfg.rollout_steps <= 0:
        return {}
    seqs = rollout_sequences(model, cfg, count, runs)
    roll_cfg = dataclasses.replace(cfg, rollout_seconds=rollout_seconds(cfg, time.perf_counter() - t_budget))
    return train_over_rollouts(emu, seqs, roll_cfg, lr=lr, one_step=one_step)


def held_out_errors(
    emu: StructuredEmulator,
    linear: np.ndarray,
    test: sampling.Examples,
    fitted: tuple[Tensor, Tensor, Tensor, Tensor],
) -> tuple[HeldOutErrors, dict[str, dict[str, float]] | None]:
    """The relative errors of the trained ``emu`` and the ``linear`` baseline (D+1, S) on the held-out
    ``test`` examples, and of ``emu`` on the validation rows of ``fitted`` (train x, y, validation x,
    y); and an articulated hierarchy's errors network by network (``network_errors``; None for one
    network)."""
    x_tr, y_tr, x_val, y_val = fitted
    composed = articulated_core(emu)
    ts, tu, tf, tn = to_tensors(test)
    with torch.no_grad():
        xt = emu.network_inputs(ts, tu, tf)
        yt = emu.network_targets(ts, tn)
        errors: HeldOutErrors = {
            "one_step_rel_error": relative_error(emu.network(xt), yt),
            "linear_baseline_rel_error": relative_error(apply_linear(linear, xt), yt),
            "validation_rel_error": relative_error(emu.network(x_val), y_val),
        }
        per_network = network_errors(composed, x_tr, y_tr, xt, yt) if composed is not None else None
    return errors, per_network


def training_extras(
    choice: LoopChoice | None,
    per_network: dict[str, dict[str, float]] | None,
    sampling_reason: str | None,
    clearance_reason: str | None = None,
) -> TrainingExtras:
    """The metrics a training has only in some cases: the loop check's (with ``choice``), an articulated
    hierarchy's errors network by network, why sampling was cut short, and whether the network reads
    the floor's clearance where the data decided it."""
    extras: TrainingExtras = {}
    if choice is not None:
        extras.update(choice.metrics())
    if per_network is not None:
        extras["networks"] = per_network
    if sampling_reason:
        extras["sampling_reason"] = sampling_reason
    if clearance_reason:
        extras["clearance_reason"] = clearance_reason
    return extras


# The share of ``TrainConfig.time_budget`` that sampling may take (what set-up spent comes off it), and
# the least it gets however much set-up spent: the rest trains
SAMPLING_SHARE = 0.4
SAMPLING_FLOOR = 0.15


def sampling_plan(
    model: PhysicalModel, cfg: TrainConfig, count: int, elapsed: float
) -> sampling.SamplingPlan:
    """The examples to simulate after ``elapsed`` seconds of the budget: ``count`` and
    ``cfg.test_examples``, cut to what fits in the budget's sampling share at the model's measured step
    rate (``sampling.plan_within``) unless the user set the count, there is no budget, or the data come
    from the model's own source."""
    if cfg.examples is not None or cfg.time_budget is None or model.spec.data_source is not None:
        return sampling.SamplingPlan(count, cfg.test_examples)
    seconds = max(SAMPLING_SHARE * cfg.time_budget - elapsed, SAMPLING_FLOOR * cfg.time_budget)
    return sampling.plan_within(
        model, cfg.substeps, count, cfg.test_examples, seconds, sampler=cfg.sampler, seed=cfg.seed
    )


# Seconds kept, within ``TrainConfig.time_budget``, for what follows the phases: the held-out
# evaluation, the export and writing the artifact
AFTER_PHASES_S = 10.0


def one_step_seconds(cfg: TrainConfig, elapsed: float) -> float:
    """The one-step phase's cap after ``elapsed`` seconds (set-up and sampling): ``cfg.max_seconds`` (times
    ``cfg.budget_scale()``), cut where the budget would otherwise leave the rollout phase less than a
    third of its cap (never below a third of the cap: a very slow model overruns its budget rather
    than going untrained)."""
    if cfg.time_budget is None:
        return cfg.max_seconds
    cap = cfg.max_seconds * cfg.budget_scale()
    rollout = cfg.rollout_seconds * cfg.budget_scale() / 3 if cfg.rollout_steps > 0 else 0.0
    left = cfg.time_budget - elapsed - rollout - AFTER_PHASES_S
    if left < cap:
        log.info(
            "time budget %.0f s: the one-step phase gets %.0f s after %.0f s of set-up and sampling",
            cfg.time_budget,
            max(left, cap / 3),
            elapsed,
        )
    return max(min(cap, left), cap / 3)


def rollout_seconds(cfg: TrainConfig, elapsed: float) -> float:
    """The rollout phase's cap after ``elapsed`` seconds: what the budget leaves, between a third of
    ``cfg.rollout_seconds`` (times ``cfg.budget_scale()``) and all of it."""
    if cfg.time_budget is None:
        return cfg.rollout_seconds
    cap = cfg.rollout_seconds * cfg.budget_scale()
    left = cfg.time_budget - elapsed - AFTER_PHASES_S
    return max(min(cap, left), cap / 3)


def network_errors(
    core: ArticulatedCore, x_tr: Tensor, y_tr: Tensor, x_test: Tensor, y_test: Tensor
) -> dict[str, dict[str, float]]:
    """Each network's held-out one-step relative error over its own outputs, and the same for a linear
    map fitted on its inputs (a branch's fit reads the true trunk change; ``articulated.ridge_fit``:
    with this many inputs, plain least squares is worse than the mean on held-out data), by name."""
    cols = core.output_columns()
    pred = core(x_test)
    fit_inputs = core.network_inputs(x_tr, y_tr)
    test_inputs = core.network_inputs(x_test, y_test)
    out = {}
    for name, c in cols.items():
        w = ridge_fit(fit_inputs[name], y_tr[:, c]).numpy()
        out[name] = {
            "one_step_rel_error": relative_error(pred[:, c], y_test[:, c]),
            "linear_baseline_rel_error": relative_error(apply_linear(w, test_inputs[name]), y_test[:, c]),
            "outputs": len(c),
            "inputs": int(fit_inputs[name].shape[1]),
        }
    return out


def start_from_linear(emu: StructuredEmulator, linear: np.ndarray) -> None:
    """Set the linear path to the least-squares fit (D+1, S) and silence the MLP's last layer, so that
    training starts from the linear model and the MLP learns what it leaves."""
    assert emu.skip is not None
    w = torch.from_numpy(linear).float()
    last = emu.core[-1]
    assert isinstance(last, torch.nn.Linear)
    with torch.no_grad():
        emu.skip.weight.copy_(w[:-1].T)
        emu.skip.bias.copy_(w[-1])
        last.weight.mul_(0.01)
        last.bias.zero_()


def train_core(
    emu: StructuredEmulator,
    x: Tensor,
    y: Tensor,
    x_val: Tensor,
    y_val: Tensor,
    cfg: TrainConfig,
    choice: LoopChoice | None = None,
) -> float:
    """Mini-batch training of N^σ on normalised data, early stopping on the validation loss; returns
    the learning rate it ended with. ``choice``: the kept epoch weighs a closed loop too
    (``neuroanimator.training.loop_choice``); None: the epoch of the lowest validation loss."""
    net = _Network(emu)
    opt = _optimizer(net, cfg)
    if cfg.schedule not in ("cosine", "plateau"):
        raise ValueError(f"schedule must be 'cosine' or 'plateau', got {cfg.schedule!r}")
    plateau = torch.optim.lr_scheduler.ReduceLROnPlateau(opt, factor=0.5, patience=max(2, cfg.patience // 4))
    n_state_inputs = sum(w for name, w in emu.input_groups if name not in ("controls", "forces"))
    gen = torch.Generator().manual_seed(cfg.seed)
    best, best_state, stale = math.inf, None, 0
    done = 0.0  # the cosine schedule's progress, 0 to 1
    t0 = time.perf_counter()
    bar = tqdm(range(cfg.max_epochs), desc="training", unit="epoch", disable=not cfg.progress, leave=False)
    for epoch in bar:
        _train_epoch(net, opt, x, y, cfg, gen, n_state_inputs, epoch)
        val, worst = _validation_loss(net, x_val, y_val, epoch)
        if cfg.schedule == "cosine":
            done = _anneal(opt, cfg, epoch, time.perf_counter() - t0)
        else:
            plateau.step(val)
        if val < best * (1 - 1e-4):
            best, stale = val, 0
            best_state = {k: v.detach().clone() for k, v in net.state_dict().items()}
        else:
            stale += 1
        loop = choice.offer(epoch, val, best, net, emu) if choice is not None else None
        # the worst validation example beside the mean: a mean that rises while the rate falls can be a
        # few inputs far outside the rest on which the network extrapolates (the runner on 1.6 million)
        bar.set_postfix(
            val=f"{val:.2e}",
            best=f"{best:.2e}",
            worst=f"{worst:.1e}",
            lr=f"{opt.param_groups[0]['lr']:.1e}",
            # the time cap usually ends a run before its epochs do: what is left of it (progress reads it)
            left=f"{max(0.0, cfg.max_seconds - (time.perf_counter() - t0)):.0f}s",
            **({"loop": f"{loop:.3g}"} if loop is not None else {}),
        )
        # under the cosine schedule a stalled validation loss early on is the noise of a high learning
        # rate, not the end: stop only once it has come down halfway (the runner stopped at epoch 55 of
        # 150 at lr 2.1e-3, every network worse than the plateau schedule's)
        if stale >= cfg.patience and (cfg.schedule != "cosine" or done >= 0.5):
            log.info("early stop at epoch %d (best validation mse %.3e)", epoch, best)
            break
        if time.perf_counter() - t0 > cfg.max_seconds:
            log.info("time cap %.0f s reached at epoch %d", cfg.max_seconds, epoch)
            break
    bar.close()
    kept = choice.restore(net) if choice is not None else None
    if kept is None and best_state is not None:
        net.load_state_dict(best_state)
    return float(opt.param_groups[0]["lr"])


def _optimizer(net: torch.nn.Module, cfg: TrainConfig) -> torch.optim.Optimizer:
    """``cfg.optimizer`` over the network's parameters at ``cfg.lr``."""
    if cfg.optimizer == "adam":
        # fused: one kernel for every parameter's update, about a fifth faster a step on the CPU
        return torch.optim.Adam(net.parameters(), lr=cfg.lr, fused=True)
    if cfg.optimizer == "sgd":
        return torch.optim.SGD(net.parameters(), lr=cfg.lr, momentum=cfg.momentum)
    raise ValueError(f"optimizer must be 'adam' or 'sgd', got {cfg.optimizer!r}")


def _train_epoch(
    net: _Network,
    opt: torch.optim.Optimizer,
    x: Tensor,
    y: Tensor,
    cfg: TrainConfig,
    gen: torch.Generator,
    n_state_inputs: int,
    epoch: int,
) -> None:
    """One pass over the training inputs x (N, D) and targets y (N, S) in shuffled mini-batches, with
    ``cfg.input_noise`` on the first ``n_state_inputs`` input columns (the state's)."""
    net.train()
    perm = torch.randperm(x.shape[0], generator=gen)
    for i in range(0, x.shape[0], cfg.batch_size):
        idx = perm[i : i + cfg.batch_size]
        xb, yb = x[idx], y[idx]
        if cfg.input_noise > 0:
            # noise on the state inputs only: the net learns to pull a drifted state back
            noise = torch.randn(xb.shape[0], n_state_inputs, generator=gen) * cfg.input_noise
            xb = torch.cat([xb[:, :n_state_inputs] + noise, xb[:, n_state_inputs:]], dim=1)
        loss = net.loss(xb, yb)
        if not torch.isfinite(loss):
            raise TrainingDiverged(
                f"training diverged at epoch {epoch} (loss {float(loss.detach())}); lower the learning rate ({cfg.lr})"
            )
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()


def _validation_loss(net: _Network, x_val: Tensor, y_val: Tensor, epoch: int) -> tuple[float, float]:
    """The mean squared error on the validation rows x_val (M, D), y_val (M, S): its mean over the rows
    and its worst row."""
    net.eval()
    with torch.no_grad():
        per_example = torch.mean((net(x_val) - y_val) ** 2, dim=1)
        val, worst = float(per_example.mean()), float(per_example.max())
    if not math.isfinite(val):
        raise TrainingDiverged(
            f"training diverged: the validation loss became {val} at epoch {epoch}; lower the learning rate"
        )
    return val, worst


def _anneal(opt: torch.optim.Optimizer, cfg: TrainConfig, epoch: int, elapsed: float) -> float:
    """Set the cosine schedule's learning rate after ``epoch`` and ``elapsed`` seconds; returns its
    progress, 0 to 1. It anneals over the budget, whichever of epochs or seconds runs out first: a
    time-capped run still ends at a small learning rate, where the last digits of the error are won."""
    done = max((epoch + 1) / cfg.max_epochs, elapsed / cfg.max_seconds)
    for group in opt.param_groups:
        group["lr"] = cfg.lr * (0.01 + 0.99 * 0.5 * (1 + math.cos(math.pi * min(1.0, done))))
    return done


def source_defaults(model: PhysicalModel, cfg: TrainConfig, given: set[str]) -> TrainConfig:
    """``cfg`` with the training settings of the model's data source (its module's ``TRAIN_DEFAULTS``)
    for the fields not in ``given`` (those the user set)."""
    if model.spec.data_source is None:
        return cfg
    defaults = getattr(importlib.import_module(model.spec.data_source), "TRAIN_DEFAULTS", {})
    updates = {k: v for k, v in defaults.items() if k not in given}
    return dataclasses.replace(cfg, **updates) if updates else cfg


def own_runs(
    model: PhysicalModel, cfg: TrainConfig, count: int, data_cache: Path | None = None
) -> sampling.Sequences | None:
    """The runs of the ``"runs"`` sampler that hold ``count`` examples (kept in or read from
    ``data_cache``); None for a model with its own data source or for the ``"spaced"`` sampler."""
    if model.spec.data_source is not None or cfg.sampler != "runs":
        return None
    return cached(
        data_cache, model, cfg.substeps, count, cfg.seed, cfg.sampler,
        lambda: sampling.generate_runs(model, cfg.substeps, count, cfg.seed, progress=cfg.progress),
        sampling.Sequences,
    )  # fmt: skip


def rollout_sequences(
    model: PhysicalModel, cfg: TrainConfig, count: int, runs: sampling.Sequences | None = None
) -> sampling.Sequences:
    """The rollout phase's sequences: ``cfg.rollout_sequences`` (default one per 16 of the ``count``
    one-step examples, at least 64) runs of ``cfg.rollout_steps`` super-steps: windows of the one-step
    examples' ``runs`` where they hold that many (no more simulation), else from the model's own data
    source where it has one, else newly simulated."""
    n = cfg.rollout_sequences or max(64, count // 16)
    if runs is not None and (runs.states.shape[1] - 1) // cfg.rollout_steps * len(runs) >= n:
        return runs.windows(cfg.rollout_steps, n, cfg.seed + 7)
    source = model.spec.data_source
    if source is not None:
        seqs: sampling.Sequences = importlib.import_module(source).sequences(
            model, cfg.substeps, n, cfg.rollout_steps, cfg.seed + 7, progress=cfg.progress
        )
        return seqs
    return sampling.generate_sequences(
        model, cfg.substeps, n, cfg.rollout_steps, cfg.seed + 7, progress=cfg.progress
    )


class KeepBest:
    """Early stopping's bookkeeping: the best validation value so far, the module's state that gave it
    (kept only for a gain of more than 0.1%), and the epochs since."""

    def __init__(self, module: torch.nn.Module, value: float) -> None:
        self.module, self.best, self.stale = module, value, 0
        self._state = {k: v.detach().clone() for k, v in module.state_dict().items()}

    def offer(self, value: float) -> None:
        if value < self.best * (1 - 1e-3):
            self.best, self.stale = value, 0
            self._state = {k: v.detach().clone() for k, v in self.module.state_dict().items()}
        else:
            self.stale += 1

    def restore(self) -> None:
        self.module.load_state_dict(self._state)


def _sequence_tensors(seq: sampling.Sequences) -> tuple[Tensor, Tensor | None, Tensor | None]:
    s = torch.from_numpy(seq.states).float()
    u = torch.from_numpy(seq.controls).float() if seq.controls.shape[2] else None
    f = torch.from_numpy(seq.forces).float() if seq.forces.shape[2] else None
    return s, u, f


def rollout_loss(
    emu: StructuredEmulator, s: Tensor, u: Tensor | None, f: Tensor | None, scale: Tensor
) -> Tensor:
    """Mean squared error of a K-step emulated rollout against the physics, each variable divided by
    the spread of its change over one super-step: s (B, K+1, S), u (B, K, U), f (B, K, F)."""
    k_steps = s.shape[1] - 1
    state = s[:, 0]
    total = torch.zeros(())
    for k in range(k_steps):
        state = emu(state, None if u is None else u[:, k], None if f is None else f[:, k])
        total = total + torch.mean(((state - s[:, k + 1]) / scale) ** 2)
    return total / k_steps


def train_over_rollouts(
    emu: StructuredEmulator,
    seq: sampling.Sequences,
    cfg: TrainConfig,
    lr: float | None = None,
    one_step: tuple[Tensor, Tensor, Tensor, Tensor] | None = None,
    should_stop: Callable[[], bool] | None = None,
) -> RolloutMetrics:
    """Fine-tune N^σ on the error of emulated rollouts (``rollout_loss``), early stopping on held-back
    sequences, at ``lr`` (default: a tenth of the config's; the one-step phase's last rate is a good
    start); returns the validation rollout loss before and after.

    With ``one_step`` (the one-step phase's normalised inputs and targets: train x, y, validation x,
    y), the loss is the rollout loss and the one-step loss, each relative to its value when the phase
    starts, and so is the validation that picks the state kept: alone, the rollout loss trades the
    one-step accuracy away where the two pull apart (a ball on a floor: rollout loss 0.43 → 0.09 while
    the one-step error went from 0.009 on validation before the phase to 0.057 held out after it),
    and the held-out one-step error is the emulator's bar. ``should_stop`` (a job cancelled) ends it
    between two batches, as its time running out does; the best state so far is kept."""
    s, u, f = _sequence_tensors(seq)
    scale = (s[:, 1:] - s[:, :-1]).reshape(-1, s.shape[2]).std(dim=0)
    scale = torch.where(scale > 1e-8, scale, torch.ones_like(scale))
    n_val = max(1, len(seq) // 10)
    val, tr = slice(0, n_val), slice(n_val, None)
    train_seqs = (s[tr], _rows(u, tr), _rows(f, tr))
    net = _Network(emu)
    opt = torch.optim.Adam(net.parameters(), lr=cfg.lr * 0.1 if lr is None else lr)
    gen = torch.Generator().manual_seed(cfg.seed + 11)
    check = _RolloutValidation(emu, net, (s[val], _rows(u, val), _rows(f, val)), scale, one_step)
    keep = KeepBest(net, check.relative())
    t0, epochs = time.perf_counter(), 0
    batch = max(32, cfg.batch_size // 4)

    def done() -> bool:
        return time.perf_counter() - t0 >= cfg.rollout_seconds or (should_stop is not None and should_stop())

    while not done() and keep.stale < 10 and epochs < cfg.max_epochs:
        _rollout_epoch(check, opt, train_seqs, batch, gen, done)
        epochs += 1
        keep.offer(check.relative())
    keep.restore()
    after_rollout, after_step = check.losses()
    log.info(
        "rollout phase: %d epochs, validation rollout loss %.3g -> %.3g%s",
        epochs,
        check.roll0,
        after_rollout,
        f", one-step mse {check.step0:.3g} -> {after_step:.3g}" if one_step is not None else "",
    )
    return {
        "rollout_loss_before": check.roll0,
        "rollout_loss_after": after_rollout,
        "rollout_epochs": epochs,
    }


def fine_tune_on_runs(
    emu: StructuredEmulator,
    states: np.ndarray,
    controls: np.ndarray,
    cfg: TrainConfig,
    seconds: float,
    seed: int,
    window: int = 8,
    keep: sampling.Sequences | None = None,
    should_stop: Callable[[], bool] | None = None,
) -> RolloutMetrics:
    """Fine-tune the emulator on runs a controller made on MuJoCo: states (N, K+1, S) and controls
    (N, K, U) at the emulator's super-step, cut into windows of ``window`` super-steps and learned
    with the rollout loss for ``seconds`` (runs that diverged are left out), so the model is right
    where the controller goes; with ``keep`` (sequences of ``window`` super-steps of the motion it
    was trained on), those too, so that it stays right there (learned alone, the controller's runs
    pull it away from every other state, the next controller's included). ``should_stop`` (a job
    cancelled) ends it early. The emulator is left in evaluation mode."""
    finite = np.all(np.isfinite(states), axis=(1, 2))
    runs = sampling.Sequences(
        states[finite], controls[finite], np.zeros((int(finite.sum()), controls.shape[1], 0))
    )
    windows = runs.windows(min(window, runs.states.shape[1] - 1), None, seed)
    if keep is not None and keep.states.shape[1] == windows.states.shape[1]:
        mixed = np.random.default_rng(seed).permutation(len(windows) + len(keep))
        windows = sampling.Sequences(
            np.concatenate([windows.states, keep.states])[mixed],
            np.concatenate([windows.controls, keep.controls])[mixed],
            np.concatenate([windows.forces, keep.forces[:, :, :0]])[mixed],
        )
    emu.requires_grad_(True)  # a frozen step may have frozen it
    emu.train()
    try:
        return train_over_rollouts(
            emu,
            windows,
            dataclasses.replace(cfg, rollout_seconds=seconds, progress=False),
            should_stop=should_stop,
        )
    finally:
        emu.eval()


def _rows(t: Tensor | None, sl: slice | Tensor) -> Tensor | None:
    return None if t is None else t[sl]


class _RolloutValidation:
    """The rollout phase's losses and their reference values: the rollout loss of the held-back
    sequences ``val`` (s (M, K+1, S), u, f), each variable divided by ``scale`` (S,), and with
    ``one_step`` (train x, y, validation x, y) the one-step loss on its validation rows; ``roll0`` and
    ``step0`` are their values when the phase starts (at least 1e-12)."""

    def __init__(
        self,
        emu: StructuredEmulator,
        net: _Network,
        val: tuple[Tensor, Tensor | None, Tensor | None],
        scale: Tensor,
        one_step: tuple[Tensor, Tensor, Tensor, Tensor] | None,
    ) -> None:
        self.emu, self.net, self.val, self.scale, self.one_step = emu, net, val, scale, one_step
        roll0, step0 = self.losses()
        self.roll0, self.step0 = max(roll0, 1e-12), max(step0, 1e-12)

    def one_step_mse(self, x: Tensor, y: Tensor) -> Tensor:
        return torch.mean((self.net(x) - y) ** 2)

    def losses(self) -> tuple[float, float]:
        """The validation rollout loss and one-step loss (0 without ``one_step``), the emulator in
        evaluation mode."""
        self.emu.eval()
        with torch.no_grad():
            roll = float(rollout_loss(self.emu, *self.val, self.scale))
            step = (
                float(self.one_step_mse(self.one_step[2], self.one_step[3]))
                if self.one_step is not None
                else 0.0
            )
        return roll, step

    def relative(self) -> float:
        """The validation that picks the state kept: each loss relative to its starting value, summed."""
        roll, step = self.losses()
        return roll / self.roll0 + (step / self.step0 if self.one_step is not None else 0.0)


def _rollout_epoch(
    check: _RolloutValidation,
    opt: torch.optim.Optimizer,
    seqs: tuple[Tensor, Tensor | None, Tensor | None],
    batch: int,
    gen: torch.Generator,
    done: Callable[[], bool] | None = None,
) -> None:
    """One pass over the training sequences s (N, K+1, S), u, f in shuffled batches of ``batch`` (cut
    short once ``done``): the rollout loss relative to its starting value, plus with ``check.one_step``
    the one-step loss of ``4 · batch`` random training rows relative to its own."""
    emu, one_step = check.emu, check.one_step
    s, u, f = seqs
    emu.train()
    perm = torch.randperm(s.shape[0], generator=gen)
    for i in range(0, perm.numel(), batch):
        if i and done is not None and done():
            break
        idx = perm[i : i + batch]
        loss = rollout_loss(emu, s[idx], _rows(u, idx), _rows(f, idx), check.scale) / check.roll0
        if one_step is not None:
            rows = torch.randint(0, one_step[0].shape[0], (4 * batch,), generator=gen)
            loss = loss + check.one_step_mse(one_step[0][rows], one_step[1][rows]) / check.step0
        if not torch.isfinite(loss):
            raise TrainingDiverged(f"training over rollouts diverged (loss {float(loss.detach())})")
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
