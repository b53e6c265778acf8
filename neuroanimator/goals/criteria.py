"""Success criteria: checks on a final state, evaluated with numpy (no torch).

A criterion is a list of checks (``SuccessCheck``, JSON like ``{"check": "norm", "variables":
["velocity.x", "velocity.y"], "max": 0.5}``), each naming state variables by their labels
(``StateLayout.labels()``, e.g. ``"angles.j0"``, ``"position.z"``). Targets default to the job's
target state, so a criterion follows a job that moves the goal. Kinds:

- ``angle``: every variable within ``max`` radians of its target, the difference wrapped to (-π, π].
- ``abs``: every variable within ``max`` of its target.
- ``distance``: the Euclidean distance of the variables (together) to their target at most ``max``.
- ``norm``: the Euclidean norm of the variables (a speed) at most ``max``.
- ``orientation``: the rotation angle between the quaternion (4 variables) and its target at most
  ``max`` radians; ``q`` and ``-q`` are the same orientation.
- ``range``: every variable in ``[min, max]`` (either bound may be left out).

The same checks describe themselves in words (``describe``), so the text a user reads and the
test the code runs cannot drift apart.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, Literal, TypedDict, get_args

import numpy as np
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict, Field, model_validator

from neuroanimator.goals.terms import MAX_VALUE, finite_number, shown

CheckKind = Literal["angle", "abs", "distance", "norm", "orientation", "range"]
KINDS: tuple[str, ...] = get_args(CheckKind)


def _absent(value: object) -> bool:
    return value is None


class SuccessCheck(BaseModel):
    """One check of a success criterion, as a job states it and ``validate_checks`` accepted it.

    ``variables`` are state labels; ``target`` (one value per variable) overrides the job's target
    state; ``max`` bounds the measured value (for ``range`` also ``min``; either may be left out).
    Bounds and targets that are not set are left out of the JSON, as a job writes them.
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    check: CheckKind
    variables: list[str] = Field(min_length=1)
    max: float | None = Field(None, allow_inf_nan=False, exclude_if=_absent)
    min: float | None = Field(None, allow_inf_nan=False, exclude_if=_absent)
    target: list[float] | None = Field(None, exclude_if=_absent)

    @model_validator(mode="after")
    def _bounded(self) -> SuccessCheck:
        if self.check == "range" and self.min is None and self.max is None:
            raise ValueError("a range check needs min or max")
        if self.check != "range" and self.max is None:
            raise ValueError(f"max is required for a {self.check} check")
        return self

    @property
    def bound(self) -> float:
        """``max`` of a check of any kind but ``range`` (which requires it)."""
        assert self.max is not None, "checked on construction"
        return self.max


def _values(state: NDArray[np.float64], labels: Sequence[str], names: Sequence[str]) -> NDArray[np.float64]:
    return np.asarray([state[labels.index(n)] for n in names], dtype=np.float64)


def check_errors(
    check: SuccessCheck, final: NDArray[np.floating], target: NDArray[np.floating], labels: Sequence[str]
) -> tuple[bool, float]:
    """(passed, measured value) of one check on a final state (S,) against a target state (S,).

    The measured value is what is compared with the bound: the largest error, the distance, the
    norm or the rotation angle (for ``range``, the value furthest outside the range, else inside).
    """
    s = np.asarray(final, dtype=np.float64)
    names = check.variables
    x = _values(s, labels, names)
    tgt = (
        np.asarray(check.target, dtype=np.float64)
        if check.target is not None
        else _values(np.asarray(target, dtype=np.float64), labels, names)
    )
    kind = check.check
    if not np.all(np.isfinite(x)):
        return False, float("inf")
    if kind == "angle":
        err = np.abs((x - tgt + np.pi) % (2 * np.pi) - np.pi)
        value = float(err.max())
    elif kind == "abs":
        value = float(np.abs(x - tgt).max())
    elif kind == "distance":
        value = float(np.linalg.norm(x - tgt))
    elif kind == "norm":
        value = float(np.linalg.norm(x))
    elif kind == "orientation":
        q = x / np.linalg.norm(x)
        qd = tgt / np.linalg.norm(tgt)
        value = float(2.0 * np.arccos(min(1.0, abs(float(q @ qd)))))
    elif kind == "range":
        lo = -np.inf if check.min is None else check.min
        hi = np.inf if check.max is None else check.max
        ok = bool(np.all((x >= lo) & (x <= hi)))
        # report the worst value: the one furthest below min or above max
        value = float(x[np.argmax(np.maximum(lo - x, x - hi))])
        return ok, value
    else:  # validated before; an unknown kind is a programming error
        raise ValueError(f"check must be one of {KINDS}, got {kind!r}")
    return value <= check.bound, value


class CheckResult(TypedDict):
    """One check's outcome on a final state: what it requires (``describe_check``), whether it held,
    and the value measured (``check_errors``)."""

    check: str
    passed: bool
    value: float


def evaluate(
    checks: Sequence[SuccessCheck],
    final: NDArray[np.floating],
    target: NDArray[np.floating],
    labels: Sequence[str],
) -> tuple[bool, list[CheckResult]]:
    """Whether a final state (S,) meets every check, and each check's outcome for the report."""
    details: list[CheckResult] = []
    for c in checks:
        ok, value = check_errors(c, final, target, labels)
        details.append({"check": describe_check(c, target, labels), "passed": ok, "value": value})
    return all(d["passed"] for d in details) and bool(checks), details


