"""bench/hierarchy_errors.py runs end to end at a tiny scale on the dolphin (real MuJoCo, real training)."""

from __future__ import annotations

from tests.helpers import run_bench


def test_hierarchy_errors_small() -> None:
    lines, r = run_bench(
        "bench/hierarchy_errors.py",
        *("--examples", "120", "--test", "40", "--hidden", "4", "--seconds", "0.5"),
        *("--networks", "global,segment2", "--top", "3"),
        timeout=240,
    )
    assert [n["network"] for n in r["networks"]] == ["global", "segment2"]
    for n in r["networks"]:
        assert n["one_step_rel_error"] >= 0 and n["linear_baseline_rel_error"] >= 0
        assert len(n["worst_groups"]) == 3
        shares = [g["share"] for g in n["worst_groups"]]
        assert shares == sorted(shares, reverse=True) and 0 < sum(shares) <= n["one_step_rel_error"] + 1e-9
    # every kind of the dolphin's state groups gets a full-state linear row
    assert set(r["full_state_linear"]) == {
        "scalar:pos",
        "scalar:vel",
        "scalar:pitch",
        "scalar:rate",
    }
    for v in r["full_state_linear"].values():
        assert 0 < v["worst_1pct_share"] <= v["worst_5pct_share"] <= 1
    assert any(line.startswith("| segment2 |") for line in lines)
