"""bench/upload_to_drive.py runs end to end at a tiny scale: the project's model folder uploaded as a zip
to a real trainer service and worker, trained a few epochs, then stepped in a real emulator service."""

from __future__ import annotations

import zipfile
from pathlib import Path

import pytest

from tests.helpers import ROOT, run_bench


def test_upload_to_first_drive_small(redis_url: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    folder = ROOT / "tests" / "data" / "tinybot"
    archive = tmp_path / "tinybot.zip"
    with zipfile.ZipFile(archive, "w") as z:
        for f in sorted(p for p in folder.rglob("*") if p.is_file()):
            z.write(f, f.relative_to(folder).as_posix())
    monkeypatch.setenv("REDIS_URL", redis_url)
    _, r = run_bench(
        "bench/upload_to_drive.py",
        *("--model", str(archive), "--entry", "robot.xml"),
        *("--examples", "300", "--epochs", "2", "--super-step", "10", "--keep", "--force"),
        timeout=240,
    )
    (row,) = r["models"]
    assert row["status"] == "succeeded", row
    assert row["substeps"] == 10 and row["examples"] == 300
    assert {"validating", "sampling", "training", "exporting"} <= set(row["phase_seconds"])
    assert 0 < row["validation_s"] < row["training_s"] <= row["first_drive_s"]
