"""Job specs: ``validate_job`` turns a request into a ``JobSpec``, without importing torch or MuJoCo.

An API process calls it on every submission, so it reads only numpy and the artifact manifests,
through the torch-free ``neuroanimator.artifacts.registry``. The spec it
returns is itself a valid request, so validating twice changes nothing: a worker validates the
queued spec again against its own artifacts.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from neuroanimator.artifacts import registry
from neuroanimator.catalog.tasks import TASKS
from neuroanimator.contracts.controller import JobCreate
from neuroanimator.core.manifest import ControlInput, Manifest
from neuroanimator.core.state import QUATERNION_KINDS, LayoutGroup
from neuroanimator.goals import criteria
from neuroanimator.goals.criteria import SuccessCheck
from neuroanimator.goals.errors import JobSpecError
from neuroanimator.goals.spec import (
    DEFAULT_HORIZON,
    DEFAULT_MU_S,
    DEFAULT_MU_U,
    DEFAULT_POINTS_PER_STEP,
    MAX_GLOBAL_GENERATIONS,
    MAX_HORIZON,
    MAX_ITERATIONS,
    MAX_LEARNING_RATE,
    MAX_MU,
    MAX_PHYSICS_ROUNDS,
    MAX_STARTS,
    MAX_SUBSTEPS,
    JobSpec,
    OptimizerSettings,
    Task,
)
from neuroanimator.goals.terms import MAX_WEIGHT, finite_number, normalize_terms, shown, unit, vector

# what a request may set: the API body's fields, less what only the API uses
JOB_FIELDS = frozenset(JobCreate.model_fields) - {"idempotency_key"}
OPTIMIZER_FIELDS = frozenset(OptimizerSettings.model_fields)


def find_artifact(
    root: registry.Root, model: str, version: str | None, substeps: int | None
) -> tuple[Path, Manifest]:
    """The version folder and manifest of a model (``registry.resolve`` + ``read_manifest``); a missing
    model, version or super-step is a ``JobSpecError`` on that field."""
    try:
        path = registry.resolve(root, model, version, substeps)
        return path, registry.read_manifest(path)
    except registry.ArtifactError as exc:
        raise JobSpecError("version" if exc.what in ("manifest", "results") else exc.what, str(exc)) from exc


def _int(field: str, value: Any, low: int, high: int) -> int:
    """An integer (or a float of integer value) in [low, high]; a huge integer or ±inf is out of it."""
    ok = (
        isinstance(value, int | float)
        and not isinstance(value, bool)
        and (isinstance(value, int) or (math.isfinite(value) and value == int(value)))
        and low <= value <= high
    )
    if not ok:
        raise JobSpecError(field, f"expected an integer in [{low}, {high}], got {shown(value)}")
    return int(value)


def _float(
    field: str, value: Any, *, low: float, high: float, low_open: bool = False, high_open: bool = False
) -> float:
    lo_s = "(" if low_open else "["
    hi_s = ")" if high_open else "]"
    expected = f"a number in {lo_s}{low:g}, {high:g}{hi_s}"
    v = finite_number(value)
    if v is None or v < low or v > high or (low_open and v == low) or (high_open and v == high):
        raise JobSpecError(field, f"expected {expected}, got {shown(value)}")
    return v


def _state(field: str, value: Any, layout: Sequence[LayoutGroup], size: int, model: str) -> list[float]:
    """A state of the model's size, finite, with every quaternion group of unit length."""
    out = vector(field, value, size, f"state values for model {model}")
    for g in layout:
        if g.kind in QUATERNION_KINDS:
            a = g.offset
            q = out[a : a + 4]
            if math.sqrt(sum(v * v for v in q)) < 1e-6:
                raise JobSpecError(
                    field, f"quaternion {g.name} (values {a}..{a + 3}) must be non-zero, got {q}"
                )
            out[a : a + 4] = unit(q)
    return out


def default_state(layout: Sequence[LayoutGroup], size: int) -> list[float]:
    """Zeros with identity quaternions: the state a job without a task starts from by default."""
    s = [0.0] * size
    for g in layout:
        if g.kind in QUATERNION_KINDS:
            s[g.offset] = 1.0
    return s


