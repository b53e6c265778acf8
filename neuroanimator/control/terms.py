"""The objective-term catalogue as plain data: names, parameters, defaults and validation.

Torch-free, so ``validate_job`` can check a job's ``terms`` without loading PyTorch; the
differentiable implementations live in ``objectives.py`` under the same names. A term in a job is
a JSON object ``{"term": <name>, "weight": <w >= 0>, ...parameters}``; the objective is

    J = μ_u/2 Σ_k Σ_i (u_ki / r_i)²  +  μ_s/2 ‖W (s_K − s_d)‖²  +  Σ_terms weight · term

(eq. 5.3 plus the extra terms; r_i is the largest magnitude of control i's useful range, so every
control counts in units of its own range). State variables are named by their labels
(``StateLayout.labels()``) or by index.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

from neuroanimator.control.errors import JobSpecError

TERMS: dict[str, str] = {
    "final_state": "weight/2 ‖W (s_K − target)‖² on the final state; params: target (S), weights (S); "
    "defaults: the job's target_state and state_weights",
    "control_effort": "weight/2 Σ (u/r)² over the held controls of every super-step",
    "control_smoothness": "weight/2 Σ ((u_k − u_{k−1})/r)²: penalises jumps between super-steps",
    "final_velocity": "weight/2 ‖v_K‖² on the velocity variables at the end; params: variables "
    "(labels; default every qvel variable)",
    "forward_distance": "−weight · direction·(p_K − p_0): maximises the root's displacement along "
    "direction (default +x)",
    "stay_within_bounds": "weight/2 Σ_k (max(0, low − x_k)² + max(0, x_k − high)²): a soft box on one "
    "state variable over the whole trajectory; params: variable, low and/or high",
    "path_target": "weight/2 Σ_waypoints ‖W (s_k − target)‖²; params: waypoints [{step | time, target}], "
    "weights (S; default the job's)",
}


def _number(field: str, value: Any, *, low: float | None = None) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise JobSpecError(field, f"expected a finite number, got {value!r}")
    if low is not None and value < low:
        raise JobSpecError(field, f"expected a number >= {low}, got {value!r}")
    return float(value)


def vector(field: str, value: Any, size: int, what: str = "numbers") -> list[float]:
    """A list of ``size`` finite numbers, or JobSpecError naming the field, the expected and the got."""
    if not isinstance(value, list | tuple):
        raise JobSpecError(field, f"expected a list of {size} {what}, got {type(value).__name__}")
    if len(value) != size:
        raise JobSpecError(field, f"expected {size} {what}, got {len(value)}")
    out = []
    for i, v in enumerate(value):
        if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
            raise JobSpecError(field, f"expected {size} finite {what}, got {v!r} at index {i}")
        out.append(float(v))
    return out


def variable_index(field: str, name: Any, labels: Sequence[str]) -> int:
    """A state variable by label or index."""
    if isinstance(name, int) and not isinstance(name, bool) and 0 <= name < len(labels):
        return name
    if isinstance(name, str) and name in labels:
        return list(labels).index(name)
    raise JobSpecError(field, f"expected a state label (one of {list(labels)}) or an index, got {name!r}")


def normalize_terms(
    terms: Any,
    *,
    labels: Sequence[str],
    layout: Sequence[dict[str, Any]],
    target: list[float],
    weights: list[float],
    horizon: int,
    super_dt: float,
) -> list[dict[str, Any]]:
    """Validate a job's ``terms`` and return them with every default filled in.

    Variables become indices (``variables``/``variable``), waypoint times become super-step
    indices, and unknown names or parameters raise ``JobSpecError``.
    """
    if terms is None:
        return []
    if not isinstance(terms, list):
        raise JobSpecError("terms", f"expected a list of term objects, got {type(terms).__name__}")
    size = len(labels)
    out: list[dict[str, Any]] = []
    for i, t in enumerate(terms):
        at = f"terms[{i}]"
        if not isinstance(t, dict):
            raise JobSpecError(at, f"expected an object like {{'term': 'final_state'}}, got {t!r}")
        name = t.get("term")
        if name not in TERMS:
            raise JobSpecError(f"{at}.term", f"unknown term {name!r}; known terms are {sorted(TERMS)}")
        weight = _number(f"{at}.weight", t.get("weight", 1.0), low=0.0)
        norm: dict[str, Any] = {"term": name, "weight": weight}
        allowed = {"term", "weight"}
        if name == "final_state":
            allowed |= {"target", "weights"}
            norm["target"] = vector(f"{at}.target", t.get("target", target), size)
            norm["weights"] = vector(f"{at}.weights", t.get("weights", weights), size)
        elif name == "final_velocity":
            allowed |= {"variables"}
            default = [
                i
                for g in layout
                if g["source"] == "qvel"
                for i in range(int(g["offset"]), int(g["offset"]) + int(g["size"]))
            ]
            names = t.get("variables", default)
            if not isinstance(names, list) or not names:
                raise JobSpecError(
                    f"{at}.variables", f"expected a non-empty list of state labels, got {names!r}"
                )
            norm["variables"] = [variable_index(f"{at}.variables", n, labels) for n in names]
        elif name == "forward_distance":
            allowed |= {"direction"}
            root = next((g for g in layout if g["kind"] == "position"), None)
            if root is None:
                raise JobSpecError(
                    at, "forward_distance needs a model with a root position group; this one has none"
                )
            dim = int(root["size"])
            direction = vector(f"{at}.direction", t.get("direction", [1.0] + [0.0] * (dim - 1)), dim)
            length = math.sqrt(sum(d * d for d in direction))
            if length == 0.0:
                raise JobSpecError(f"{at}.direction", "expected a non-zero direction, got all zeros")
            norm["direction"] = [d / length for d in direction]
            norm["variables"] = list(range(int(root["offset"]), int(root["offset"]) + dim))
        elif name == "stay_within_bounds":
            allowed |= {"variable", "low", "high"}
            if "variable" not in t:
                raise JobSpecError(f"{at}.variable", "expected a state label, got nothing")
            norm["variable"] = variable_index(f"{at}.variable", t["variable"], labels)
            if "low" not in t and "high" not in t:
                raise JobSpecError(at, "expected low and/or high bounds, got neither")
            lo = _number(f"{at}.low", t["low"]) if "low" in t else None
            hi = _number(f"{at}.high", t["high"]) if "high" in t else None
            if lo is not None and hi is not None and lo > hi:
                raise JobSpecError(f"{at}.low", f"expected low <= high, got low={lo} > high={hi}")
            norm["low"], norm["high"] = lo, hi
        elif name == "path_target":
            allowed |= {"waypoints", "weights"}
            norm["weights"] = vector(f"{at}.weights", t.get("weights", weights), size)
            wps = t.get("waypoints")
            if not isinstance(wps, list) or not wps:
                raise JobSpecError(f"{at}.waypoints", f"expected a non-empty list of waypoints, got {wps!r}")
            norm["waypoints"] = []
            for j, wp in enumerate(wps):
                wat = f"{at}.waypoints[{j}]"
                if not isinstance(wp, dict):
                    raise JobSpecError(wat, f"expected an object {{step|time, target}}, got {wp!r}")
                if "step" in wp:
                    step = wp["step"]
                    if isinstance(step, bool) or not isinstance(step, int) or not 0 <= step <= horizon:
                        raise JobSpecError(
                            f"{wat}.step", f"expected an integer in [0, {horizon}], got {step!r}"
                        )
                elif "time" in wp:
                    time = _number(f"{wat}.time", wp["time"], low=0.0)
                    step = round(time / super_dt)
                    if step > horizon:
                        raise JobSpecError(
                            f"{wat}.time", f"expected a time in [0, {horizon * super_dt:g}] s, got {time:g}"
                        )
                else:
                    raise JobSpecError(
                        wat, "expected a step (super-step index) or a time (seconds), got neither"
                    )
                norm["waypoints"].append(
                    {"step": int(step), "target": vector(f"{wat}.target", wp.get("target"), size)}
                )
        extra = sorted(set(t) - allowed)
        if extra:
            raise JobSpecError(
                at, f"unknown parameters {extra} for term {name!r}; it takes {sorted(allowed)}"
            )
        out.append(norm)
    return out
