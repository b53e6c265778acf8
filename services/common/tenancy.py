"""Who may see a model: uploaded models belong to the API key that uploaded them until an operator
publishes them.

A model uploaded through the trainer service has an owner file beside its versions,
``<data dir>/<model>/owner.json``: ``{"owner": "<key id>", "published": false, "uploaded": "<UTC
time>"}``. Every service that lists or serves models (the emulator's registry, the controller's jobs,
the trainer's model list) asks ``can_see`` for the caller of the request (``auth.CALLER``):

- a model without an owner file (the committed catalog's, one trained with ``neuro train``) is
  everybody's;
- a published model is everybody's;
- otherwise only its owner's key, and operators (``OPERATOR_KEYS``), see it; to any other key it
  does not exist (404 or "unknown model", never 403, and its name is in no list).

With API keys off there is no caller and every model is visible. The owner file is written before
the model's first ``latest`` pointer (``registry.list_models`` lists a model only once it has one), so
an uploaded model is never visible to everybody on its way in. Files are replaced atomically; readers
cache them per (path, modification time).
"""

from __future__ import annotations

import datetime as dt
import json
import os
import tempfile
from dataclasses import asdict, dataclass
from pathlib import Path

from neuroanimator.artifacts import registry
from services.common.auth import CALLER, OPERATOR

OWNER_FILE = "owner.json"


@dataclass(frozen=True)
class Ownership:
    """The owner file of an uploaded model."""

    owner: str  # the key id of the key that uploaded it (``public`` when keys were off)
    published: bool = False
    uploaded: str = ""  # UTC, ISO 8601

    @classmethod
    def new(cls, owner: str) -> Ownership:
        return cls(owner, False, dt.datetime.now(dt.UTC).isoformat(timespec="seconds"))


_cache: dict[Path, tuple[tuple[int, int], Ownership | None]] = {}


def read(root: registry.Root, model: str) -> Ownership | None:
    """The owner file of a model; None when it has none (everybody's) or it cannot be read."""
    path = root / model / OWNER_FILE
    try:
        st = path.stat()
    except OSError:
        return None
    mtime = (st.st_mtime_ns, st.st_ino)
    hit = _cache.get(path)
    if hit is not None and hit[0] == mtime:
        return hit[1]
    try:
        data = json.loads(path.read_text())
        found: Ownership | None = Ownership(
            owner=str(data["owner"]),
            published=bool(data.get("published", False)),
            uploaded=str(data.get("uploaded", "")),
        )
    except (OSError, ValueError, KeyError, TypeError):
        # unreadable: nobody but operators (a model is never shown to everybody by accident)
        found = Ownership(owner="", published=False)
    _cache[path] = (mtime, found)
    return found


def write(root: registry.Root, model: str, ownership: Ownership) -> None:
    """Write (or replace) a model's owner file, atomically; the model's folder is made if need be."""
    folder = root / model
    folder.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=folder, prefix=".tmp-owner-")
    os.fchmod(fd, 0o644)  # readable by the services, whichever user they run as
    with os.fdopen(fd, "w") as fh:
        json.dump(asdict(ownership), fh)
        fh.write("\n")
    os.replace(tmp, folder / OWNER_FILE)


def visible(found: Ownership | None, caller: str | None, operator: bool) -> bool:
    """Whether a model with this owner file is visible to ``caller`` (None: keys off, or the service
    itself)."""
    return found is None or found.published or caller is None or operator or found.owner == caller


def can_see(root: registry.Root, model: str) -> bool:
    """Whether the current request's caller sees ``model`` (``auth.CALLER``, ``auth.OPERATOR``)."""
    if CALLER.get() is None:
        return True
    return visible(read(root, model), CALLER.get(), OPERATOR.get())


def visible_models(root: registry.Root) -> list[str]:
    """The trained models the current request's caller sees, sorted."""
    return [m for m in registry.list_models(root) if can_see(root, m)]


def public_models(root: registry.Root) -> list[str]:
    """The trained models everybody sees (no owner file, or published), sorted."""
    out = []
    for m in registry.list_models(root):
        found = read(root, m)
        if found is None or found.published:
            out.append(m)
    return out
