"""State layouts: offsets, validation and round trips."""

from __future__ import annotations

import json

import pytest

from neuroanimator.state import StateGroup, StateLayout


@pytest.fixture
def layout() -> StateLayout:
    return StateLayout(
        (
            StateGroup("pos", "position", 3, "qpos", 0, ("x", "y", "z")),
            StateGroup("orient", "quaternion", 4, "qpos", 3),
            StateGroup("vel", "world_vector", 3, "qvel", 0),
            StateGroup("spin", "local_vector", 3, "qvel", 3),
            StateGroup("hinge", "angle", 1, "qpos", 7),
        )
    )


def test_offsets_and_size(layout: StateLayout) -> None:
    assert layout.offsets == (0, 3, 7, 10, 13)
    assert layout.size == 14


def test_slices_cover_the_vector_in_order(layout: StateLayout) -> None:
    assert layout.slice_of("pos") == slice(0, 3)
    assert layout.slice_of("orient") == slice(3, 7)
    assert layout.slice_of("spin") == slice(10, 13)
    assert layout.slice_of("hinge") == slice(13, 14)
    covered = [i for _, sl in layout.group_slices() for i in range(sl.start, sl.stop)]
    assert covered == list(range(layout.size))


def test_unknown_group_name_raises_key_error(layout: StateLayout) -> None:
    with pytest.raises(KeyError, match="nope"):
        layout.slice_of("nope")


def test_find_returns_first_group_of_kind(layout: StateLayout) -> None:
    found = layout.find("quaternion", "heading")
    assert found is not None and found.name == "orient"
    assert layout.find("heading") is None


def test_labels_name_every_variable(layout: StateLayout) -> None:
    labels = layout.labels()
    assert len(labels) == layout.size
    assert labels[:4] == ["pos.x", "pos.y", "pos.z", "orient[0]"]
    assert labels[-1] == "hinge"


def test_bad_kind_raises_naming_the_group() -> None:
    with pytest.raises(ValueError, match="'wobble'"):
        StateGroup("wobble", "spinor", 2, "qpos", 0)  # type: ignore[arg-type]


@pytest.mark.parametrize(
    ("kind", "size"),
    [("quaternion", 3), ("local_quaternion", 5), ("position", 1), ("world_vector", 4), ("heading", 2)],
)
def test_bad_size_for_kind_raises_naming_the_group(kind: str, size: int) -> None:
    with pytest.raises(ValueError, match="'badgroup'"):
        StateGroup("badgroup", kind, size, "qpos", 0)  # type: ignore[arg-type]


def test_empty_group_raises_naming_the_group() -> None:
    with pytest.raises(ValueError, match="'empty'"):
        StateGroup("empty", "scalar", 0, "qvel", 0)


def test_label_count_mismatch_raises_naming_the_group() -> None:
    with pytest.raises(ValueError, match="'rates'"):
        StateGroup("rates", "scalar", 3, "qvel", 0, ("a", "b"))


def test_duplicate_group_names_raise() -> None:
    g = StateGroup("a", "scalar", 1, "qpos", 0)
    with pytest.raises(ValueError, match="unique"):
        StateLayout((g, StateGroup("a", "angle", 1, "qpos", 1)))


def test_two_root_positions_raise() -> None:
    with pytest.raises(ValueError, match="position"):
        StateLayout((StateGroup("p1", "position", 3, "qpos", 0), StateGroup("p2", "position", 3, "qpos", 3)))


def test_two_root_orientations_raise() -> None:
    with pytest.raises(ValueError, match="orientation"):
        StateLayout((StateGroup("q", "quaternion", 4, "qpos", 0), StateGroup("h", "heading", 1, "qpos", 4)))


def test_to_dict_from_dict_round_trip(layout: StateLayout) -> None:
    items = layout.to_dict()
    assert [it["offset"] for it in items] == list(layout.offsets)
    assert StateLayout.from_dict(items) == layout


def test_round_trip_through_json(layout: StateLayout) -> None:
    assert StateLayout.from_dict(json.loads(json.dumps(layout.to_dict()))) == layout
