"""The service process keeps PyTorch out, and its settings come from the environment."""

from __future__ import annotations

import subprocess
import sys

import pytest

from services.emulator.settings import Settings


def test_service_does_not_import_torch() -> None:
    code = (
        "import sys\n"
        "from services.emulator.app import create_app\n"
        "from services.emulator.settings import Settings\n"
        "create_app(Settings(artifacts_dir='artifacts'))\n"
        "import services.emulator.__main__\n"
        "assert 'torch' not in sys.modules, 'torch was imported'\n"
    )
    subprocess.run([sys.executable, "-c", code], check=True, timeout=120)


def test_settings_from_environment(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("MAX_BATCH", "17")
    monkeypatch.setenv("MAX_WAIT_MS", "2")
    monkeypatch.setenv("REPLICA_ID", "east1")
    s = Settings()
    assert (s.max_batch, s.max_wait_ms, s.replica_id, s.api_keys) == (17, 2.0, "east1", "")
