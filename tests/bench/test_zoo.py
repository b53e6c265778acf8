"""The zoo's smallest models through the whole pipeline (bench/zoo.py --quick): dm_control's files as
the package ships them (includes and all), one made by its own function, and a model refused."""

from __future__ import annotations

from tests.helpers import run_bench


def test_quick_zoo_trains_shipped_and_made_models_and_reports_each() -> None:
    lines, result = run_bench("bench/zoo.py", "--models", "pendulum,lqr", "--quick", "--no-catalog")
    rows = {r["model"]: r for r in result["rows"]}
    assert set(rows) == {"pendulum", "lqr"}
    for name, row in rows.items():
        assert row["accepted"], f"{name}: {row['reason']}"  # --quick forces the tiny emulators through
        assert row["substeps"] in (50, 25, 10) and row["state_size"] > 0
        assert row["one_step"] is not None and row["linear"] is not None
        assert row["finite"] is True
        assert row["reason"].startswith(f"n={row['substeps']}: ")  # the trainer said why
    assert rows["lqr"]["state_size"] == 4  # two bodies on slides, built by dm_control's own function
    assert rows["pendulum"]["joint_rad_5s"] is not None  # errors in physical units
    assert any(line.startswith("| pendulum | dm_control | yes |") for line in lines)
