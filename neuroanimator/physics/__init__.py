"""The physics catalog: every built-in system, each defined like a user's MJCF (``ModelSpec`` + MJCF)."""

from __future__ import annotations

from collections.abc import Callable
from functools import cache

from neuroanimator.physics import lander, pendulum, truck
from neuroanimator.physics.model import Frame, ModelError, PhysicalModel
from neuroanimator.physics.spec import ForceInput, InitialStates, ModelSpec

CATALOG: dict[str, Callable[[], PhysicalModel]] = {
    "pendulum-passive": pendulum.passive,
    "pendulum-active": pendulum.active,
    "pendulum-force": pendulum.force,
    "lander": lander.lander,
    "truck": truck.truck,
}


@cache
def get(name: str) -> PhysicalModel:
    """A catalog model by name; unknown names raise ``ModelError`` listing the known ones."""
    try:
        factory = CATALOG[name]
    except KeyError:
        raise ModelError(f"unknown model {name!r}; the catalog has {sorted(CATALOG)}") from None
    return factory()


__all__ = [
    "CATALOG",
    "ForceInput",
    "Frame",
    "InitialStates",
    "ModelError",
    "ModelSpec",
    "PhysicalModel",
    "get",
]
