"""bench/dolphin_regularizer.py runs end to end on a tiny dolphin emulator (real MuJoCo, real training)."""

from __future__ import annotations

import dataclasses
from pathlib import Path

from neuroanimator import catalog
from neuroanimator.artifacts import store as artifacts
from neuroanimator.training.hierarchy import train_hierarchy
from tests.helpers import run_bench
from tests.test_hierarchy import TINY


def test_dolphin_regularizer_small(tmp_path: Path) -> None:
    dolphin = catalog.get("dolphin")
    artifacts.save(
        tmp_path, dolphin, train_hierarchy(dolphin, dataclasses.replace(TINY, regularizer_steps=0))
    )
    png = tmp_path / "fig.png"
    lines, r = run_bench(
        "bench/dolphin_regularizer.py",
        *("--artifacts", str(tmp_path), "--seconds", "12", "--periods", "4", "--png", str(png), "--no-speed"),
        timeout=240,
    )
    # no regulariser stored: the bench takes the catalog's with 5 steps, and compares with none
    assert r["regularizer_steps"] == 5 and r["speed"] is None
    (stroke,) = r["strokes"]
    assert stroke["period_s"] == 4
    assert stroke["mujoco"]["ed_mean"] > 0 and stroke["mujoco"]["distance_m"] > 0
    for key in ("with", "without"):
        assert stroke[key]["com_error_m"] >= 0 and "ed_growth" in stroke[key]
    assert png.stat().st_size > 10_000
    assert any(line.startswith("| 4 s | emulator, regularised |") for line in lines)
