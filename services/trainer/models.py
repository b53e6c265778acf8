"""Uploaded models in the artifact registry: their names, owners, sizes, export, publication and deletion.

A name belongs to the key that first uploaded a model under it: ``claim`` makes the model's folder
with only its owner file (``services.common.tenancy``), atomically (a folder renamed into place), when
the training is queued. The folder is not listed as a model until a version is exported into it
(``export``: the version and its assets are copied in beside, then renamed into place, then the
``latest`` pointers name it), so the emulator and controller services see a new model or version
whole or not at all, and a failed or cancelled first training gives its name back (``release``). The
same key's later uploads under the name add versions; another key's are refused (409), as are names of
models that were not uploaded (the committed catalog's, or trained with ``neuro train``). Uploads live
in the data directory (``registry.Roots.data``), never beside the committed defaults.

Deleting renames the model's folder out of the registry (a dot name, which no listing shows) before
removing it, so readers never see half a model, and its policies' folder with it; sessions already
running on it keep their emulator.
"""

from __future__ import annotations

import os
import shutil
import tempfile
import uuid
from dataclasses import replace
from pathlib import Path

from neuroanimator.artifacts import registry
from services.common import tenancy
from services.common.tenancy import Ownership


class NameTaken(Exception):
    """The name is another key's, or a model's that was not uploaded."""


class ExportError(Exception):
    """The trained version cannot be exported (its model was deleted or its name taken meanwhile)."""


def claim(roots: registry.Roots, name: str, owner: str) -> bool:
    """Make ``name`` the owner's in the data directory: True when it is new, False when the owner's model
    gets a new version; ``NameTaken`` when it is not the owner's to use (a committed model's name too)."""
    problem = registry.name_problem(name)
    if problem is not None:
        raise NameTaken(f"{problem} (the form field name)")
    root = roots.data
    root.mkdir(parents=True, exist_ok=True)
    folder = root / name
    if not folder.exists() and not roots.read_only_has(name):
        tmp = Path(tempfile.mkdtemp(dir=root, prefix=".tmp-claim-"))
        tmp.chmod(0o755)
        tenancy.write(tmp.parent, tmp.name, Ownership.new(owner))
        try:
            os.rename(tmp, folder)  # fails when another request made the folder meanwhile
            return True
        except OSError:
            shutil.rmtree(tmp, ignore_errors=True)
    found = None if roots.read_only_has(name) else tenancy.read(root, name)
    if found is None or found.owner != owner:
        # the same words for the catalog's names and for other keys': whose it is stays theirs to know
        raise NameTaken(
            f"the name {name!r} is not available (it names a model that is not yours): choose another "
            "name (the form field name)"
        )
    return False


def release(root: Path, name: str, owner: str) -> None:
    """Give a claimed name back when nothing was exported under it (its first training failed; the
    caller knows that no other training of the owner's holds the name)."""
    folder = root / name
    found = tenancy.read(root, name)
    if found is None or found.owner != owner or registry.versions(root, name):
        return
    if (folder / registry.LATEST).exists():
        return
    _remove(root, name)


def _remove(root: Path, name: str) -> None:
    gone = root / f".deleted-{name}-{uuid.uuid4().hex[:8]}"
    os.rename(root / name, gone)
    shutil.rmtree(gone, ignore_errors=True)


def delete(root: Path, name: str) -> None:
    """Remove an uploaded model, every version of it and every policy learned for it (see the
    module's text): a policy names a version that is gone, and a later upload under the name, another
    key's perhaps, must not find the policies of the model it replaced."""
    _remove(root, name)
    if (root / registry.POLICIES_DIR / name).is_dir():
        _remove(root / registry.POLICIES_DIR, name)


def publish(root: Path, name: str) -> Ownership:
    """Make an uploaded model everybody's."""
    found = tenancy.read(root, name)
    assert found is not None
    published = replace(found, published=True)
    tenancy.write(root, name, published)
    return published


def uploaded(root: Path) -> list[str]:
    """Every uploaded model (a folder with an owner file), sorted; names being trained included."""
    if not root.is_dir():
        return []
    return sorted(
        p.name for p in root.iterdir() if registry.is_name(p.name) and (p / tenancy.OWNER_FILE).is_file()
    )


def owned(root: Path, owner: str) -> list[str]:
    """The models (and claimed names) of one owner."""
    return [
        m for m in uploaded(root) if (found := tenancy.read(root, m)) is not None and found.owner == owner
    ]


def size(root: Path, names: list[str]) -> int:
    return sum(registry.model_size(root, m) for m in names)


def readable(folder: Path) -> None:
    """Make a folder and its files readable by every user (the services may run as another user than
    the workers that write them; temporary files are made private)."""
    folder.chmod(0o755)
    for p in folder.iterdir():
        p.chmod(0o755 if p.is_dir() else 0o644)


def export(staging: Path, root: Path, name: str, owner: str) -> str:
    """Move the version trained into ``staging`` (a registry of this one model) into ``root``; returns
    its version. The model's folder must still be the owner's claim (``ExportError`` otherwise)."""
    found = tenancy.read(root, name)
    if found is None or found.owner != owner:
        raise ExportError(
            f"model {name!r} was deleted (or its name taken) while it trained; upload it again to train it"
        )
    version = registry.latest_version(staging, name)
    src, dst = staging / name, root / name
    manifest = registry.read_manifest(src / version)
    if (dst / version).exists():
        raise ExportError(f"model {name!r} already has a version {version!r}; train it again")
    if (src / registry.ASSETS_DIR).is_dir():  # by content: one already there is the same file
        (dst / registry.ASSETS_DIR).mkdir(exist_ok=True)
        for asset in (src / registry.ASSETS_DIR).iterdir():
            target = dst / registry.ASSETS_DIR / asset.name
            if not target.exists():
                fd, tmp = tempfile.mkstemp(dir=target.parent, prefix=".tmp-asset-")
                os.close(fd)
                shutil.copyfile(asset, tmp)
                os.chmod(tmp, 0o644)
                os.replace(tmp, target)
    tmp_version = Path(tempfile.mkdtemp(dir=dst, prefix=f".tmp-{version}-"))
    shutil.copytree(src / version, tmp_version, dirs_exist_ok=True)
    readable(tmp_version)
    os.rename(tmp_version, dst / version)
    plot = src / registry.PLOT_FILE
    if plot.is_file():
        shutil.copyfile(plot, dst / registry.PLOT_FILE)
    registry.write_pointer(dst, registry.pointer_name(manifest.substeps), version)
    registry.write_pointer(dst, registry.pointer_name(), version)
    return version