def validate_job(job: JobCreate | JobSpec | Mapping[str, Any], artifacts_root: registry.Root) -> JobSpec:
    """Check a job and return its ``JobSpec``, every default filled in (the task's first).

    ``job`` is an API body, a spec validated before (``validate_job(spec) == spec`` while the
    artifacts are the same), or the JSON object of either. Raises ``JobSpecError(field, message)``
    naming the field, the expected and the got, for an unknown task, model, version or term, a
    state of the wrong length or not finite, a horizon outside [1, 1000], max_iterations outside
    [1, 10000], learning_rate outside (0, 100], momentum outside [0, 1), and the like. Imports
    neither torch nor MuJoCo.
    """
    spec = _request(job)
    task = _task(spec)
    model = _model(spec, task)
    manifest = _manifest(spec, task, model, artifacts_root)
    layout = manifest.layout
    labels = manifest.state_labels
    initial, target, weights = _states(spec, task, layout, len(labels), model)
    horizon = _int("horizon", spec.get("horizon", task.horizon if task else DEFAULT_HORIZON), 1, MAX_HORIZON)
    pps = _float(
        "points_per_step",
        spec.get("points_per_step", task.points_per_step if task else DEFAULT_POINTS_PER_STEP),
        low=0.0,
        high=1.0,
        low_open=True,
    )
    mu_u = _float("mu_u", spec.get("mu_u", task.mu_u if task else DEFAULT_MU_U), low=0.0, high=MAX_MU)
    mu_s = _float("mu_s", spec.get("mu_s", task.mu_s if task else DEFAULT_MU_S), low=0.0, high=MAX_MU)
    terms = normalize_terms(
        spec.get("terms", [dict(t) for t in task.terms] if task else []),
        labels=labels,
        layout=layout,
        target=target,
        weights=weights,
        horizon=horizon,
        super_dt=manifest.super_timestep,
    )
    if mu_u == 0 and mu_s == 0 and not terms:
        raise JobSpecError("terms", "the objective is empty: mu_u = mu_s = 0 and no terms")
    return JobSpec(
        task=task.name if task else None,
        model=model,
        version=manifest.version,
        substeps=manifest.substeps,
        initial_state=initial,
        target_state=target,
        state_weights=weights,
        horizon=horizon,
        points_per_step=pps,
        mu_u=mu_u,
        mu_s=mu_s,
        terms=terms,
        initial_controls=_initial_controls(spec, task, manifest.controls, model),
        success=_success(spec, task, labels),
        optimizer=_optimizer(spec.get("optimizer", {}), task),
    )


def _request(job: Any) -> Mapping[str, Any]:
    """The job as the JSON object of a request, with no key a job does not take."""
    if isinstance(job, JobCreate):
        spec: Mapping[str, Any] = job.spec()
    elif isinstance(job, JobSpec):
        spec = job.model_dump()
    elif isinstance(job, Mapping):
        spec = job
    else:
        raise JobSpecError("spec", f"expected an object, got {type(job).__name__}")
    unknown = sorted(set(spec) - JOB_FIELDS)
    if unknown:
        raise JobSpecError(unknown[0], f"unknown key; a job takes {sorted(JOB_FIELDS)}, got {unknown}")
    return spec


def _task(spec: Mapping[str, Any]) -> Task | None:
    """The built-in task the job names, if it names one."""
    if spec.get("task") is None:
        return None
    name = spec["task"]
    if not isinstance(name, str) or name not in TASKS:
        raise JobSpecError("task", f"unknown task {name!r}; known tasks are {sorted(TASKS)}", sorted(TASKS))
    return TASKS[name]


def _model(spec: Mapping[str, Any], task: Task | None) -> str:
    """The model the job runs on: the one it names, else its task's (a task's job names no other)."""
    model = spec.get("model")
    if model is None:
        if task is None:
            raise JobSpecError("task", "expected a task or a model, got neither")
        model = task.model
    if not isinstance(model, str):
        raise JobSpecError("model", f"expected a model name, got {model!r}")
    if task is not None and model != task.model:
        raise JobSpecError("model", f"task {task.name!r} runs on model {task.model!r}, got {model!r}")
    return model


def _manifest(spec: Mapping[str, Any], task: Task | None, model: str, root: registry.Root) -> Manifest:
    """The manifest of the artifact the job runs on: the version it names, else the latest (of its
    task's super-step when it names neither version nor super-step); a model without controls has
    nothing to synthesise."""
    version = spec.get("version")
    if version is not None and not isinstance(version, str):
        raise JobSpecError("version", f"expected a version name, got {version!r}")
    substeps = spec.get("substeps", task.substeps if task and version is None else None)
    if substeps is not None:
        substeps = _int("substeps", substeps, 1, MAX_SUBSTEPS)
    _, manifest = find_artifact(root, model, version, substeps)
    if not manifest.controls:
        raise JobSpecError("model", f"model {model!r} has no controls: there is nothing to synthesise")
    return manifest


