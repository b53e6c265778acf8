"""bench/contact_errors.py on the catalog's ball: the held-out error split by contact in the super-step."""

from __future__ import annotations

import pytest

from tests.helpers import run_bench


def test_the_error_is_split_by_contact_and_by_output() -> None:
    lines, r = run_bench("bench/contact_errors.py", "ball", "--examples", "1000")
    assert r["model"] == "ball" and r["examples"] == 1000 and r["one_step_rel_error"] > 0
    kinds = {row["kind"]: row for row in r["kinds"]}
    assert set(kinds) == {"none", "always", "switch"}
    assert sum(row["examples_share"] for row in kinds.values()) == pytest.approx(1.0)
    assert sum(row["error_share"] for row in kinds.values()) == pytest.approx(1.0)
    # the ball bounces, rolls and flies: every kind occurs, and a touchdown inside a super-step (a kink)
    # is the hardest to emulate
    assert all(row["examples_share"] > 0.01 for row in kinds.values())
    assert kinds["switch"]["rel_error_within"] > kinds["none"]["rel_error_within"]
    # the shares of the kinds, weighted back, give the whole error
    whole = sum(
        row["rel_error_within"] * row["examples_share"] for row in kinds.values() if row["examples_share"]
    )
    assert whole == pytest.approx(r["one_step_rel_error"], rel=1e-4)
    assert sum(r["outputs"].values()) == pytest.approx(1.0, rel=1e-4)
    assert any(line.startswith("| switch |") for line in lines)
