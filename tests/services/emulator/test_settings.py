"""The service's settings come from the environment."""

from __future__ import annotations

import pytest

from services.emulator.settings import Settings


def test_settings_from_environment(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("MAX_BATCH", "17")
    monkeypatch.setenv("MAX_WAIT_MS", "2")
    monkeypatch.setenv("REPLICA_ID", "east1")
    s = Settings()
    assert (s.max_batch, s.max_wait_ms, s.replica_id, s.api_keys) == (17, 2.0, "east1", "")