def _states(
    spec: Mapping[str, Any], task: Task | None, layout: Sequence[LayoutGroup], size: int, model: str
) -> tuple[list[float], list[float], list[float]]:
    """The initial state (S,), the target state (S,) (by default the initial one when there is no
    task) and the state weights (S,), none negative."""
    initial = _state(
        "initial_state",
        spec.get("initial_state", list(task.initial_state) if task else default_state(layout, size)),
        layout,
        size,
        model,
    )
    target = _state(
        "target_state",
        spec.get("target_state", list(task.target_state) if task else initial),
        layout,
        size,
        model,
    )
    weights = vector(
        "state_weights",
        spec.get("state_weights", list(task.state_weights) if task else [1.0] * size),
        size,
        bound=MAX_WEIGHT,
    )
    negative = [i for i, w in enumerate(weights) if w < 0]
    if negative:
        i = negative[0]
        raise JobSpecError(
            f"state_weights[{i}]", f"expected {size} weights >= 0, got {weights[i]:g} at index {i}"
        )
    return initial, target, weights


def _initial_controls(
    spec: Mapping[str, Any], task: Task | None, controls: Sequence[ControlInput], model: str
) -> list[float]:
    """The controls (U,) the search starts from, each within its limits (by default 0 clipped to them)."""
    lim = np.array([[c.limit_low, c.limit_high] for c in controls], dtype=np.float64)
    u0 = vector(
        "initial_controls",
        spec.get(
            "initial_controls",
            list(task.initial_controls) if task else np.clip(0.0, lim[:, 0], lim[:, 1]).tolist(),
        ),
        len(controls),
        f"control values for model {model}",
    )
    for i, (v, (lo, hi)) in enumerate(zip(u0, lim, strict=True)):
        if not lo <= v <= hi:
            raise JobSpecError(
                "initial_controls",
                f"control {controls[i].name} must lie in its limits [{lo:g}, {hi:g}], got {v:g}",
            )
    return u0


def _success(spec: Mapping[str, Any], task: Task | None, labels: Sequence[str]) -> list[SuccessCheck]:
    """The success checks (the task's by default), each naming state variables the model has."""
    success = spec.get("success", [c.model_dump() for c in task.success] if task else [])
    problems = criteria.validate_checks(success, labels)
    if problems:
        where, what = problems[0]
        raise JobSpecError(f"success{where}", what)
    return [SuccessCheck.model_validate(c) for c in success]


def _optimizer(given: Any, task: Task | None) -> OptimizerSettings:
    """The request's optimizer settings over the task's over the defaults, each checked."""
    if not isinstance(given, Mapping):
        raise JobSpecError("optimizer", f"expected an object, got {type(given).__name__}")
    bad = sorted(set(given) - OPTIMIZER_FIELDS)
    if bad:
        raise JobSpecError(
            f"optimizer.{bad[0]}", f"unknown key; the optimizer takes {sorted(OPTIMIZER_FIELDS)}"
        )
    opt = {**OptimizerSettings().model_dump(), **(task.optimizer if task else {}), **given}
    for flag in ("stop_on_success", "line_search"):
        if not isinstance(opt[flag], bool):
            raise JobSpecError(f"optimizer.{flag}", f"expected true or false, got {opt[flag]!r}")
    return OptimizerSettings(
        learning_rate=_float(
            "optimizer.learning_rate", opt["learning_rate"], low=0.0, high=MAX_LEARNING_RATE, low_open=True
        ),
        momentum=_float("optimizer.momentum", opt["momentum"], low=0.0, high=1.0, high_open=True),
        max_iterations=_int("optimizer.max_iterations", opt["max_iterations"], 1, MAX_ITERATIONS),
        tolerance=_float("optimizer.tolerance", opt["tolerance"], low=0.0, high=1.0),
        stop_on_success=opt["stop_on_success"],
        line_search=opt["line_search"],
        polish_iterations=_int("optimizer.polish_iterations", opt["polish_iterations"], 0, MAX_ITERATIONS),
        physics_rounds=_int("optimizer.physics_rounds", opt["physics_rounds"], 0, MAX_PHYSICS_ROUNDS),
        starts=_int("optimizer.starts", opt["starts"], 1, MAX_STARTS),
        global_generations=_int(
            "optimizer.global_generations", opt["global_generations"], 0, MAX_GLOBAL_GENERATIONS
        ),
        gauss_newton_iterations=_int(
            "optimizer.gauss_newton_iterations", opt["gauss_newton_iterations"], 0, MAX_ITERATIONS
        ),
    )
