"""bench/errors_by_time.py on the catalog's ball: the one-step error by time since a run's start."""

from __future__ import annotations

import itertools

import pytest

from tests.helpers import run_bench


def test_the_error_is_split_by_time_since_the_start() -> None:
    lines, r = run_bench("bench/errors_by_time.py", "ball", "--runs", "16", "--seconds", "1.5")
    assert r["model"] == "ball" and r["runs"] == 16 and r["one_step_rel_error"] > 0
    steps, edges = r["super_steps"], [(b["from_s"], b["to_s"]) for b in r["bins"]]
    assert edges[0][0] == 0 and edges[-1][1] == pytest.approx(1.5)  # the bins tile the runs
    assert all(a[1] == pytest.approx(b[0]) for a, b in itertools.pairwise(edges))
    # the bins' errors, weighted by their super-steps, give the whole runs' error
    step_s = edges[-1][1] / steps
    whole = sum(b["one_step_rel_error"] * (b["to_s"] - b["from_s"]) / step_s for b in r["bins"]) / steps
    assert whole == pytest.approx(r["one_step_rel_error"], rel=1e-4)
    assert any(line.startswith("| 0.00-") for line in lines)
