"""What a training that died leaves behind, removed: ``reap(settings, store)``.

A training normally cleans up after itself when it ends (``execution._cleanup``). One whose process
was killed (the machine restarted, the worker was SIGKILLed in the middle of an export) cannot, and
would leave its upload and staging folders, a half-copied ``.tmp-…`` version in the registry, and a
claimed name without versions that counts against its key's quota. A training worker reaps them when
it starts and whenever it reaps expired leases:

- ``uploads/<id>`` and ``staging/<id>`` of trainings that ended (or that Redis no longer knows, once
  ``GRACE_S`` old: an upload being received has no record yet);
- ``.tmp-*`` and ``.deleted-*`` folders of the registry (an export or a delete in progress renames
  them within seconds) once ``GRACE_S`` old;
- an uploaded model's name with no version, whose owner has no training queued or running for it,
  once ``GRACE_S`` old.
"""

from __future__ import annotations

import contextlib
import logging
import shutil
import time
from pathlib import Path
from typing import Protocol

import redis

from neuroanimator.artifacts import registry
from services.common import tenancy
from services.common.jobs import FINAL, Keys
from services.trainer import models
from services.trainer.settings import Settings

log = logging.getLogger(__name__)
GRACE_S = 900.0


def _old(path: Path, now: float, grace: float) -> bool:
    try:
        return now - path.stat().st_mtime > grace
    except OSError:
        return False


class Trainings(Protocol):
    """What reaping reads of the trainer's store (``store.TrainingStore``, which calls ``reap``)."""

    r: redis.Redis
    keys: Keys

    def active(self, owner: str, model: str | None = None, but: str | None = None) -> int: ...


def _status(store: Trainings, job_id: str) -> str | None:
    raw = store.r.hget(store.keys.job(job_id), "status")
    return raw.decode() if isinstance(raw, bytes) else raw


def reap(s: Settings, store: Trainings, grace: float = GRACE_S) -> list[str]:
    """Remove the leftovers (see the module's text); what was removed, for the log."""
    now = time.time()
    removed: list[str] = []
    try:
        for folder in (s.uploads(), s.staging()):
            if not folder.is_dir():
                continue
            for p in folder.iterdir():
                status = _status(store, p.name)
                if (status is not None and status in FINAL) or (status is None and _old(p, now, grace)):
                    shutil.rmtree(p, ignore_errors=True)
                    removed.append(f"{folder.name}/{p.name}")
        root = s.data_dir
        if root.is_dir():
            for model_dir in [root, *(root / m for m in models.uploaded(root))]:
                for p in model_dir.iterdir():
                    if p.name.startswith((".tmp-", ".deleted-")) and _old(p, now, grace):
                        shutil.rmtree(p, ignore_errors=True) if p.is_dir() else p.unlink(missing_ok=True)
                        removed.append(f"{model_dir.name}/{p.name}")
            for name in models.uploaded(root):
                found = tenancy.read(root, name)
                claimed = root / name / tenancy.OWNER_FILE  # written when the name was claimed
                if found is None or registry.versions(root, name) or not _old(claimed, now, grace):
                    continue
                if store.active(found.owner, name):
                    continue
                with contextlib.suppress(OSError):
                    models.release(root, name, found.owner)
                    removed.append(f"the name {name} (no version)")
    except (OSError, redis.RedisError) as exc:
        log.warning("leftovers not reaped", extra={"error": str(exc)})
    if removed:
        log.warning("removed what dead trainings left behind", extra={"removed": removed})
    return removed
