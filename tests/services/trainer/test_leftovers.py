"""What a training killed in the middle of its export leaves (its upload, its staging registry, a
half-copied ``.tmp-…`` version, a name claimed without versions) is reaped: nothing stays on disk, the
name and the key's quota are free again. A training that is still queued keeps everything."""

from __future__ import annotations

import os
import time
from collections.abc import Iterator

import pytest

from services.common import tenancy
from services.trainer import leftovers
from services.trainer.store import TrainingStore
from tests.services.trainer.trn import KEYS, TINY, TINYBOT, Trainer, auth, upload, zipped


@pytest.fixture(name="trn")
def trn_fixture(redis_url: str, tmp_path_factory: pytest.TempPathFactory) -> Iterator[Trainer]:
    t = Trainer(redis_url, tmp_path_factory.mktemp("trainer"), **KEYS)
    try:
        yield t
    finally:
        t.close()


def test_a_training_killed_during_export_leaves_nothing(trn: Trainer) -> None:
    api = trn.client()
    settings = trn.settings()
    store = TrainingStore(trn.r, settings)
    dead = upload(api, "tinybot.zip", zipped(TINYBOT), key="key-a", name="dies", **TINY)
    alive = upload(api, "tinybot.zip", zipped(TINYBOT), key="key-a", name="waits", **TINY)
    assert dead.status_code == alive.status_code == 202, (dead.text, alive.text)
    job = dead.json()["id"]
    # its worker started it, exported half a version, and was SIGKILLed: the reaper failed the training
    rec, _ = store.start(job, 1, "w-gone", 1)
    assert rec is not None
    staging = settings.staging() / job / "dies" / "v1"
    staging.mkdir(parents=True)
    (staging / "emulator.onnx").write_bytes(b"x" * 1000)
    half = trn.data / "dies" / ".tmp-v1-abc123"
    half.mkdir()
    (half / "emulator.onnx").write_bytes(b"x" * 1000)
    assert store.end(job, 1, "failed", "abandoned: worker w-gone stopped renewing the training's lease")
    old = time.time() - 2 * leftovers.GRACE_S
    os.utime(half, (old, old))
    os.utime(trn.data / "dies" / tenancy.OWNER_FILE, (old, old))
    assert api.get("/models", headers=auth("key-a")).json()["usage"]["models"] == 2

    removed = leftovers.reap(settings, store)
    assert not (settings.staging() / job).exists() and not (settings.uploads() / job).exists()
    assert not (trn.data / "dies").exists(), removed  # no .tmp version, no name without versions
    assert (settings.uploads() / alive.json()["id"]).is_dir() and (trn.data / "waits").is_dir()
    usage = api.get("/models", headers=auth("key-a")).json()["usage"]
    assert usage["models"] == 1 and usage["trainings"] == 1, usage
    # the name is free: another key may take it now
    assert upload(api, "tinybot.zip", zipped(TINYBOT), key="key-b", name="dies", **TINY).status_code == 202
