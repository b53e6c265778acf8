"""The ``neuro`` command: train, evaluate and benchmark emulators; list models.

Every command that reads artifacts reads the data directory (``registry.default_data_dir``: where
``train`` writes, ``$NEUROANIMATOR_DATA_DIR`` or ``~/.local/share/neuroanimator``) over the committed
defaults (``artifacts/``), or only the folder ``--artifacts DIR`` names; ``eval`` and ``bench`` print a
table, and with ``--json`` one JSON object as the last line of output.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from pydantic import ValidationError

from neuroanimator import catalog
from neuroanimator.artifacts import registry
from neuroanimator.core.operating_spec import OperatingSpec
from neuroanimator.core.results import NetworkSize, VersionEval, split_bench, summarize_eval
from neuroanimator.core.train_config import TrainConfig
from neuroanimator.evaluation import physical_errors
from neuroanimator.sim import sampling
from neuroanimator.sim.mjcf import load_mjcf
from neuroanimator.sim.model import ModelError, PhysicalModel

if TYPE_CHECKING:  # torch loads only for the commands that need it (see ``_fit``)
    from neuroanimator.training.hierarchy import HierarchyResult
    from neuroanimator.training.metrics import ChoiceNotes
    from neuroanimator.training.train import TrainResult

log = logging.getLogger("neuroanimator")


_ARTIFACTS_HELP = "read only this artifact registry (default: the data directory over the committed defaults)"


def _registries(folder: str | None) -> registry.Root:
    """The one registry ``--artifacts`` names, else the data directory over the committed defaults."""
    return Path(folder) if folder else registry.Roots.default()


def _table(rows: list[dict[str, Any]], columns: list[tuple[str, str, str]]) -> str:
    """Render rows as an aligned text table; columns are (key, header, format). A row is free-form: any
    values ``format`` takes, keyed by column (and what ``--json`` prints beside them)."""
    cells = [[h for _, h, _ in columns]]
    for r in rows:
        cells.append([("-" if r.get(k) is None else format(r[k], f)) for k, _, f in columns])
    widths = [max(len(c[i]) for c in cells) for i in range(len(columns))]
    lines = ["  ".join(c[i].rjust(widths[i]) for i in range(len(columns))) for c in cells]
    lines.insert(1, "  ".join("-" * w for w in widths))
    return "\n".join(lines)


def _out(text: str) -> None:
    sys.stdout.write(text + "\n")
    sys.stdout.flush()


# ---------------------------------------------------------------------------- train
# ``TrainConfig`` fields and the ``neuro train`` options that set them
CONFIG_OPTIONS = {
    "hidden": "hidden",
    "branch_hidden": "branch_hidden",
    "members": "members",
    "loop_tolerance": "loop_tolerance",
    "activation": "activation",
    "examples": "examples",
    "sampler": "sampler",
    "schedule": "schedule",
    "batch_size": "batch_size",
    "lr": "lr",
    "max_seconds": "max_seconds",
    "time_budget": "time_budget",
    "max_epochs": "epochs",
    "clearance": "clearance",
    "limits": "limits",
    "proximity": "proximity",
    "mirror": "mirror",
    "rollout_steps": "rollout_steps",
    "rollout_seconds": "rollout_seconds",
    "regularizer_steps": "regularizer_steps",
    "state_noise": "state_noise",
}


def given_fields(args: argparse.Namespace) -> set[str]:
    """The ``TrainConfig`` fields the command line set: a model's own training settings
    (``training.source_defaults``) never override them."""
    given = {name for name, option in CONFIG_OPTIONS.items() if getattr(args, option, None) is not None}
    if args.max_seconds is not None:
        given.add("time_budget")  # --max-seconds sets the cap asked for, with no budget to cut it
    return given


def cmd_train(args: argparse.Namespace) -> int:
    started = time.perf_counter()  # the time budget is over the whole command, probes included
    model, auto, fixed = _train_model(args)
    cfg = _train_config(args, model, fixed)
    trained = _fit(args, model, cfg, auto, started)
    if trained is None:
        return 2
    result, cfg = trained
    return _accept_and_save(args, model, cfg, result)


def _train_model(args: argparse.Namespace) -> tuple[PhysicalModel, bool, int | None]:
    """The model to train (a catalog model, or one's own ``--mjcf``), whether short probes choose its
    super-step (``auto``), and the super-step the command line fixed (``None``: none)."""
    if (args.model is None) == (args.mjcf is None):
        raise ModelError("give either a catalog model name or --mjcf PATH (not both)")
    if args.mjcf is None and (args.entry or args.name or args.spec or args.keyframe):
        raise ModelError("--entry, --name, --spec and --keyframe go with --mjcf")
    auto = args.substeps == "auto" or (args.substeps is None and args.mjcf is not None)
    fixed = None if auto or args.substeps is None else int(args.substeps)
    model: PhysicalModel = (
        load_mjcf(
            args.mjcf,
            substeps=fixed,
            entry=args.entry,
            name=args.name,
            operating_spec=read_operating_spec(args.spec) if args.spec else None,
            keyframe=args.keyframe,
        )
        if args.mjcf
        else catalog.get(args.model)
    )
    problem = registry.name_problem(model.name)  # said before the training, not after it
    if problem is not None:
        raise ModelError(f"{problem} (--name)")
    return model, auto, fixed


def read_operating_spec(path: str) -> OperatingSpec:
    """The operating spec in the JSON file ``path``; ``ModelError`` naming the file and the field."""
    try:
        text = Path(path).read_text()
    except OSError as exc:
        raise ModelError(f"--spec {path}: cannot read it ({exc.strerror})") from exc
    try:
        return OperatingSpec.model_validate_json(text)
    except ValidationError as exc:
        problems = "; ".join(
            f"{'.'.join(str(x) for x in e['loc']) or 'the file'}: {e['msg']}" for e in exc.errors()
        )
        raise ModelError(f"--spec {path}: not an operating spec: {problems}") from exc


def _train_config(args: argparse.Namespace, model: PhysicalModel, fixed: int | None) -> TrainConfig:
    """The training settings: the preset's, with what the command line sets (checked in option order)."""
    cfg = TrainConfig(
        substeps=fixed if fixed is not None else model.spec.substeps,
        preset=args.preset,
        optimizer=args.optimizer,
        seed=args.seed,
        progress=not args.quiet,
        thesis_hidden=model.spec.thesis_hidden or max(20, 2 * model.state_size),
    )
    _set_network_options(cfg, args)
    _set_optimisation_options(cfg, args)
    cfg.frame, cfg.skip = args.frame, not args.no_skip
    _set_input_options(cfg, args)
    _set_rollout_and_noise_options(cfg, args, model)
    return cfg


def _set_network_options(cfg: TrainConfig, args: argparse.Namespace) -> None:
    """The network: widths, ensemble, kept epoch and hidden units."""
    if args.hidden is not None:
        cfg.hidden = args.hidden
    if args.branch_hidden is not None:
        cfg.branch_hidden = args.branch_hidden
    if args.members is not None:
        cfg.members = args.members
    if args.loop_tolerance is not None:
        cfg.loop_tolerance = None if args.loop_tolerance == "off" else args.loop_tolerance
    if args.activation is not None:
        cfg.activation = args.activation


def _set_optimisation_options(cfg: TrainConfig, args: argparse.Namespace) -> None:
    """The data and the one-step optimisation: examples, sampler, learning rate and time limits."""
    if args.examples is not None:
        cfg.examples = args.examples
    if args.sampler is not None:
        cfg.sampler = args.sampler
    if args.schedule is not None:
        cfg.schedule = args.schedule
    if args.batch_size is not None:
        cfg.batch_size = args.batch_size
    if args.lr is not None:
        cfg.lr = args.lr
    if args.max_seconds is not None:
        cfg.max_seconds = args.max_seconds
        cfg.time_budget = None  # the cap asked for, not one cut to a budget
    if args.time_budget is not None:
        if args.time_budget < 0:
            raise ModelError(f"--time-budget must be 0 (none) or more seconds, got {args.time_budget:g}")
        cfg.time_budget = args.time_budget or None
    if args.epochs is not None:
        cfg.max_epochs = args.epochs


def _set_input_options(cfg: TrainConfig, args: argparse.Namespace) -> None:
    """What the network reads besides the state (on/off options): clearance, limits, proximity; and
    mirrored examples."""
    if args.clearance is not None:
        cfg.clearance = args.clearance == "on"
    if args.limits is not None:
        cfg.limits = args.limits == "on"
    if args.proximity is not None:
        cfg.proximity = args.proximity == "on"
    if args.mirror is not None:
        cfg.mirror = args.mirror == "on"


def _set_rollout_and_noise_options(cfg: TrainConfig, args: argparse.Namespace, model: PhysicalModel) -> None:
    """The rollout phase, the regulariser's steps and a hierarchy's state noise, each checked."""
    if args.rollout_steps is not None:
        if args.rollout_steps < 0:
            raise ModelError(f"--rollout-steps must be 0 or more, got {args.rollout_steps}")
        cfg.rollout_steps = args.rollout_steps
    if args.rollout_seconds is not None:
        if not args.rollout_seconds > 0:
            raise ModelError(f"--rollout-seconds must be above 0, got {args.rollout_seconds}")
        cfg.rollout_seconds = args.rollout_seconds
    if args.regularizer_steps is not None:
        if args.regularizer_steps < 0:
            raise ModelError(f"--regularizer-steps must be 0 or more, got {args.regularizer_steps}")
        cfg.regularizer_steps = args.regularizer_steps
    if args.state_noise is not None:
        if not 0 <= args.state_noise <= 1:
            raise ModelError(f"--state-noise must be between 0 and 1, got {args.state_noise:g}")
        if args.state_noise and not model.spec.parts:
            raise ModelError(
                f"--state-noise trains a hierarchy's networks; {model.name} is emulated by one network"
            )
        cfg.state_noise = args.state_noise


def _fit(
    args: argparse.Namespace, model: PhysicalModel, cfg: TrainConfig, auto: bool, started: float
) -> tuple[TrainResult | HierarchyResult, TrainConfig] | None:
    """Choose the network and super-step, then train; the result (its metrics noting how the network
    and super-step were chosen) and the settings it was trained with, or ``None`` (logged) when
    training diverged."""
    # torch loads only for the commands that need it
    from neuroanimator.training.train import TrainingDiverged

    try:
        cfg, notes = _network_and_super_step(args, model, cfg, auto)
        result, cfg = _train_emulator(args, model, cfg, started)
    except TrainingDiverged as exc:
        log.error("%s", exc)
        return None
    result.metrics.update(notes)
    return result, cfg


def _network_and_super_step(
    args: argparse.Namespace, model: PhysicalModel, cfg: TrainConfig, auto: bool
) -> tuple[TrainConfig, ChoiceNotes]:
    """The network and (``auto``) the super-step, from short probes of how often contacts and limits
    engage; a hierarchy over parts, or a model whose data come from its own source (a controller), keeps
    the network and super-step its spec gives. With ``auto`` the model's spec takes the super-step
    chosen. Returns the settings and what to note in the result's metrics."""
    from neuroanimator.training import super_step

    notes: ChoiceNotes = {}
    motion = None
    if args.mjcf is not None:  # a model of one's own: runs cut where they spin a body up (first: the
        # contacts and limits are those of the runs kept)
        motion = super_step.spin_up(model, cfg, cfg.substeps if not auto else super_step.CANDIDATES[-1])
        if model.spec.operating is not None:
            notes["operating_reason"] = model.spec.operating.describe()
    spec_given = bool(model.spec.parts or model.spec.data_source)
    activity = None if spec_given else super_step.constraint_activity(model, seed=cfg.seed)
    network_reason = None
    if activity is not None:
        given = {
            "hidden_given": args.hidden is not None,
            "activation_given": args.activation is not None,
            "schedule_given": args.schedule is not None,
        }
        if args.mjcf is not None:  # a model of one's own: the deeper network the suite measured
            batch_given = args.batch_size is not None
            cfg, network_reason = super_step.user_defaults(cfg, activity, **given, batch_given=batch_given)
        else:
            cfg, network_reason = super_step.constrained_defaults(cfg, activity, **given)
        if network_reason:
            log.info("%s: network %s", model.name, network_reason)
    if network_reason:
        notes["network_reason"] = network_reason
    if activity is not None:
        notes["contact_fraction"] = activity.contact
        notes["limit_fraction"] = activity.limit
    if auto:
        choice = super_step.choose_substeps(model, cfg, activity=activity, motion=motion)
        log.info("%s: super-step %s", model.name, choice.reason)
        cfg.substeps = choice.substeps
        model.spec = model.spec.model_copy(update={"substeps": choice.substeps})
        notes["substeps_reason"] = choice.reason
    return cfg, notes


def _train_emulator(
    args: argparse.Namespace, model: PhysicalModel, cfg: TrainConfig, started: float
) -> tuple[TrainResult | HierarchyResult, TrainConfig]:
    """Train the emulator, one network or a hierarchy of them (thesis 4.4), with the settings a model
    trained on its controller's motion, or a hierarchy, brings where the command line left them; the
    result and the settings it was trained with."""
    from neuroanimator.training import data_cache
    from neuroanimator.training.hierarchy import small_defaults, train_hierarchy
    from neuroanimator.training.train import source_defaults, train

    if model.spec.data_source:  # a model trained on its controller's motion: its own settings
        cfg = source_defaults(model, cfg, given_fields(args))
    cache = data_cache.directory(args.data_cache)
    if model.spec.parts:  # a hierarchy of networks (thesis 4.4)
        cfg = small_defaults(
            cfg,
            hidden_given=args.hidden is not None,
            examples_given=args.examples is not None,
            rollout_given=args.rollout_steps is not None,
        )
        return train_hierarchy(model, cfg, data_cache=cache), cfg
    return train(model, cfg, spent=time.perf_counter() - started, data_cache=cache), cfg


def _accept_and_save(
    args: argparse.Namespace, model: PhysicalModel, cfg: TrainConfig, result: TrainResult | HierarchyResult
) -> int:
    """Refuse an emulator that misses the acceptance bar (unless ``--force``), else write it to the
    artifact registry and report it (with ``--json``, as one JSON object)."""
    from neuroanimator.artifacts import store as artifacts
    from neuroanimator.training import super_step

    m = result.metrics
    summary: dict[str, Any] = {"model": model.name, "substeps": cfg.substeps, "state_size": model.state_size}
    if model.spec.operating is not None:  # where it was trained to operate, and why (a model of one's own)
        summary["operating"] = model.spec.operating.model_dump(mode="json")
    if not args.force:
        try:
            super_step.check_useful(
                model.name,
                cfg.substeps,
                m["one_step_rel_error"],
                m["linear_baseline_rel_error"],
                m.get("sampling_reason"),
            )
        except super_step.ModelOutOfReach as exc:
            if args.json:  # what was measured, so that a refusal can be looked into
                _out(json.dumps({**summary, "accepted": False, "reason": str(exc), **m}))
            raise
    path = artifacts.save(Path(args.out) if args.out else registry.default_data_dir(), model, result)
    _out(
        f"{model.name} n={cfg.substeps}: one-step relative error {m['one_step_rel_error']:.3g} "
        f"(linear baseline {m['linear_baseline_rel_error']:.4f}), {m['weights']} weights, "
        f"{m['examples']} examples, {m['total_seconds']:.0f} s\nwrote {path}"
    )
    if args.json:
        _out(json.dumps({**summary, "accepted": True, "artifact": str(path), **m}))
    return 0


# ---------------------------------------------------------------------------- eval
def cmd_eval(args: argparse.Namespace) -> int:
    from neuroanimator.evaluation import evaluate as evaluation

    root = _registries(args.artifacts)
    latest = registry.read_manifest(registry.resolve(root, args.model))
    ns = [args.substeps] if args.substeps else registry.available_substeps(root, args.model)
    rows: list[VersionEval] = []
    for n in ns:
        path = registry.resolve(root, args.model, substeps=n)
        manifest = registry.read_manifest(path)
        model = registry.load_physical_model(path, manifest)
        errs = evaluation.one_step_errors(path, model, manifest)
        curve, physical = evaluation.rollout_errors(path, model, n, trials=args.trials, steps=args.steps)
        nets = manifest.emulator.networks  # a hierarchy: its global network's size, all its weights
        net = nets[0]
        rows.append(
            VersionEval(
                model=args.model,
                version=manifest.version,
                substeps=n,
                **errs,
                baseline_ratio=errs["linear_baseline_rel_error"] / max(errs["one_step_rel_error"], 1e-12),
                rollout_error_curve=curve,
                rollout_error_at_20s=curve.at(20.0),
                rollout_error_final=curve.error[-1],
                architecture=NetworkSize(
                    hidden=net.hidden, activation=net.activation, weights=sum(n.weights for n in nets)
                ),
                train_seconds=manifest.metrics.total_seconds,
                physical_errors=physical,
            )
        )
    plot = Path(args.plot) if args.plot else root / args.model / registry.PLOT_FILE
    evaluation.plot_curves(
        {r.substeps: r.rollout_error_curve for r in rows},
        f"{args.model}: rollout error vs MuJoCo ({args.trials} trials)",
        plot,
    )
    _out(
        _table(
            [r.model_dump() for r in rows],
            [
                ("substeps", "n", "d"),
                ("one_step_rel_error", "one-step rel err", ".5f"),
                ("linear_baseline_rel_error", "linear baseline", ".4f"),
                ("baseline_ratio", "ratio", ".0f"),
                ("rollout_error_at_20s", "rollout err @20s", ".4f"),
                ("rollout_error_final", f"@{args.steps * latest.timestep:.0f}s", ".4f"),
            ],
        )
    )
    for r in rows:  # a normalised error can hide metres of drift: the same rollouts in physical units
        _out(f"n={r.substeps}, rollout errors vs MuJoCo over {args.trials} trials:")
        for line in physical_errors.format_table(r.physical_errors):
            _out(f"  {line}")
    summary = summarize_eval(rows, latest.spec.thesis_hidden, args.substeps, str(plot))
    if summary.n100_vs_n25_at_20s is not None:
        _out(
            f"N^100 / N^25 rollout error: {summary.n100_vs_n25_at_20s:.2f} at 20 s, "
            f"at most {summary.n100_vs_n25_max:.2f} over matching times from 5 s on"
        )
    _out(f"plot: {plot}")
    if args.save:
        for r in rows:
            _out(f"saved {registry.write_eval(root, r)}")
    if args.json:
        _out(summary.model_dump_json())
    return 0


# ---------------------------------------------------------------------------- bench
def cmd_bench(args: argparse.Namespace) -> int:
    from neuroanimator.evaluation import speed

    batches = tuple(int(b) for b in args.batches.split(",")) if args.batches else speed.BATCHES
    root = _registries(args.artifacts)
    res = speed.run(root, args.model, batches, repeats=args.repeats)
    _out(f"{args.model}: single client, {speed.SINGLE_STEPS} physical steps (thesis Table 6.2)")
    _out(
        _table(
            [r.model_dump() for r in res.single],
            [
                ("substeps", "n", "d"),
                ("physics_s", "MuJoCo s", ".4f"),
                ("emulator_s", "emulator s", ".4f"),
                ("ratio", "speed-up", ".1f"),
            ],
        )
    )
    _out(
        f"\n{args.model}: batched, {speed.BATCH_SECONDS:.0f} s simulated per client, n={res.batched_substeps}"
    )
    _out(
        _table(
            [r.model_dump() for r in res.batched],
            [
                ("batch", "B", "d"),
                ("physics_steps_per_s", "mujoco.rollout steps/s", ".3g"),
                ("emulator_steps_per_s", "emulator steps/s", ".3g"),
                ("ratio", "speed-up", ".0f"),
            ],
        )
    )
    if args.save:
        for record in split_bench(res):
            _out(f"saved {registry.write_bench(root, record)}")
    if args.json:
        _out(res.model_dump_json())
    return 0


# ---------------------------------------------------------------------------- models
def cmd_models(args: argparse.Namespace) -> int:
    if args.catalog:  # for scripts (the Makefile, the stack): the built-in names, one per line
        _out("\n".join(catalog.CATALOG))
        return 0
    root = _registries(args.artifacts)
    names = list(catalog.CATALOG) + [m for m in registry.list_models(root) if m not in catalog.CATALOG]
    rows = []
    for name in names:
        trained = ",".join(map(str, registry.available_substeps(root, name))) or None
        # a free-form row of the table (and of --json)
        row: dict[str, Any] = {"model": name, "trained": trained, "versions": None, "size": None}
        if trained is not None:
            versions = registry.versions(root, name)
            folders = {v: registry.version_folder(root, name, v) for v in versions}
            sizes = {v: registry.version_size(f) for v, f in folders.items() if f is not None}
            latest = registry.latest_version(root, name)
            row |= {
                "versions": len(versions),
                "latest_bytes": sizes.get(latest),
                "size_bytes": registry.model_size(root, name),
                "version_bytes": sizes,
                "size": f"{_bytes(sizes.get(latest, 0))} ({_bytes(registry.model_size(root, name))} stored)",
            }
        rows.append(row)
    columns = [("model", "model", "s"), ("trained", "trained n", "s"), ("versions", "versions", "d")]
    _out(_table(rows, [*columns, ("size", "size: latest (all stored)", "s")]))
    if args.json:
        _out(json.dumps(rows))
    return 0


def _bytes(n: int) -> str:
    return f"{n / 1e6:.1f} MB" if n >= 1_000_000 else f"{n / 1e3:.1f} kB"


# ---------------------------------------------------------------------------- policy
def cmd_policy(args: argparse.Namespace) -> int:
    from neuroanimator.control.policy import PolicySettings
    from neuroanimator.control.policy_job import policy_task, run_policy_job
    from neuroanimator.control.reward_policy import RewardResult, RewardSettings
    from neuroanimator.control.suite_tasks import SuiteTask
    from neuroanimator.goals.policy_task import PolicyTask

    task: PolicyTask | SuiteTask
    if args.task.endswith(".json"):  # a reward task of the user's own (RewardTaskSpec)
        from neuroanimator.control.reward_terms import reward_task_file

        try:
            task = reward_task_file(Path(args.task), _registries(args.artifacts))
        except (OSError, ValueError) as exc:
            log.error("%s", exc)
            return 2
    else:
        task = policy_task(args.task)
    seconds = args.seconds or task.train_seconds
    settings: PolicySettings | RewardSettings
    if isinstance(task, SuiteTask):
        settings = RewardSettings(
            seconds=seconds, refine=not args.no_refine, seed=args.seed, seeds=args.seeds
        )
    elif args.seeds not in (None, 1):
        log.error(
            "--seeds: a goal-reaching task trains from one seed; several side by side are for a reward task"
        )
        return 2
    else:
        settings = PolicySettings(seconds=seconds, refine=not args.no_refine, seed=args.seed)
    done = run_policy_job(task, _registries(args.artifacts), settings)
    r = done.result
    row: dict[str, object] = {"task": task.name}
    if isinstance(r, RewardResult):
        row |= {"return_physics": round(r.return_physics, 1), "return_emulator": round(r.return_emulator, 1)}
        if len(r.seed_returns) > 1:
            row |= {"seed": r.seed, "seed_returns": [round(x, 1) for x in r.seed_returns]}
        judged = [
            ("return_physics", "return (MuJoCo)", ".1f"),
            ("return_emulator", "return (emulator)", ".1f"),
        ]
    else:
        row |= {"success_physics": r.success_physics, "success_emulator": r.success_emulator}
        judged = [("success_physics", "success (MuJoCo)", ".2f"),
                  ("success_emulator", "success (emulator)", ".2f")]  # fmt: skip
    row |= {
        "evaluate_runs": r.evaluate_runs,
        "mujoco_steps": r.mujoco_steps,
        "iterations": r.iterations,
        "wall_s": round(r.wall_s, 1),
        "policy": str(done.folder),
    }
    columns = [
        ("task", "task", "s"),
        *judged,
        ("mujoco_steps", "MuJoCo steps", "d"),
        ("wall_s", "wall s", ".0f"),
    ]
    _out(_table([row], columns))
    if args.json:
        _out(json.dumps(row))
    return 0


# ---------------------------------------------------------------------------- worker
def cmd_worker(args: argparse.Namespace) -> int:
    # A worker must not fork after torch started its thread pools: run it in a fresh interpreter, whatever
    # this process has imported.
    argv = [sys.executable, "-m", "services.controller.worker"]
    argv += ["--burst"] if args.burst else []
    argv += ["--name", args.name] if args.name else []
    argv += ["--threads", str(args.threads)] if args.threads else []
    argv += ["--max-jobs", str(args.max_jobs)] if args.max_jobs else []
    os.execv(sys.executable, argv)
    return 0  # not reached


def _positive_int(text: str) -> int:
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be a positive integer, got {value}")
    return value


def _loop_tolerance(text: str) -> float | str:
    if text == "off":
        return text
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be a fraction of at least 0 or 'off', got {text!r}") from None
    if not value >= 0:
        raise argparse.ArgumentTypeError(f"must be a fraction of at least 0 or 'off', got {text!r}")
    return value


def _positive_float(text: str) -> float:
    value = float(text)
    if not value > 0:
        raise argparse.ArgumentTypeError(f"must be a positive number, got {value}")
    return value


def _widths(text: str) -> tuple[int, ...]:
    """Hidden layer widths: comma-separated positive integers."""
    try:
        widths = tuple(int(w) for w in text.split(","))
    except ValueError:
        widths = ()
    if not widths or min(widths) < 1:
        raise argparse.ArgumentTypeError(
            f"must be comma-separated positive integers such as 64,64, got {text!r}"
        )
    return widths


def _substeps(text: str) -> int | str:
    return "auto" if text == "auto" else _positive_int(text)


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="neuro", description="NeuroAnimator: neural emulators of MuJoCo models")
    p.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    sub = p.add_subparsers(dest="command", required=True)
    _add_train_parser(sub)
    _add_eval_parser(sub)
    _add_bench_parser(sub)
    _add_worker_parser(sub)
    _add_models_parser(sub)
    _add_policy_parser(sub)
    return p


