"""Input checks of the stepping core: lengths, float32, and the one in-range check of every transport.

A model's inputs are one row of U controls then F forces (as the batcher stacks them and binary frames
carry them). ``InputRange`` holds the range the emulator was trained over (the manifest's ``low`` ..
``high`` of each control and force) and clips to it. Bounds and inputs are compared in float32, the
type the emulator takes: the manifest's own ``high`` (32.4 for the lander's main jet, which is
32.400001525878906 in float32) is in range whether it arrives as a JSON number or as float32 bytes.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from neuroanimator.core.manifest import ControlInput
from neuroanimator.core.model_spec import ForceInput
from services.emulator.bounds import RowBounds
from services.emulator.errors import BadInput

_F32_MAX = float(np.finfo(np.float32).max)
_EMPTY = np.zeros(0, np.float32)
_EMPTY.flags.writeable = False  # shared by every model without controls or forces

RowLabel = Callable[[int], tuple[str, str]]
"""Row index -> (field prefix, message suffix) naming the row in an error, e.g. ("items[3].",
" of session 'r0-x'")."""


def check_vector(field: str, values: Sequence[float], width: int, what: str) -> NDArray[np.float32]:
    """A (width,) float32 vector from finite JSON numbers; ``BadInput`` on a wrong length or a value
    beyond float32's range."""
    if len(values) != width:
        raise BadInput(
            f"{field} must have {width} values for {what}, got {len(values)}",
            code="wrong_length",
            field=field,
            expected=width,
            got=len(values),
        )
    if width == 0:
        return _EMPTY
    arr = np.asarray(values, dtype=np.float64)
    # beyond float32's range (JSON allows it) or NaN/Inf: refused
    bad = np.flatnonzero(~(np.abs(arr) <= _F32_MAX))
    if bad.size:
        i = int(bad[0])
        raise BadInput(
            f"{field}[{i}] = {values[i]!r} is beyond the float32 range",
            code="not_finite",
            field=f"{field}[{i}]",
            expected="a finite float32",
            got=values[i],
        )
    return arr.astype(np.float32)


@dataclass(slots=True)
class CheckedInputs:
    """One session's inputs ready to step: the (U+F,) float32 ``row`` (controls then forces, in range)
    and the indices of the controls and forces that were clipped to get there."""

    row: NDArray[np.float32]
    num_controls: int
    clipped_controls: list[int] = field(default_factory=list)
    clipped_forces: list[int] = field(default_factory=list)

    @property
    def clipped(self) -> bool:
        return bool(self.clipped_controls or self.clipped_forces)

    @property
    def controls(self) -> NDArray[np.float32]:
        return self.row[: self.num_controls]

    @property
    def forces(self) -> NDArray[np.float32]:
        return self.row[self.num_controls :]


class InputRange:
    """The trained range of a model's (U+F,) inputs, controls then forces, as float32 bounds."""

    def __init__(self, controls: Sequence[ControlInput], forces: Sequence[ForceInput]) -> None:
        self.num_controls = len(controls)
        self.num_forces = len(forces)
        self.width = self.num_controls + self.num_forces
        both = [(c.low, c.high) for c in controls] + [(f.low, f.high) for f in forces]
        bounds = np.array(both, np.float64).reshape(-1, 2).astype(np.float32)
        self.low: NDArray[np.float32] = bounds[:, 0].copy()
        self.high: NDArray[np.float32] = bounds[:, 1].copy()
        self.rows = RowBounds(self.low, self.high)
        # the same float32 bounds as Python floats, for ``fits``
        self.bounds = list(zip(self.low.tolist(), self.high.tolist(), strict=True))
        # (U,) zero moved into each control's range: what stands in for the controls a session's policy
        # sets in the batcher (``policy_rows``), so that nothing is reported clipped for them
        self.neutral_controls = np.clip(0.0, self.low, self.high)[: self.num_controls].astype(np.float32)

    def fits(self, values: Sequence[float]) -> bool:
        """Every value in range (NaN is not): the check of one short row of Python floats (a binary
        websocket frame unpacked; numpy costs more than it saves on a few values)."""
        return all(lo <= v <= hi for (lo, hi), v in zip(self.bounds, values, strict=True))

    def input_name(self, j: int) -> str:
        """The name of value ``j`` of a row: ``controls[j]`` or ``forces[j - U]``."""
        return f"controls[{j}]" if j < self.num_controls else f"forces[{j - self.num_controls}]"

    def clip(
        self, rows: NDArray[np.float32], label: RowLabel | None = None
    ) -> tuple[NDArray[np.float32], NDArray[np.bool_] | None]:
        """Rows (N, U+F) of float32 inputs clipped to the range, and the (N, U+F) mask of the values that
        were clipped (None when none was). ``BadInput`` naming the first NaN or Inf (``label`` names
        its row)."""
        # the common case in two comparisons: every value in range (NaN fails both, and is named below)
        if self.rows.contain(rows):
            return rows, None
        bad = ~np.isfinite(rows)
        if bad.any():
            i, j = (int(v) for v in np.argwhere(bad)[0])
            prefix, suffix = label(i) if label is not None else ("", "")
            name = f"{prefix}{self.input_name(j)}"
            raise BadInput(
                f"{name}{suffix} is {float(rows[i, j])!r}; inputs must be finite float32",
                code="not_finite",
                field=name,
                expected="a finite float32",
                got=float(rows[i, j]),
            )
        low, high = self.rows.repeated(len(rows))
        mask = (rows < low) | (rows > high)
        return np.clip(rows, low, high).astype(np.float32), mask

    def check_row(self, values: NDArray[np.float32]) -> CheckedInputs:
        """A (U+F,) float32 row (a binary frame's; its length already checked)."""
        rows, mask = self.clip(values[None])
        if mask is None:
            return CheckedInputs(values, self.num_controls)
        idx = np.flatnonzero(mask[0])
        u = self.num_controls
        return CheckedInputs(rows[0], u, idx[idx < u].tolist(), (idx[idx >= u] - u).tolist())

    def check_lists(
        self, controls: Sequence[float], forces: Sequence[float], what: str, prefix: str = ""
    ) -> CheckedInputs:
        """Controls (U) and forces (F) as JSON numbers; ``prefix`` goes before the field names."""
        u = check_vector(f"{prefix}controls", controls, self.num_controls, what)
        f = check_vector(f"{prefix}forces", forces, self.num_forces, what)
        row = u if not self.num_forces else f if not self.num_controls else np.concatenate([u, f])
        return self.check_row(row)