def _fmt(v: float) -> str:
    return f"{v:.3g}"


def describe_check(
    check: SuccessCheck, target: Sequence[float] | NDArray[np.floating] | None, labels: Sequence[str]
) -> str:
    """One line of text that says what a check requires."""
    names = check.variables
    if check.target is not None:
        tgt = [float(v) for v in check.target]
    elif target is not None:
        tgt = [float(target[labels.index(n)]) for n in names]
    else:
        tgt = []
    kind = check.check
    joined = ", ".join(names)
    if kind == "range":
        lo, hi = check.min, check.max
        if lo is not None and hi is not None:
            return f"{joined} in [{_fmt(lo)}, {_fmt(hi)}]"
        return f"{joined} >= {_fmt(lo)}" if lo is not None else f"{joined} <= {_fmt(check.bound)}"
    limit = _fmt(check.bound)
    if kind == "angle":
        pairs = ", ".join(f"{n} = {_fmt(t)}" for n, t in zip(names, tgt, strict=True))
        return f"{pairs} within {limit} rad (angles wrapped)"
    if kind == "abs":
        pairs = ", ".join(f"{n} = {_fmt(t)}" for n, t in zip(names, tgt, strict=True))
        return f"{pairs} within {limit}"
    if kind == "distance":
        return f"({joined}) within {limit} of ({', '.join(_fmt(t) for t in tgt)})"
    if kind == "norm":
        return f"|({joined})| <= {limit}"
    deg = np.degrees(check.bound)
    return f"orientation ({joined}) within {limit} rad ({deg:.0f} deg) of the target"


def describe(
    checks: Sequence[SuccessCheck],
    target: Sequence[float] | NDArray[np.floating] | None,
    labels: Sequence[str],
) -> str:
    """The whole criterion in words: every check must hold on the final state."""
    if not checks:
        return "no success criterion"
    return "at the end: " + "; ".join(describe_check(c, target, labels) for c in checks)


def validate_checks(checks: Any, labels: Sequence[str]) -> list[tuple[str, str]]:
    """Problems with a list of checks (empty when it is valid): (where, what) pairs, ``where`` the
    path of the offending field below the list (``[0].target[1]``), ``what`` the expected and the got."""
    problems: list[tuple[str, str]] = []
    if not isinstance(checks, list):
        return [("", f"must be a list of checks, got {type(checks).__name__}")]
    for i, c in enumerate(checks):
        where = f"[{i}]"
        if not isinstance(c, dict):
            problems.append((where, f"must be an object, got {type(c).__name__}"))
            continue
        kind = c.get("check")
        if kind not in KINDS:
            problems.append((f"{where}.check", f"must be one of {list(KINDS)}, got {shown(kind)}"))
            continue
        unknown_keys = sorted(set(c) - set(SuccessCheck.model_fields))
        if unknown_keys:
            problems.append(
                (where, f"unknown keys {unknown_keys}; a check takes {sorted(SuccessCheck.model_fields)}")
            )
        names = c.get("variables")
        if not isinstance(names, list) or not names or not all(isinstance(n, str) for n in names):
            problems.append(
                (f"{where}.variables", f"must be a non-empty list of state labels, got {shown(names)}")
            )
            continue
        if len(names) > len(labels):
            problems.append(
                (f"{where}.variables", f"must name at most {len(labels)} state labels, got {len(names)}")
            )
            continue
        unknown = [n for n in names if n not in labels]
        if unknown:
            problems.append(
                (f"{where}.variables", f"unknown state labels {shown(unknown)}; labels are {list(labels)}")
            )
        if kind == "orientation" and len(names) != 4:
            problems.append((f"{where}.variables", f"must name 4 quaternion components, got {len(names)}"))
        if "target" in c:
            target = c["target"]
            if not isinstance(target, list) or len(target) != len(names):
                problems.append((f"{where}.target", f"must be {len(names)} numbers, got {shown(target)}"))
            else:
                for j, v in enumerate(target):
                    if not _finite(v):
                        problems.append(
                            (
                                f"{where}.target[{j}]",
                                f"must be a number of magnitude <= {MAX_VALUE:g}, got {shown(v)}",
                            )
                        )
                        break
        bounds = [b for b in ("min", "max") if b in c]
        if kind != "range" and "max" not in c:
            problems.append((f"{where}.max", f"is required for a {kind} check"))
        if kind == "range" and not bounds:
            problems.append((where, "needs min or max"))
        for b in bounds:
            if not _finite(c[b]):
                problems.append(
                    (f"{where}.{b}", f"must be a number of magnitude <= {MAX_VALUE:g}, got {shown(c[b])}")
                )
        if (
            kind == "range"
            and len(bounds) == 2
            and _finite(c["min"])
            and _finite(c["max"])
            and finite_number(c["min"]) > finite_number(c["max"])  # type: ignore[operator]
        ):
            problems.append(
                (f"{where}.min", f"must be <= max, got min={shown(c['min'])} > max={shown(c['max'])}")
            )
    return problems


def _finite(value: Any) -> bool:
    """A finite JSON number of magnitude at most ``terms.MAX_VALUE`` (a huge integer is not)."""
    v = finite_number(value)
    return v is not None and abs(v) <= MAX_VALUE
