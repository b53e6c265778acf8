"""The physics catalog: every built-in system, each defined like a user's MJCF (``ModelSpec`` + MJCF).

One module per physical system (``SYSTEMS``), with its MJCF beside it: the catalog models built from
it and the control tasks set on them (``TASKS``, collected by ``neuroanimator.catalog.tasks``).
Importing the catalog loads no MuJoCo (a model's factory does, when called), so its names and tasks
can be read by processes that never simulate: the controller API, ``make``, the stack launcher.
"""

from __future__ import annotations

from collections.abc import Callable
from functools import cache
from types import ModuleType
from typing import TYPE_CHECKING, Any

from neuroanimator.catalog import ball, dolphin, lander, pendulum, quadrotor, truck
from neuroanimator.catalog.runner import body as runner
from neuroanimator.core.model_spec import ForceInput, InitialStates, ModelSpec

if TYPE_CHECKING:
    from neuroanimator.sim.model import Frame, ModelError, PhysicalModel

SYSTEMS: tuple[ModuleType, ...] = (pendulum, lander, truck, dolphin, runner, quadrotor, ball)
CATALOG: dict[str, Callable[[], PhysicalModel]] = {
    "pendulum-passive": pendulum.passive,
    "pendulum-active": pendulum.active,
    "pendulum-force": pendulum.force,
    "lander": lander.lander,
    "truck": truck.truck,
    "dolphin": dolphin.dolphin,
    "runner": runner.runner,
    "quadrotor": quadrotor.quadrotor,
    "ball": ball.ball,
}
_FROM_MODEL = ("Frame", "ModelError", "PhysicalModel")  # names that need MuJoCo, loaded on first use


def __getattr__(name: str) -> Any:
    if name in _FROM_MODEL:
        from neuroanimator.sim import model

        return getattr(model, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


@cache
def get(name: str) -> PhysicalModel:
    """A catalog model by name; unknown names raise ``ModelError`` listing the known ones."""
    from neuroanimator.sim.model import ModelError

    try:
        factory = CATALOG[name]
    except KeyError:
        raise ModelError(f"unknown model {name!r}; the catalog has {sorted(CATALOG)}") from None
    return factory()


__all__ = [
    "CATALOG",
    "SYSTEMS",
    "ForceInput",
    "Frame",
    "InitialStates",
    "ModelError",
    "ModelSpec",
    "PhysicalModel",
    "get",
]
