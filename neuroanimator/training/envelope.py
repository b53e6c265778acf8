"""The training envelope of an emulator: per state group, the range of the states it was trained on.

An emulator is trustworthy where it has seen data. ``training_envelope`` takes the states of the
training examples (their states and next states, (N, S)) and gives, per state group and value, the
smallest and largest value seen, widened by ``MARGIN`` of that range on each side; the manifest stores
it (``Manifest.envelope``) and the emulator service flags every step whose new state leaves it.

A value the emulator is indifferent to has no bounds (``None``): a root-position axis the physics is
translation-invariant along (the emulator never sees it; a root slide the same, ``Frame.slides``), a
heading its frame removes, a hinge angle
(it enters as sin and cos, so a joint that turned a full circle looks the same) and an orientation
quaternion (any attitude is one; what the emulator knows of attitudes shows in the other groups).
Imports neither torch nor MuJoCo.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from neuroanimator.core.manifest import EnvelopeGroup
from neuroanimator.core.state import QUATERNION_KINDS, StateLayout

if TYPE_CHECKING:
    from neuroanimator.sim.model import PhysicalModel
    from neuroanimator.sim.sampling import Examples

MARGIN = 0.1
"""How far the envelope reaches beyond the data, as a fraction of each value's range."""


def unbounded(
    layout: StateLayout, translate: Sequence[bool], rotate: bool, slides: Sequence[str] = ()
) -> NDArray[np.bool_]:
    """(S,) True for the values the emulator is indifferent to (see the module docstring), for a layout
    with these symmetries (``translate``: per root-position axis; ``rotate``: about the vertical;
    ``slides``: root slides' groups translated away)."""
    out = np.zeros(layout.size, bool)
    for g, sl in layout.group_slices():
        if g.name in slides:
            out[sl] = True
        elif g.kind == "position":
            out[sl] = list(translate) + [False] * (g.size - len(translate))
        elif g.kind == "angle" or g.kind in QUATERNION_KINDS or (g.kind == "heading" and rotate):
            out[sl] = True
    return out


def training_envelope(
    layout: StateLayout,
    states: NDArray[np.floating],
    translate: Sequence[bool],
    rotate: bool,
    margin: float = MARGIN,
    slides: Sequence[str] = (),
) -> list[EnvelopeGroup]:
    """The envelope of training states (N, S): per group, each value's range widened by ``margin``."""
    x = np.asarray(states, np.float64).reshape(-1, layout.size)
    if not len(x):
        raise ValueError("the envelope of no states is undefined")
    lo, hi = x.min(axis=0), x.max(axis=0)
    # the margin, and at least a float32 rounding error (a value constant in the data stays inside)
    pad = margin * (hi - lo) + 1e-6 * np.maximum(1.0, np.maximum(np.abs(lo), np.abs(hi)))
    lo, hi = lo - pad, hi + pad
    free = unbounded(layout, translate, rotate, slides)
    groups = []
    for g, sl in layout.group_slices():
        groups.append(
            EnvelopeGroup(
                group=g.name,
                low=[None if f else float(v) for v, f in zip(lo[sl], free[sl], strict=True)],
                high=[None if f else float(v) for v, f in zip(hi[sl], free[sl], strict=True)],
            )
        )
    return groups


def examples_envelope(model: PhysicalModel, data: Examples) -> list[EnvelopeGroup]:
    """The envelope of a model's training examples: their states and next states."""
    states = np.concatenate([data.states, data.next_states])
    fr = model.frame
    return training_envelope(model.layout, states, fr.translate, fr.rotate, slides=fr.slides)
