"""The policy registry, read side: ``<root>/policies/<model>/<name>/<version>/`` (torch-free).

Each policy has a ``latest`` pointer file beside its versions. Like emulators, policies are read from
the committed defaults and the data directory together (``registry.Roots``) and written only to the
data directory (``control.policy_store``).
"""

from __future__ import annotations

from pathlib import Path

from pydantic import ValidationError

from neuroanimator.artifacts.registry import LATEST, POLICIES_DIR, ArtifactError, Root, folders, is_name
from neuroanimator.core.policy_manifest import PolicyManifest

POLICY_FILE = "policy.json"
POLICY_ONNX = "policy.onnx"
POLICY_WEIGHTS = "policy.pt"


class PolicyError(LookupError):
    """No such policy, version or readable manifest."""


def policy_dirs(root: Root, model: str, name: str) -> list[Path]:
    """The folders that may hold a model's policy, the data directory's first."""
    if not (is_name(model) and is_name(name)):
        return []
    return [f / POLICIES_DIR / model / name for f in folders(root)]


def resolve_policy(root: Root, model: str, name: str, version: str | None = None) -> Path:
    """The folder of a policy's version (``latest`` when None); ``PolicyError`` naming what is missing."""
    if version is not None and not is_name(version):
        raise PolicyError(f"policy version {version!r} is not a plain name")
    for d in policy_dirs(root, model, name):
        want = version
        if want is None:
            pointer = d / LATEST
            if not pointer.is_file():
                continue
            want = pointer.read_text().strip()
        if (d / want / POLICY_FILE).is_file():
            return d / want
    what = f"version {version!r} of policy" if version else "policy"
    raise PolicyError(f"{what} {name!r} for model {model!r} not found")


def read_policy(path: Path) -> PolicyManifest:
    try:
        return PolicyManifest.model_validate_json((path / POLICY_FILE).read_text())
    except (OSError, ValidationError) as e:
        raise PolicyError(f"policy manifest at {path.name} unreadable: {e}") from e


def list_policies(root: Root, model: str | None = None) -> list[PolicyManifest]:
    """The latest version of every policy (of ``model``, or of all), sorted by model and name; the data
    directory's shadows a default of the same name."""
    found: dict[tuple[str, str], PolicyManifest] = {}
    for folder in reversed(folders(root)):  # defaults first, then the data directory over them
        base = folder / POLICIES_DIR
        if not base.is_dir():
            continue
        for mdir in sorted(base.iterdir()):
            if not is_name(mdir.name) or (model is not None and mdir.name != model) or not mdir.is_dir():
                continue
            for pdir in sorted(mdir.iterdir()):
                pointer = pdir / LATEST
                if not pointer.is_file():
                    continue
                try:
                    found[(mdir.name, pdir.name)] = read_policy(pdir / pointer.read_text().strip())
                except PolicyError:
                    continue
    return [found[k] for k in sorted(found)]


__all__ = ["POLICIES_DIR", "ArtifactError", "PolicyError", "list_policies", "read_policy", "resolve_policy"]
