"""The objective-term catalogue: names, parameters, defaults, validation and the validated types.

Torch-free, so ``validate_job`` can check a job's ``terms`` without loading PyTorch; the
differentiable implementations live in ``objectives.py`` under the same names. A term in a job is
a JSON object ``{"term": <name>, "weight": <w >= 0>, ...parameters}``; the objective is

    J = μ_u/2 Σ_k Σ_i (u_ki / r_i)²  +  μ_s/2 ‖W (s_K − s_d)‖²  +  Σ_terms weight · term

(eq. 5.3 plus the extra terms; r_i is the largest magnitude of control i's useful range, so every
control counts in units of its own range). State variables are named by their labels
(``StateLayout.labels()``) or by index.

``normalize_terms`` returns each term as its validated type (``Term``, one class per name, every
default filled in, variables as indices); the JSON of a validated term is itself a valid term that
validates to the same value.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field

from neuroanimator.core.state import LayoutGroup
from neuroanimator.goals.errors import JobSpecError

TERMS: dict[str, str] = {
    "final_state": "weight/2 ‖W (s_K − target)‖² on the final state; params: target (S), weights (S); "
    "defaults: the job's target_state and state_weights",
    "control_effort": "weight/2 Σ (u/r)² over the held controls of every super-step",
    "control_smoothness": "weight/2 Σ ((u_k − u_{k−1})/r)²: penalises jumps between super-steps",
    "final_velocity": "weight/2 ‖v_K‖² on the velocity variables at the end; params: variables "
    "(labels; default every qvel variable)",
    "forward_distance": "−weight · direction·(p_K − p_0): maximises the displacement of variables "
    "(default: the root position) along direction (default +x)",
    "stay_within_bounds": "weight/2 Σ_k (max(0, low − x_k)² + max(0, x_k − high)²): a soft box on one "
    "state variable over the whole trajectory; params: variable, low and/or high (null: no bound)",
    "success_margin": "weight Σ_checks max(0, r − margin)²: the job's success checks as a penalty, r "
    "the check's measure over its bound, squared (a check at its bound has r = 1, one met with room "
    "to spare r < margin, and adds nothing); params: margin (default 0.5)",
    "path_target": "weight/2 Σ_waypoints ‖W (s_k − target)‖²; params: waypoints [{step | time, target}], "
    "weights (S; default the job's)",
}
UNIT_TOLERANCE = 1e-12  # a direction or quaternion this close to unit length is kept as it is
MAX_VALUE = 1e4
"""The largest magnitude of a state value, target, bound or direction component in a job (metres,
radians and their rates): beyond it no model of the catalog has a physical state, and a simulation
started there diverges at once."""
MAX_WEIGHT = 1e6
"""The largest weight of a term or of a state variable."""
Finite = Annotated[float, Field(allow_inf_nan=False)]


class _Term(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)

    term: str = Field(description="the term's name, one of TERMS")
    weight: Finite = Field(ge=0)


class FinalStateTerm(_Term):
    """weight/2 ‖W (s_K − target)‖²: target (S,) and weights (S,)."""

    term: Literal["final_state"]
    target: list[Finite]
    weights: list[Finite]


class ControlEffortTerm(_Term):
    """weight/2 Σ (u/r)² over the held controls."""

    term: Literal["control_effort"]


class ControlSmoothnessTerm(_Term):
    """weight/2 Σ ((u_k − u_{k−1})/r)²."""

    term: Literal["control_smoothness"]


class FinalVelocityTerm(_Term):
    """weight/2 ‖s_K[variables]‖²: variables are state indices."""

    term: Literal["final_velocity"]
    variables: list[int] = Field(min_length=1)


class ForwardDistanceTerm(_Term):
    """−weight · direction·(s_K − s_0)[variables]: a unit direction, one value per variable index."""

    term: Literal["forward_distance"]
    direction: list[Finite] = Field(min_length=1)
    variables: list[int] = Field(min_length=1)


class StayWithinBoundsTerm(_Term):
    """weight/2 Σ_k (max(0, low − x_k)² + max(0, x_k − high)²) of state index ``variable``; a bound
    that is None is no bound (at least one is set)."""

    term: Literal["stay_within_bounds"]
    variable: int = Field(ge=0)
    low: Finite | None
    high: Finite | None


class SuccessMarginTerm(_Term):
    """weight Σ_checks max(0, r − margin)² over the job's success checks (``objectives.py``)."""

    term: Literal["success_margin"]
    margin: Finite = Field(gt=0, le=1)


