"""State layouts: offsets, validation and round trips."""

from __future__ import annotations

import json

import pytest

from neuroanimator.core.state import GROUP_KINDS, LayoutGroup, StateGroup, StateLayout


def group(
    name: str, kind: str, size: int, source: str, address: int, labels: tuple[str, ...] = ()
) -> StateGroup:
    return StateGroup.model_validate(
        {"name": name, "kind": kind, "size": size, "source": source, "address": address, "labels": labels}
    )


@pytest.fixture
def layout() -> StateLayout:
    return StateLayout(
        (
            group("pos", "position", 3, "qpos", 0, ("x", "y", "z")),
            group("orient", "quaternion", 4, "qpos", 3),
            group("vel", "world_vector", 3, "qvel", 0),
            group("spin", "local_vector", 3, "qvel", 3),
            group("hinge", "angle", 1, "qpos", 7),
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
        group("wobble", "spinor", 2, "qpos", 0)


@pytest.mark.parametrize(
    ("kind", "size"),
    [("quaternion", 3), ("local_quaternion", 5), ("position", 1), ("world_vector", 4), ("heading", 2)],
)
def test_bad_size_for_kind_raises_naming_the_group(kind: str, size: int) -> None:
    with pytest.raises(ValueError, match="'badgroup'"):
        group("badgroup", kind, size, "qpos", 0)


def test_empty_group_raises_naming_the_group() -> None:
    with pytest.raises(ValueError, match="'empty'"):
        group("empty", "scalar", 0, "qvel", 0)


def test_label_count_mismatch_raises_naming_the_group() -> None:
    with pytest.raises(ValueError, match="'rates'"):
        group("rates", "scalar", 3, "qvel", 0, ("a", "b"))


def test_duplicate_group_names_raise() -> None:
    g = group("a", "scalar", 1, "qpos", 0)
    with pytest.raises(ValueError, match="unique"):
        StateLayout((g, group("a", "angle", 1, "qpos", 1)))


def test_two_root_positions_raise() -> None:
    with pytest.raises(ValueError, match="position"):
        StateLayout((group("p1", "position", 3, "qpos", 0), group("p2", "position", 3, "qpos", 3)))


def test_two_root_orientations_raise() -> None:
    with pytest.raises(ValueError, match="orientation"):
        StateLayout((group("q", "quaternion", 4, "qpos", 0), group("h", "heading", 1, "qpos", 4)))


def test_placed_groups_carry_their_offsets_and_round_trip(layout: StateLayout) -> None:
    placed = layout.placed()
    assert [g.offset for g in placed] == list(layout.offsets)
    assert all(isinstance(g, LayoutGroup) for g in placed)
    assert StateLayout.of(placed) == layout


def test_round_trip_through_json(layout: StateLayout) -> None:
    text = json.dumps([g.model_dump(mode="json") for g in layout.placed()])
    assert StateLayout.of([LayoutGroup.model_validate(g) for g in json.loads(text)]) == layout


def test_a_placed_group_at_the_wrong_offset_is_refused(layout: StateLayout) -> None:
    placed = layout.placed()
    placed[1] = placed[1].model_copy(update={"offset": 4})
    with pytest.raises(ValueError, match="'orient' has offset 4"):
        StateLayout.of(placed)


def test_groups_are_typed_values_with_a_closed_set_of_kinds() -> None:
    g = group("heading", "heading", 1, "qpos", 2)
    with pytest.raises(ValueError, match="frozen"):
        g.size = 2  # type: ignore[misc]
    with pytest.raises(ValueError, match="source"):
        group("heading", "heading", 1, "qacc", 2)
    with pytest.raises(ValueError, match="extra"):
        StateGroup.model_validate({**g.model_dump(), "colour": "red"})
    schema = LayoutGroup.model_json_schema()
    assert schema["properties"]["kind"]["enum"] == list(GROUP_KINDS)
