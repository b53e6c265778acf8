"""The trainer's folders are absolute once read: a training runs in a staging folder of its own, where
a relative ``DATA_DIR`` would name another place (the trainer started apart, as the
README says, from the repository root, failed every training so)."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from services.trainer.settings import Settings


def test_relative_folders_are_made_absolute(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(tmp_path)
    s = Settings(artifacts_dir=Path("artifacts"), data_dir=Path("data"))
    assert (s.artifacts_dir, s.data_dir) == (tmp_path / "artifacts", tmp_path / "data")
    assert s.uploads().is_absolute() and s.staging().is_absolute()
    assert s.uploads() == tmp_path / "data" / ".trainer" / "uploads"
    monkeypatch.setenv("WORK_DIR", "work")
    assert Settings().work() == tmp_path / "work"
    assert os.path.isabs(Settings(work_dir=Path("~/x")).work())