def _add_policy_parser(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    """``neuro policy``: train a feedback policy through an emulator."""
    from neuroanimator.catalog.suite import SUITE_TASK_INFO
    from neuroanimator.catalog.tasks import POLICY_TASKS

    pp = sub.add_parser("policy", help="train a feedback policy through the emulator and store it")
    pp.add_argument(
        "task",
        help=f"policy task: {', '.join(POLICY_TASKS)}; or a dm_control suite task (its model trained "
        f"from the suite's MJCF under the domain's name): {', '.join(SUITE_TASK_INFO)}; or a JSON file "
        "holding a reward task of your own (as POST /policies takes it: docs/policies.md)",
    )
    pp.add_argument("--seconds", type=_positive_float, help="training budget (default: the task's)")
    pp.add_argument("--no-refine", action="store_true", help="no fine-tuning on the policy's MuJoCo runs")
    pp.add_argument("--artifacts", help=_ARTIFACTS_HELP)
    pp.add_argument("--seed", type=int, default=0)
    pp.add_argument(
        "--seeds",
        type=int,
        choices=range(1, 9),
        metavar="K",
        help="a reward task: train from K seeds side by side (seed, seed+1, ...), a process and a core "
        "each, and keep the best on MuJoCo (default: the task's, 2 for a body on the ground)",
    )
    pp.add_argument("--json", action="store_true")
    pp.set_defaults(func=cmd_policy)


def _add_train_parser(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    """``neuro train``: simulate data, train an emulator, export it."""
    t = sub.add_parser("train", help="simulate data, train an emulator, export it to the artifact registry")
    _add_train_source_options(t)
    _add_train_network_options(t)
    _add_train_optimisation_options(t)
    _add_train_input_options(t)
    _add_train_rollout_options(t)
    t.add_argument("--seed", type=int, default=0)
    t.add_argument("--quiet", action="store_true", help="no progress bars")
    t.add_argument("--json", action="store_true")
    t.set_defaults(func=cmd_train)


def _add_train_source_options(t: argparse.ArgumentParser) -> None:
    """``neuro train``'s model (a catalog name, or one's own ``--mjcf``), super-step and where it writes."""
    t.add_argument("model", nargs="?", help=f"catalog model: {', '.join(catalog.CATALOG)}")
    t.add_argument(
        "--mjcf",
        help="train on your own model instead of a catalog one: an MJCF file (its includes and assets are "
        "read from beside it), a model folder, or a .zip / .tar.gz of one",
    )
    t.add_argument(
        "--entry", help="with --mjcf FOLDER or ARCHIVE: the MJCF file in it (default: the only one)"
    )
    t.add_argument("--name", help="with --mjcf: the model's name (default: the MJCF's model attribute)")
    t.add_argument(
        "--spec",
        help="with --mjcf: an operating spec (JSON: the controls' centres and spreads, how runs start, the "
        "controls' time scale, the run length; docs/operating-spec.md); default: the model's keyframes, "
        "else the controls that hold it still, else every control over its range",
    )
    t.add_argument(
        "--keyframe", help="with --mjcf: train around this keyframe of the model only (default: all of them)"
    )
    t.add_argument(
        "--substeps",
        type=_substeps,
        help="super timestep n, or 'auto' (default: the catalog model's; 'auto' for --mjcf: 50 for a model "
        "without contacts or limits, else the longest of 50, 25, 10 that short probes can learn)",
    )
    t.add_argument(
        "--force", action="store_true", help="write the emulator even when it misses the acceptance bar"
    )
    t.add_argument(
        "--out",
        help="artifact registry to write to (default: the data directory, $NEUROANIMATOR_DATA_DIR or "
        "~/.local/share/neuroanimator; the committed defaults are rebuilt with --out artifacts)",
    )
    t.add_argument(
        "--data-cache",
        help="keep the simulated examples in this directory and read them back when a later training asks "
        "for the same ones (model, super-step, count, seed, sampler, simulating code; default: "
        "$NEURO_DATA_CACHE, else none)",
    )


def _add_train_network_options(t: argparse.ArgumentParser) -> None:
    """``neuro train``'s preset, optimiser and network."""
    t.add_argument("--preset", choices=["default", "thesis"], default="default")
    t.add_argument("--optimizer", choices=["adam", "sgd"], default="adam")
    t.add_argument(
        "--hidden",
        type=_widths,
        help="hidden layer widths, e.g. 64,64 (default for --mjcf: 128,128,128; a catalog model's own)",
    )
    t.add_argument(
        "--branch-hidden",
        type=_widths,
        help="an articulated hierarchy's limb networks (the runner's arms and legs), or a hierarchy's part "
        "networks (the dolphin's segments): hidden layer widths (default: as --hidden)",
    )
    t.add_argument(
        "--members",
        type=_positive_int,
        help="an articulated hierarchy (the runner): each network the mean of this many MLPs, each trained "
        "on its own error (an ensemble; default 1)",
    )
    t.add_argument(
        "--loop-tolerance",
        metavar="FRACTION|off",
        type=_loop_tolerance,
        help="the kept epoch: of those whose validation loss is within this fraction of the lowest, the "
        "one whose closed loop (the model's own controller through the emulator) ends nearest MuJoCo's; "
        "for models whose data source has a loop check (the runner; default off, or the model's own)",
    )
    t.add_argument(
        "--activation",
        choices=["sigmoid", "tanh", "silu", "gelu", "relu"],
        help="hidden units (default for --mjcf: silu)",
    )


def _add_train_optimisation_options(t: argparse.ArgumentParser) -> None:
    """``neuro train``'s training data and one-step optimisation: examples, sampler, epochs, learning
    rate and time limits."""
    t.add_argument(
        "--examples",
        type=_positive_int,
        help="training examples (default: 10 × weights, cut to what the model simulates in 40%% of the time budget)",
    )
    t.add_argument(
        "--sampler",
        choices=sampling.SAMPLERS,
        help="training data: every super-step of runs driven with held controls (runs, the default: "
        "about n physical steps an example) or thesis 4.5's examples at lags of [Δt, 5Δt] (spaced: about 6n)",
    )
    t.add_argument("--epochs", type=_positive_int, help="maximum epochs")
    t.add_argument(
        "--batch-size", type=_positive_int, help="examples per gradient step (default 256; 512 for --mjcf)"
    )
    t.add_argument("--lr", type=_positive_float, help="learning rate")
    t.add_argument(
        "--schedule",
        choices=["plateau", "cosine"],
        help="learning rate: halved when validation stalls (plateau, the default for a smooth catalog model) "
        "or annealed over the time budget (cosine, the default for --mjcf and where contacts or limits engage)",
    )
    t.add_argument(
        "--max-seconds",
        type=_positive_float,
        help="cap on the one-step phase's optimisation time (default 150; given, no --time-budget applies)",
    )
    t.add_argument(
        "--time-budget",
        type=float,
        help="the whole command's wall-clock budget in seconds, probes and sampling included (default 285; "
        "0: none): the rollout phase gets what is left, the one-step phase is cut only after very slow sampling; "
        "a larger budget buys more: the examples and both phases' caps grow by how many times 285 s it is",
    )


def _add_train_input_options(t: argparse.ArgumentParser) -> None:
    """``neuro train``'s local frame and what the network reads besides the state; mirrored examples."""
    t.add_argument(
        "--frame",
        choices=["auto", "body", "heading"],
        default="auto",
        help="local frame of a free root: body (the default) or heading only",
    )
    t.add_argument("--no-skip", action="store_true", help="no linear path beside the MLP")
    t.add_argument(
        "--limits",
        choices=["on", "off"],
        help="each limited joint also enters as ramps past its range at the start, middle and end of the "
        "super-step, where its limit's force switches on (default on; off for the runner)",
    )
    t.add_argument(
        "--clearance",
        choices=["on", "off"],
        help="the network also reads how high the geoms that come near the floor are above it, computed "
        "in the graph by forward kinematics (contact with the ground; default: on where a fifth or more of "
        "the sampled states touch the floor, a walker's or a hopper's, and the training says why)",
    )
    t.add_argument(
        "--proximity",
        choices=["on", "off"],
        help="the network also reads the distance between each pair of geoms that touch each other in "
        "the training data (a fingertip and what it pushes), computed in the graph by forward kinematics "
        "(default off: on dm_control's finger it did not lower the error; a hierarchy's networks read none)",
    )
    t.add_argument(
        "--mirror",
        choices=["on", "off"],
        help="a left-right symmetric figure (joints and actuators named left_*/right_*, mirror images of "
        "each other across the x-z plane): half the examples are simulated, half are their mirror images "
        "(default off); a model that is not symmetric is refused, naming the part",
    )


def _add_train_rollout_options(t: argparse.ArgumentParser) -> None:
    """``neuro train``'s rollout phase, a hierarchy's state noise and a mass-spring model's
    regulariser."""
    t.add_argument(
        "--rollout-steps",
        type=int,
        help="super-steps of the rollout training phase (default 8, a hierarchy's 0: off; a "
        "hierarchy's is through its composed step, regulariser included)",
    )
    t.add_argument(
        "--rollout-seconds",
        type=float,
        help="wall-clock cap on the rollout training phase (default 60 s)",
    )
    t.add_argument(
        "--state-noise",
        type=float,
        help="a hierarchy's global network trained from states moved by noise of this share of each "
        "group's change over a super-step, its targets unchanged, so that it learns to pull a drifted "
        "body back (default 0; the committed dolphin's 0.02, as BENCHMARKS.md measures)",
    )
    t.add_argument(
        "--regularizer-steps",
        type=int,
        help="a mass-spring model's spring Euler steps after each super-step (thesis 6.1.3; default: "
        "the model's, 2 for the dolphin, with its plates' pull, as measured in BENCHMARKS.md; 0: off)",
    )


def _add_eval_parser(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    """``neuro eval``: one-step and rollout error against MuJoCo."""
    e = sub.add_parser("eval", help="one-step and rollout error against MuJoCo (thesis Fig. 6.6)")
    e.add_argument("model")
    e.add_argument("--substeps", type=_positive_int, help="only this n (default: every trained n)")
    e.add_argument("--artifacts", help=_ARTIFACTS_HELP)
    e.add_argument("--trials", type=_positive_int, default=30)
    e.add_argument("--steps", type=_positive_int, default=6000, help="physical steps per trial")
    e.add_argument("--plot", help="PNG path (default: <artifacts>/<model>/rollout_error.png)")
    e.add_argument(
        "--save", action="store_true", help="store each version's results in its folder (eval.json)"
    )
    e.add_argument("--json", action="store_true")
    e.set_defaults(func=cmd_eval)


def _add_bench_parser(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    """``neuro bench``: speed against MuJoCo."""
    b = sub.add_parser("bench", help="speed against MuJoCo on the same cores (thesis Table 6.2)")
    b.add_argument("model")
    b.add_argument("--artifacts", help=_ARTIFACTS_HELP)
    b.add_argument("--batches", help="comma-separated batch sizes (default 1,64,1024,4096)")
    b.add_argument("--repeats", type=_positive_int, default=3)
    b.add_argument(
        "--save", action="store_true", help="store each version's results in its folder (bench.json)"
    )
    b.add_argument("--json", action="store_true")
    b.set_defaults(func=cmd_bench)


def _add_worker_parser(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    """``neuro worker``: run controller-synthesis jobs from the queue."""
    w = sub.add_parser(
        "worker", help="run controller-synthesis jobs from the Redis queue (settings from env)"
    )
    w.add_argument("--burst", action="store_true", help="run the queued jobs, then exit")
    w.add_argument("--name", help="the worker's name (default: host.pid.random)")
    w.add_argument(
        "--threads",
        type=_positive_int,
        help="torch threads per job (default: WORKER_THREADS; unset, a policy job its task's, others one)",
    )
    w.add_argument("--max-jobs", type=_positive_int, help="exit after this many jobs")
    w.set_defaults(func=cmd_worker)


def _add_models_parser(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    """``neuro models``: the catalog and what is trained."""
    ls = sub.add_parser("models", help="the catalog and what is trained")
    ls.add_argument("--artifacts", help=_ARTIFACTS_HELP)
    ls.add_argument("--json", action="store_true")
    ls.add_argument("--catalog", action="store_true", help="only the catalog's model names, one per line")
    ls.set_defaults(func=cmd_models)


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(
        level=logging.DEBUG if args.verbose else logging.INFO,
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
        stream=sys.stderr,
    )
    try:
        return int(args.func(args))
    except (ModelError, registry.ArtifactError, ValueError) as exc:
        log.error("%s", exc)
        return 2


if __name__ == "__main__":
    sys.exit(main())