class Waypoint(BaseModel):
    """A target state (S,) at super-step ``step`` (0 is the initial state)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    step: int = Field(ge=0)
    target: list[Finite]


class PathTargetTerm(_Term):
    """weight/2 Σ_waypoints ‖W (s_step − target)‖² with weights (S,)."""

    term: Literal["path_target"]
    weights: list[Finite]
    waypoints: list[Waypoint] = Field(min_length=1)


Term = Annotated[
    FinalStateTerm
    | ControlEffortTerm
    | ControlSmoothnessTerm
    | FinalVelocityTerm
    | ForwardDistanceTerm
    | StayWithinBoundsTerm
    | SuccessMarginTerm
    | PathTargetTerm,
    Field(discriminator="term"),
]
"""A validated objective term; ``term`` names its kind (the keys of ``TERMS``)."""


def finite_number(value: Any) -> float | None:
    """``value`` as a float when it is a finite JSON number, else None: booleans, strings, NaN, ±inf
    and integers too large for a float (JSON may carry 1 followed by 330 zeros) are not."""
    if isinstance(value, bool) or not isinstance(value, int | float):
        return None
    try:
        out = float(value)
    except OverflowError:
        return None
    return out if math.isfinite(out) else None


def shown(value: Any) -> str:
    """``repr`` of a value for a message, cut to 80 characters (a number may have hundreds of digits)."""
    text = repr(value)
    return text if len(text) <= 80 else f"{text[:60]}... ({len(text)} characters)"


def _number(field: str, value: Any, *, low: float | None = None, high: float = MAX_VALUE) -> float:
    v = finite_number(value)
    if v is None:
        raise JobSpecError(field, f"expected a finite number, got {shown(value)}")
    if low is not None and v < low:
        raise JobSpecError(field, f"expected a number >= {low}, got {shown(value)}")
    if abs(v) > high:
        raise JobSpecError(field, f"expected a number of magnitude <= {high:g}, got {shown(value)}")
    return v


def vector(field: str, value: Any, size: int, what: str = "numbers", bound: float = MAX_VALUE) -> list[float]:
    """A list of ``size`` finite numbers of magnitude at most ``bound``, or JobSpecError naming the
    field, the expected and the got."""
    if not isinstance(value, list | tuple):
        raise JobSpecError(field, f"expected a list of {size} {what}, got {type(value).__name__}")
    if len(value) != size:
        raise JobSpecError(field, f"expected {size} {what}, got {len(value)}")
    out = []
    for i, v in enumerate(value):
        f = finite_number(v)
        if f is None:
            raise JobSpecError(f"{field}[{i}]", f"expected {size} finite {what}, got {shown(v)} at index {i}")
        if abs(f) > bound:
            raise JobSpecError(
                f"{field}[{i}]",
                f"expected {size} {what} of magnitude <= {bound:g}, got {shown(v)} at index {i}",
            )
        out.append(f)
    return out


def variable_index(field: str, name: Any, labels: Sequence[str]) -> int:
    """A state variable by label or index."""
    if isinstance(name, int) and not isinstance(name, bool) and 0 <= name < len(labels):
        return name
    if isinstance(name, str) and name in labels:
        return list(labels).index(name)
    raise JobSpecError(
        field, f"expected a state label (one of {list(labels)}) or an index, got {shown(name)}"
    )


def unit(values: list[float]) -> list[float]:
    """``values`` scaled to length 1, or as they are when already of unit length (so a validated
    direction or quaternion validates to the same numbers, not to a last-bit rounding of them).
    ``math.hypot`` scales as it goes, so huge components do not overflow to a length of inf."""
    length = math.hypot(*values)
    if abs(length - 1.0) <= UNIT_TOLERANCE:
        return values
    return [v / length for v in values]


def _indices(field: str, names: Any, labels: Sequence[str]) -> list[int]:
    if not isinstance(names, list) or not names:
        raise JobSpecError(field, f"expected a non-empty list of state labels, got {shown(names)}")
    if len(names) > len(labels):
        raise JobSpecError(
            field, f"expected at most {len(labels)} state variables (the model's), got {len(names)}"
        )
    return [variable_index(f"{field}[{i}]", n, labels) for i, n in enumerate(names)]


def _bound(field: str, t: Mapping[str, object], key: str) -> float | None:
    return None if t.get(key) is None else _number(f"{field}.{key}", t[key])


@dataclass(frozen=True)
class _JobContext:
    """What a term's defaults and checks read from its job: the model's state labels and layout,
    the job's target (S,) and state weights (S,), its horizon in super-steps and the super-step."""

    labels: Sequence[str]
    layout: Sequence[LayoutGroup]
    target: list[float]
    weights: list[float]
    horizon: int
    super_dt: float


