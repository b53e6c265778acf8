"""Success criteria: plain-data checks on a final state, evaluated with numpy (no torch).

A criterion is a list of checks, each a JSON-able dict naming state variables by their labels
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
from typing import Any

import numpy as np
from numpy.typing import NDArray

KINDS = ("angle", "abs", "distance", "norm", "orientation", "range")


def _values(state: NDArray[np.float64], labels: Sequence[str], names: Sequence[str]) -> NDArray[np.float64]:
    return np.asarray([state[labels.index(n)] for n in names], dtype=np.float64)


def check_errors(
    check: dict[str, Any], final: NDArray[np.floating], target: NDArray[np.floating], labels: Sequence[str]
) -> tuple[bool, float]:
    """(passed, measured value) of one check on a final state (S,) against a target state (S,).

    The measured value is what is compared with the bound: the largest error, the distance, the
    norm or the rotation angle (for ``range``, the value furthest outside the range, else inside).
    """
    s = np.asarray(final, dtype=np.float64)
    names = list(check["variables"])
    x = _values(s, labels, names)
    tgt = (
        np.asarray(check["target"], dtype=np.float64)
        if "target" in check
        else _values(np.asarray(target, dtype=np.float64), labels, names)
    )
    kind = check["check"]
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
        lo = check.get("min", -np.inf)
        hi = check.get("max", np.inf)
        ok = bool(np.all((x >= lo) & (x <= hi)))
        # report the worst value: the one furthest below min or above max
        value = float(x[np.argmax(np.maximum(lo - x, x - hi))])
        return ok, value
    else:  # validated before; an unknown kind is a programming error
        raise ValueError(f"check must be one of {KINDS}, got {kind!r}")
    return value <= float(check["max"]), value


def evaluate(
    checks: Sequence[dict[str, Any]],
    final: NDArray[np.floating],
    target: NDArray[np.floating],
    labels: Sequence[str],
) -> tuple[bool, list[dict[str, Any]]]:
    """Whether a final state (S,) meets every check, and each check's outcome for the report."""
    details = []
    for c in checks:
        ok, value = check_errors(c, final, target, labels)
        details.append({"check": describe_check(c, target, labels), "passed": ok, "value": value})
    return all(d["passed"] for d in details) and bool(checks), details


def _fmt(v: float) -> str:
    return f"{v:.3g}"


def describe_check(
    check: dict[str, Any], target: Sequence[float] | NDArray[np.floating] | None, labels: Sequence[str]
) -> str:
    """One line of text that says what a check requires."""
    names = list(check["variables"])
    if "target" in check:
        tgt = [float(v) for v in check["target"]]
    elif target is not None:
        tgt = [float(target[labels.index(n)]) for n in names]
    else:
        tgt = []
    kind = check["check"]
    joined = ", ".join(names)
    if kind == "angle":
        pairs = ", ".join(f"{n} = {_fmt(t)}" for n, t in zip(names, tgt, strict=True))
        return f"{pairs} within {_fmt(check['max'])} rad (angles wrapped)"
    if kind == "abs":
        pairs = ", ".join(f"{n} = {_fmt(t)}" for n, t in zip(names, tgt, strict=True))
        return f"{pairs} within {_fmt(check['max'])}"
    if kind == "distance":
        return f"({joined}) within {_fmt(check['max'])} of ({', '.join(_fmt(t) for t in tgt)})"
    if kind == "norm":
        return f"|({joined})| <= {_fmt(check['max'])}"
    if kind == "orientation":
        deg = np.degrees(float(check["max"]))
        return f"orientation ({joined}) within {_fmt(check['max'])} rad ({deg:.0f} deg) of the target"
    lo, hi = check.get("min"), check.get("max")
    if lo is not None and hi is not None:
        return f"{joined} in [{_fmt(lo)}, {_fmt(hi)}]"
    if lo is not None:
        return f"{joined} >= {_fmt(lo)}"
    return f"{joined} <= {_fmt(float(check['max']))}"


def describe(
    checks: Sequence[dict[str, Any]],
    target: Sequence[float] | NDArray[np.floating] | None,
    labels: Sequence[str],
) -> str:
    """The whole criterion in words: every check must hold on the final state."""
    if not checks:
        return "no success criterion"
    return "at the end: " + "; ".join(describe_check(c, target, labels) for c in checks)


def validate_checks(checks: Any, labels: Sequence[str]) -> list[str]:
    """Problems with a list of checks (empty when it is valid); each names the check and the field."""
    problems: list[str] = []
    if not isinstance(checks, list):
        return [f"must be a list of checks, got {type(checks).__name__}"]
    for i, c in enumerate(checks):
        where = f"[{i}]"
        if not isinstance(c, dict):
            problems.append(f"{where} must be an object, got {type(c).__name__}")
            continue
        kind = c.get("check")
        if kind not in KINDS:
            problems.append(f"{where}.check must be one of {list(KINDS)}, got {kind!r}")
            continue
        names = c.get("variables")
        if not isinstance(names, list) or not names or not all(isinstance(n, str) for n in names):
            problems.append(f"{where}.variables must be a non-empty list of state labels, got {names!r}")
            continue
        unknown = [n for n in names if n not in labels]
        if unknown:
            problems.append(f"{where}.variables: unknown state labels {unknown}; labels are {list(labels)}")
        if kind == "orientation" and len(names) != 4:
            problems.append(f"{where}.variables must name 4 quaternion components, got {len(names)}")
        if "target" in c and (
            not isinstance(c["target"], list)
            or len(c["target"]) != len(names)
            or not np.all(np.isfinite(np.asarray(c["target"], dtype=float)))
        ):
            problems.append(f"{where}.target must be {len(names)} finite numbers, got {c['target']!r}")
        bounds = [b for b in ("min", "max") if b in c]
        if kind != "range" and "max" not in c:
            problems.append(f"{where}.max is required for a {kind} check")
        if kind == "range" and not bounds:
            problems.append(f"{where} needs min or max")
        for b in bounds:
            v = c[b]
            if isinstance(v, bool) or not isinstance(v, int | float) or not np.isfinite(v):
                problems.append(f"{where}.{b} must be a finite number, got {v!r}")
    return problems
