"""Drivers: a model's own closed-loop controller, run beside its emulator.

Some models are driven by a controller rather than by a person: the runner's 29 controls are the
joint targets of its running controller, which no client could sensibly set by hand. Such a model's
spec names a driver (``ModelSpec.driver``); the emulator service runs it for a session that asks, so
that every super-step the driver reads the emulated state and sets the controls, and the client sets
only the driver's parameters (the runner's target speed) and the force inputs (a push). The emulator
then emulates the closed loop, as the controller on MuJoCo produced its training data.

A driver is stateful (the runner's controller has a phase: stance, flight, which leg): one instance
per session, and one more for a MuJoCo shadow of it.

Shapes: S = state size, U = controls.
"""

from __future__ import annotations

import importlib
import math
from collections.abc import Mapping
from typing import TYPE_CHECKING, Protocol

import numpy as np
from numpy.typing import NDArray

from neuroanimator.core.model_spec import DriverSpec

if TYPE_CHECKING:
    from neuroanimator.sim.model import PhysicalModel


class DriverError(ValueError):
    """A driver asked for that the model does not have, or parameters outside its ranges."""


class Driver(Protocol):
    """One running instance of a model's controller."""

    def start(self) -> NDArray[np.float64]:
        """(S,) the state the driven motion starts from (the runner: a running stride at the target speed)."""
        ...

    def configure(self, params: Mapping[str, float]) -> None:
        """New parameters (checked by ``check_params``); the controller's phase carries on."""
        ...

    def act(self, state: NDArray[np.floating]) -> NDArray[np.float64]:
        """(S,) the state at the start of a super-step -> (U,) the controls for that super-step."""
        ...


def check_params(spec: DriverSpec | None, model: str, given: Mapping[str, float]) -> dict[str, float]:
    """The driver's full parameters: ``given`` over the defaults. ``DriverError`` naming the problem:
    a model without a driver, an unknown name, a value that is not finite or outside its range."""
    if spec is None:
        raise DriverError(f"model {model!r} has no driver: its controls come from the client")
    known = {p.name: p for p in spec.params}
    out = {p.name: p.default for p in spec.params}
    for name, value in given.items():
        param = known.get(name)
        if param is None:
            raise DriverError(
                f"driver {spec.name!r} of model {model!r} has no parameter {name!r} (it has: {sorted(known)})"
            )
        v = float(value)
        if not math.isfinite(v) or not param.low <= v <= param.high:
            raise DriverError(
                f"driver parameter {name!r} must be in [{param.low}, {param.high}] {param.unit}".rstrip()
                + f", got {value}"
            )
        out[name] = v
    return out


def load_driver(
    spec: DriverSpec, physical: PhysicalModel, substeps: int, params: Mapping[str, float]
) -> Driver:
    """A new instance of the model's driver with these (checked) parameters."""
    module_name, _, function = spec.factory.partition(":")
    if not module_name.startswith("neuroanimator."):  # the spec's pattern says so too: only our own code
        raise DriverError(f"driver {spec.name!r}: factory {spec.factory!r} is not in this package")
    factory = getattr(importlib.import_module(module_name), function)
    driver: Driver = factory(physical, substeps, dict(params))
    return driver