def normalize_terms(
    terms: Any,
    *,
    labels: Sequence[str],
    layout: Sequence[LayoutGroup],
    target: list[float],
    weights: list[float],
    horizon: int,
    super_dt: float,
) -> list[Term]:
    """Validate a job's ``terms`` and return them typed, with every default filled in.

    Variables become indices (``variables``/``variable``), waypoint times become super-step
    indices, directions unit vectors; unknown names or parameters raise ``JobSpecError``.
    """
    if terms is None:
        return []
    if not isinstance(terms, list):
        raise JobSpecError("terms", f"expected a list of term objects, got {type(terms).__name__}")
    job = _JobContext(labels, layout, target, weights, horizon, super_dt)
    return [_term(f"terms[{i}]", t, job) for i, t in enumerate(terms)]


def _term(at: str, t: Any, job: _JobContext) -> Term:
    """One term of a job (``at`` is where it sits, ``terms[i]``): its name and weight are checked
    first, then its parameters, then that it has no parameter its kind does not take."""
    if not isinstance(t, dict):
        raise JobSpecError(at, f"expected an object like {{'term': 'final_state'}}, got {t!r}")
    name = t.get("term")
    if name not in TERMS:
        raise JobSpecError(f"{at}.term", f"unknown term {name!r}; known terms are {sorted(TERMS)}")
    weight = _number(f"{at}.weight", t.get("weight", 1.0), low=0.0, high=MAX_WEIGHT)
    term = _BUILDERS[name](at, t, weight, job)
    allowed = {"term", "weight", *_PARAMETERS[name]}
    extra = sorted(set(t) - allowed)
    if extra:
        raise JobSpecError(at, f"unknown parameters {extra} for term {name!r}; it takes {sorted(allowed)}")
    return term


def _final_state(at: str, t: Mapping[str, object], weight: float, job: _JobContext) -> Term:
    size = len(job.labels)
    return FinalStateTerm(
        term="final_state",
        weight=weight,
        target=vector(f"{at}.target", t.get("target", job.target), size),
        weights=vector(f"{at}.weights", t.get("weights", job.weights), size, bound=MAX_WEIGHT),
    )


def _control_effort(at: str, t: Mapping[str, object], weight: float, job: _JobContext) -> Term:
    return ControlEffortTerm(term="control_effort", weight=weight)


def _control_smoothness(at: str, t: Mapping[str, object], weight: float, job: _JobContext) -> Term:
    return ControlSmoothnessTerm(term="control_smoothness", weight=weight)


def _final_velocity(at: str, t: Mapping[str, object], weight: float, job: _JobContext) -> Term:
    """By default every variable read from qvel."""
    default = [i for g in job.layout if g.source == "qvel" for i in range(g.offset, g.offset + g.size)]
    variables = _indices(f"{at}.variables", t.get("variables", default), job.labels)
    return FinalVelocityTerm(term="final_velocity", weight=weight, variables=variables)


def _forward_distance(at: str, t: Mapping[str, object], weight: float, job: _JobContext) -> Term:
    """By default the root position's variables along their first axis; the direction is made unit."""
    if "variables" in t:
        variables = _indices(f"{at}.variables", t["variables"], job.labels)
    else:
        root = next((g for g in job.layout if g.kind == "position"), None)
        if root is None:
            raise JobSpecError(
                at,
                "forward_distance needs a model with a root position group (this one has none), or variables",
            )
        variables = list(range(root.offset, root.offset + root.size))
    dim = len(variables)
    direction = vector(f"{at}.direction", t.get("direction", [1.0] + [0.0] * (dim - 1)), dim)
    if not any(direction):
        raise JobSpecError(f"{at}.direction", "expected a non-zero direction, got all zeros")
    return ForwardDistanceTerm(
        term="forward_distance", weight=weight, direction=unit(direction), variables=variables
    )


