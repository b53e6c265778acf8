"""State layouts: the one truth about what each number of a state vector means.

A state vector ``s`` (shape ``(S,)``, or ``(B, S)`` batched) is a concatenation of named *groups*.
Each group has a *kind* that says how it behaves under the model's symmetries (thesis 4.3.3):

- ``position``: a world position of the model's root (2 or 3 values); translated and rotated.
- ``quaternion``: a world orientation ``[w, x, y, z]``; rotated with quaternion algebra.
- ``local_quaternion``: an orientation relative to a parent body (ball joint); left alone.
- ``world_vector``: a vector in world coordinates (2 or 3 values, e.g. linear velocity); rotated.
- ``local_vector``: a vector already in the body frame (e.g. MuJoCo's free-joint angular velocity).
- ``heading``: the yaw angle of a planar root (1 value); it *defines* the frame, so it is shifted.
- ``angle``: a joint angle (hinge); left alone.
- ``scalar``: anything else; left alone.

Every group also names where it lives in MuJoCo's ``qpos``/``qvel`` arrays, so that states can be
read from and written to MuJoCo without any model-specific code.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from dataclasses import asdict, dataclass, field
from typing import Literal

GroupKind = Literal[
    "position",
    "quaternion",
    "local_quaternion",
    "world_vector",
    "local_vector",
    "heading",
    "angle",
    "scalar",
]
GROUP_KINDS: tuple[str, ...] = (
    "position",
    "quaternion",
    "local_quaternion",
    "world_vector",
    "local_vector",
    "heading",
    "angle",
    "scalar",
)
_SIZES: dict[str, tuple[int, ...]] = {
    "position": (2, 3),
    "quaternion": (4,),
    "local_quaternion": (4,),
    "world_vector": (2, 3),
    "heading": (1,),
}


@dataclass(frozen=True)
class StateGroup:
    """One named group of state variables.

    ``source`` is ``"qpos"`` or ``"qvel"`` and ``address`` the first index in that MuJoCo array.
    """

    name: str
    kind: GroupKind
    size: int
    source: Literal["qpos", "qvel"]
    address: int
    labels: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        if self.kind not in GROUP_KINDS:
            raise ValueError(f"group {self.name!r}: kind must be one of {GROUP_KINDS}, got {self.kind!r}")
        allowed = _SIZES.get(self.kind)
        if allowed is not None and self.size not in allowed:
            raise ValueError(
                f"group {self.name!r} of kind {self.kind} must have {allowed} values, got {self.size}"
            )
        if self.size < 1:
            raise ValueError(f"group {self.name!r} must have at least one value, got {self.size}")
        if self.source not in ("qpos", "qvel"):
            raise ValueError(f"group {self.name!r}: source must be 'qpos' or 'qvel', got {self.source!r}")
        if self.address < 0:
            raise ValueError(f"group {self.name!r}: address must be >= 0, got {self.address}")
        if self.labels and len(self.labels) != self.size:
            raise ValueError(f"group {self.name!r}: {len(self.labels)} labels for {self.size} values")


@dataclass(frozen=True)
class StateLayout:
    """An ordered list of groups; the state vector is their concatenation."""

    groups: tuple[StateGroup, ...]
    offsets: tuple[int, ...] = field(init=False)

    def __post_init__(self) -> None:
        names = [g.name for g in self.groups]
        if len(set(names)) != len(names):
            raise ValueError(f"state group names must be unique, got {names}")
        offsets, at = [], 0
        for g in self.groups:
            offsets.append(at)
            at += g.size
        object.__setattr__(self, "offsets", tuple(offsets))
        self._check_frame()

    def _check_frame(self) -> None:
        roots = [g for g in self.groups if g.kind == "position"]
        if len(roots) > 1:
            raise ValueError("a layout may have at most one root position group (kind 'position')")
        frames = [g for g in self.groups if g.kind in ("quaternion", "heading")]
        if len(frames) > 1:
            raise ValueError(
                "a layout may have at most one root orientation (kind 'quaternion' or 'heading')"
            )

    @property
    def size(self) -> int:
        return sum(g.size for g in self.groups)

    def __iter__(self) -> Iterator[StateGroup]:
        return iter(self.groups)

    def slice_of(self, name: str) -> slice:
        """The slice of the state vector that holds group ``name``."""
        for g, off in zip(self.groups, self.offsets, strict=True):
            if g.name == name:
                return slice(off, off + g.size)
        raise KeyError(f"no state group named {name!r}; groups are {[g.name for g in self.groups]}")

    def group_slices(self) -> Iterator[tuple[StateGroup, slice]]:
        for g, off in zip(self.groups, self.offsets, strict=True):
            yield g, slice(off, off + g.size)

    def find(self, *kinds: str) -> StateGroup | None:
        for g in self.groups:
            if g.kind in kinds:
                return g
        return None

    def labels(self) -> list[str]:
        """A readable name for every state variable, in order."""
        out: list[str] = []
        for g in self.groups:
            if g.labels:
                out.extend(f"{g.name}.{lab}" for lab in g.labels)
            elif g.size == 1:
                out.append(g.name)
            else:
                out.extend(f"{g.name}[{i}]" for i in range(g.size))
        return out

    def to_dict(self) -> list[dict[str, object]]:
        return [dict(asdict(g), offset=off) for g, off in zip(self.groups, self.offsets, strict=True)]

    @classmethod
    def from_dict(cls, items: Sequence[dict[str, object]]) -> StateLayout:
        groups = []
        for it in items:
            groups.append(
                StateGroup(
                    name=str(it["name"]),
                    kind=it["kind"],  # type: ignore[arg-type]
                    size=int(it["size"]),  # type: ignore[call-overload]
                    source=it["source"],  # type: ignore[arg-type]
                    address=int(it["address"]),  # type: ignore[call-overload]
                    labels=tuple(str(x) for x in it.get("labels", ()) or ()),  # type: ignore[attr-defined]
                )
            )
        return cls(tuple(groups))
