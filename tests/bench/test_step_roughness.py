"""bench/step_roughness.py: a smooth super-step's second difference falls as r⁴, a contact's jumps do not."""

from __future__ import annotations

import importlib.util
import subprocess
import sys
from pathlib import Path

import pytest

from tests.helpers import ROOT, run_bench


def test_a_pendulum_is_smooth_at_every_scale() -> None:
    lines, r = run_bench(
        "bench/step_roughness.py",
        "pendulum-passive",
        "--substeps",
        "50",
        "--examples",
        "200",
        "--like",
        "20000",
    )
    assert (
        r["model"] == "pendulum-passive" and r["substeps"] == 50 and r["super_step_s"] == pytest.approx(0.5)
    )
    assert [row["r"] for row in r["scales"]] == [1e-4, 3e-4, 1e-3, 3e-3]
    # a smooth map's second difference is quadratic in the move: its square grows as r⁴
    assert all(e == pytest.approx(4.0, abs=0.3) for e in r["exponents"])
    assert r["scales"][-1]["roughness"] < 1e-8
    assert any(line.startswith("| 0.0001 |") for line in lines)


def test_the_hoppers_floor_contact_jumps_within_tiny_moves() -> None:
    # found, not imported: importing dm_control's suite sets up a renderer the test does not need
    spec = importlib.util.find_spec("dm_control")
    assert spec is not None and spec.origin is not None
    hopper = Path(spec.origin).parent / "suite" / "hopper.xml"
    _, r = run_bench(
        "bench/step_roughness.py",
        str(hopper),
        "--substeps",
        "10",
        "--examples",
        "300",
        "--scales",
        "1e-4,1e-3",
    )
    (exponent,) = r["exponents"]
    # a contact that starts one physical step earlier or later: far from the pendulum's r⁴
    assert exponent < 1.5
    # moves of a ten-thousandth of the spread already change a share of the variance near the 0.01 bar
    assert r["scales"][0]["roughness"] > 1e-4


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["no-such-model", "--substeps", "10"], "neither a catalog model"),
        (["ball", "--substeps", "0"], "--substeps must be positive"),
        (["ball", "--substeps", "10", "--scales", "a,b"], "--scales must be comma-separated numbers"),
        (["ball", "--substeps", "10", "--scales", "0,1e-3"], "--scales must be positive"),
    ],
)
def test_bad_arguments_are_named(args: list[str], message: str) -> None:
    out = subprocess.run(
        [sys.executable, "bench/step_roughness.py", *args],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert out.returncode != 0 and message in out.stderr