def _stay_within_bounds(at: str, t: Mapping[str, object], weight: float, job: _JobContext) -> Term:
    """One variable (required) and at least one of low <= high."""
    if "variable" not in t:
        raise JobSpecError(f"{at}.variable", "expected a state label, got nothing")
    variable = variable_index(f"{at}.variable", t["variable"], job.labels)
    lo, hi = _bound(at, t, "low"), _bound(at, t, "high")
    if lo is None and hi is None:
        raise JobSpecError(at, "expected low and/or high bounds, got neither")
    if lo is not None and hi is not None and lo > hi:
        raise JobSpecError(f"{at}.low", f"expected low <= high, got low={lo} > high={hi}")
    return StayWithinBoundsTerm(term="stay_within_bounds", weight=weight, variable=variable, low=lo, high=hi)


def _success_margin(at: str, t: Mapping[str, object], weight: float, job: _JobContext) -> Term:
    margin = _number(f"{at}.margin", t.get("margin", 0.5), low=0.0)
    if not 0 < margin <= 1:
        raise JobSpecError(f"{at}.margin", f"expected a number in (0, 1], got {margin!r}")
    return SuccessMarginTerm(term="success_margin", weight=weight, margin=margin)


def _path_target(at: str, t: Mapping[str, object], weight: float, job: _JobContext) -> Term:
    size = len(job.labels)
    return PathTargetTerm(
        term="path_target",
        weight=weight,
        weights=vector(f"{at}.weights", t.get("weights", job.weights), size, bound=MAX_WEIGHT),
        waypoints=_waypoints(f"{at}.waypoints", t.get("waypoints"), size, job.horizon, job.super_dt),
    )


# each term's builder: (where it sits, its JSON object, its checked weight, the job) -> the term; the
# object's values are as the request sent them (any JSON), each checked before it is used
_BUILDERS: dict[str, Callable[[str, Mapping[str, object], float, _JobContext], Term]] = {
    "final_state": _final_state,
    "control_effort": _control_effort,
    "control_smoothness": _control_smoothness,
    "final_velocity": _final_velocity,
    "forward_distance": _forward_distance,
    "stay_within_bounds": _stay_within_bounds,
    "success_margin": _success_margin,
    "path_target": _path_target,
}
# the parameters each term takes beside "term" and "weight"
_PARAMETERS: dict[str, frozenset[str]] = {
    "final_state": frozenset({"target", "weights"}),
    "control_effort": frozenset(),
    "control_smoothness": frozenset(),
    "final_velocity": frozenset({"variables"}),
    "forward_distance": frozenset({"direction", "variables"}),
    "stay_within_bounds": frozenset({"variable", "low", "high"}),
    "success_margin": frozenset({"margin"}),
    "path_target": frozenset({"waypoints", "weights"}),
}


def _waypoints(field: str, wps: Any, size: int, horizon: int, super_dt: float) -> list[Waypoint]:
    """Waypoints ``[{step | time, target}]`` with every time turned into a super-step index."""
    if not isinstance(wps, list) or not wps:
        raise JobSpecError(field, f"expected a non-empty list of waypoints, got {shown(wps)}")
    if len(wps) > horizon + 1:
        raise JobSpecError(
            field,
            f"expected at most {horizon + 1} waypoints (one per super-step of the horizon), got {len(wps)}",
        )
    out = []
    for j, wp in enumerate(wps):
        wat = f"{field}[{j}]"
        if not isinstance(wp, dict):
            raise JobSpecError(wat, f"expected an object {{step|time, target}}, got {shown(wp)}")
        if "step" in wp:
            step = wp["step"]
            if isinstance(step, bool) or not isinstance(step, int) or not 0 <= step <= horizon:
                raise JobSpecError(f"{wat}.step", f"expected an integer in [0, {horizon}], got {shown(step)}")
        elif "time" in wp:
            end = horizon * super_dt
            steps = _number(f"{wat}.time", wp["time"], low=0.0, high=math.inf) / super_dt
            # the quotient may be inf (a time near 1e308): compared before it is rounded
            if not steps <= horizon + 0.5 or round(steps) > horizon:
                raise JobSpecError(
                    f"{wat}.time", f"expected a time in [0, {end:g}] s, got {shown(wp['time'])}"
                )
            step = round(steps)
        else:
            raise JobSpecError(wat, "expected a step (super-step index) or a time (seconds), got neither")
        out.append(Waypoint(step=int(step), target=vector(f"{wat}.target", wp.get("target"), size)))
    return out
