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

from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass, field
from typing import Literal, get_args

from pydantic import BaseModel, ConfigDict, Field, model_validator

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
GROUP_KINDS: tuple[str, ...] = get_args(GroupKind)
QUATERNION_KINDS: tuple[GroupKind, ...] = ("quaternion", "local_quaternion")
_SIZES: dict[str, tuple[int, ...]] = {
    "position": (2, 3),
    "quaternion": (4,),
    "local_quaternion": (4,),
    "world_vector": (2, 3),
    "heading": (1,),
}


StateSource = Literal["qpos", "qvel", "act"]
STATE_SOURCES: tuple[str, ...] = get_args(StateSource)


class StateGroup(BaseModel):
    """One named group of state variables: what its numbers mean and where MuJoCo keeps them.

    ``source`` is ``"qpos"``, ``"qvel"`` or ``"act"`` (the activations of actuators with their own
    dynamics: filters, muscles) and ``address`` the first index in that MuJoCo array;
    ``labels`` (one per value, or none) name the values for people. The physics modules, the model
    spec, the manifest and the wire contract all use this one type.
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    name: str
    kind: GroupKind
    size: int = Field(ge=1)
    source: StateSource
    address: int = Field(ge=0)
    labels: tuple[str, ...] = ()

    @model_validator(mode="before")
    @classmethod
    def _name_the_group(cls, data: object) -> object:
        """Check kind, size and labels first, so that the message names the group."""
        if not isinstance(data, dict):
            return data
        name, kind, size = data.get("name"), data.get("kind"), data.get("size")
        if kind not in GROUP_KINDS:
            raise ValueError(f"group {name!r}: kind must be one of {GROUP_KINDS}, got {kind!r}")
        if data.get("source") not in STATE_SOURCES:
            raise ValueError(
                f"group {name!r}: source must be one of {STATE_SOURCES}, got {data.get('source')!r}"
            )
        address = data.get("address")
        if isinstance(address, int) and address < 0:
            raise ValueError(f"group {name!r}: address must be >= 0, got {address}")
        if isinstance(size, int):
            if size < 1:
                raise ValueError(f"group {name!r} must have at least one value, got {size}")
            allowed = _SIZES.get(kind)
            if allowed is not None and size not in allowed:
                raise ValueError(f"group {name!r} of kind {kind} must have {allowed} values, got {size}")
            labels = data.get("labels") or ()
            if labels and len(labels) != size:
                raise ValueError(f"group {name!r}: {len(labels)} labels for {size} values")
        return data


class LayoutGroup(StateGroup):
    """A group at its place in a state vector: ``state[offset:offset+size]``; quaternions are
    ``[w, x, y, z]``. This is how manifests and the services' answers list a layout."""

    offset: int = Field(ge=0)


def labels_of(groups: Iterable[StateGroup]) -> list[str]:
    """A readable name for every variable of ``groups``, in the order given: ``name.label`` where the
    group names its values, ``name`` for a group of one, else ``name[i]``."""
    out: list[str] = []
    for g in groups:
        if g.labels:
            out.extend(f"{g.name}.{lab}" for lab in g.labels)
        elif g.size == 1:
            out.append(g.name)
        else:
            out.extend(f"{g.name}[{i}]" for i in range(g.size))
    return out


def heading_columns(groups: Iterable[LayoutGroup]) -> list[int]:
    """The state columns of ``heading`` groups (at most one): reported wrapped to [-π, π)
    (``quaternion.wrap_angle``). Only the
    heading is: it defines the emulator's frame, so its turns are invisible to the emulator, while a
    hinge's angle may be limited or sprung, where a turn of 2π is a different state."""
    return [g.offset for g in groups if g.kind == "heading"]


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

    @classmethod
    def of(cls, groups: Sequence[StateGroup]) -> StateLayout:
        """The layout of these groups, in order. Placed groups (``LayoutGroup``) must sit where the
        sizes before them put them."""
        layout = cls(tuple(StateGroup(**g.model_dump(exclude={"offset"})) for g in groups))
        for g, off in zip(groups, layout.offsets, strict=True):
            if isinstance(g, LayoutGroup) and g.offset != off:
                raise ValueError(
                    f"group {g.name!r} has offset {g.offset}, but the groups before it end at {off}"
                )
        return layout

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
        return labels_of(self.groups)

    def placed(self) -> list[LayoutGroup]:
        """Every group with its offset in the state vector (what a manifest lists)."""
        return [
            LayoutGroup(**g.model_dump(), offset=off)
            for g, off in zip(self.groups, self.offsets, strict=True)
        ]
