"""The artifact registry, read side: find, list and read artifacts without importing torch.

A registry is a folder ``<root>/<model>/<version>/``. A version folder holds ``emulator.onnx`` (the
whole step), ``weights.pt`` (the torch emulator's state dict), ``linear_baseline.npy``, ``model.xml``
(the MJCF it was trained on) and ``manifest.json`` (a ``Manifest``), and, once measured,
``eval.json`` and ``bench.json`` (``VersionEval``, ``VersionBench``). Pointer files in the model's
folder name versions: ``latest`` (the model's default super-step, or the first trained) and
``latest-n<N>`` for each super-step N. Versions are named ``n<N>-<UTC time>`` (``version_name``).
The files the MJCF names (meshes, textures, height fields, skins) are stored once per model by their
content in ``<root>/<model>/assets/`` (``<sha256><extension>``, listed in each manifest's ``assets``),
shared by the versions that use them: a version folder and that folder are all a model needs. A
version fine-tuned for a policy (``Manifest.tuned``) is named by no pointer: the policy names it.

A service reads two kinds of registry at once (``Roots``): the committed defaults (the catalog's
emulators, read-only, ``DEFAULTS_DIR``) and a data directory where uploads and a user's own trainings
go (``default_data_dir``: ``$NEUROANIMATOR_DATA_DIR``, else ``$XDG_DATA_HOME/neuroanimator``, else
``~/.local/share/neuroanimator``). Every function here takes either one folder or ``Roots``.

Model and version names are plain names (``NAME``), never paths. Writing versions is
``neuroanimator.artifacts.store`` (it needs torch); this module writes only measurement results. It imports
neither torch nor MuJoCo nor ONNX Runtime (``load_physical_model`` imports MuJoCo when called).
"""

from __future__ import annotations

import datetime as dt
import hashlib
import json
import os
import re
import tempfile
from pathlib import Path
from typing import TYPE_CHECKING, Literal, TypeAlias, TypeVar

from pydantic import BaseModel, ValidationError

from neuroanimator.core.manifest import Manifest, ManifestError, parse_manifest
from neuroanimator.core.results import (
    ModelBench,
    ModelEval,
    VersionBench,
    VersionEval,
    summarize_bench,
    summarize_eval,
)

if TYPE_CHECKING:
    from neuroanimator.sim.model import PhysicalModel

NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]*$")
"""What a model or version name may be: a folder name, never a path."""
POLICIES_DIR = "policies"
"""The policy registry's folder, beside the models in a registry: no model may take its name (a model
named so would hold every policy, and deleting it would delete them)."""
LATEST = "latest"
MANIFEST_FILE = "manifest.json"
ONNX_FILE = "emulator.onnx"
WEIGHTS_FILE = "weights.pt"
LINEAR_FILE = "linear_baseline.npy"
MJCF_FILE = "model.xml"
EVAL_FILE = "eval.json"
BENCH_FILE = "bench.json"
PLOT_FILE = "rollout_error.png"  # in the model's folder: the rollout curves of every n
ASSETS_DIR = "assets"  # in the model's folder: the MJCF's files, by content, shared by the versions
VERSION_FILES = (ONNX_FILE, WEIGHTS_FILE, LINEAR_FILE, MJCF_FILE, MANIFEST_FILE)
"""What every version folder holds."""
_SUBSTEPS_POINTER = re.compile(r"latest-n(\d+)")

DEFAULTS_DIR = Path(__file__).resolve().parents[2] / "artifacts"
"""The committed defaults: the catalog's trained emulators, shipped with the source (read-only)."""
DATA_DIR_ENV = "NEUROANIMATOR_DATA_DIR"

Missing = Literal["model", "version", "substeps", "manifest", "results"]
_R = TypeVar("_R", bound=BaseModel)


class ArtifactError(LookupError):
    """An artifact that does not exist or cannot be read. ``what`` says which part of the request
    failed (``model``, ``version``, ``substeps``, ``manifest`` or ``results``); the message names it."""

    def __init__(self, what: Missing, message: str) -> None:
        super().__init__(message)
        self.what: Missing = what

    def __reduce__(self) -> tuple[type[ArtifactError], tuple[Missing, str]]:
        # raised in a worker process (a seed loading its emulator), it reaches the parent whole
        return type(self), (self.what, str(self))


def default_data_dir() -> Path:
    """Where uploads and a user's trainings go unless told otherwise: ``$NEUROANIMATOR_DATA_DIR``, else
    ``$XDG_DATA_HOME/neuroanimator``, else ``~/.local/share/neuroanimator`` (never the source tree)."""
    if env := os.environ.get(DATA_DIR_ENV):
        return Path(env).expanduser().absolute()
    xdg = os.environ.get("XDG_DATA_HOME")
    base = Path(xdg).expanduser() if xdg else Path.home() / ".local" / "share"
    return (base / "neuroanimator").absolute()


class Roots:
    """Several registries read as one: a writable data directory, then read-only ones (the committed
    defaults). ``roots / model`` is the model's folder in the first registry where it has a ``latest``
    version (else the first where the folder exists; else in the data directory, where a new model is
    written), so code written for one folder reads all of them. A model lives whole in one registry:
    versions are not merged across registries. The data directory comes first so that a user's own
    training of a catalog model (``neuro train lander``) is the one they then use; uploads cannot take a
    name the read-only registries have (``read_only_has``).
    """

    def __init__(self, data: Path, *read_only: Path) -> None:
        self.data = Path(data)
        self.read_only = tuple(Path(p) for p in read_only if Path(p) != Path(data))
        self.folders = (self.data, *self.read_only)

    def __truediv__(self, model: str) -> Path:
        for folder in self.folders:
            if (folder / model / LATEST).is_file():
                return folder / model
        for folder in self.folders:
            if (folder / model).is_dir():
                return folder / model
        return self.data / model

    def __repr__(self) -> str:
        return f"Roots({', '.join(map(str, self.folders))})"

    def __eq__(self, other: object) -> bool:
        return isinstance(other, Roots) and other.folders == self.folders

    def __hash__(self) -> int:
        return hash(self.folders)

    def is_dir(self) -> bool:
        return any(f.is_dir() for f in self.folders)

    def read_only_has(self, model: str) -> bool:
        """Whether a read-only registry (the committed defaults) has a folder named ``model``."""
        return any((f / model).exists() for f in self.read_only)

    @classmethod
    def default(cls, data: Path | None = None, defaults: Path = DEFAULTS_DIR) -> Roots:
        """The data directory (``default_data_dir`` unless given) over the committed defaults."""
        return cls(data if data is not None else default_data_dir(), defaults)


Root: TypeAlias = "Path | Roots"
"""One registry folder, or several read as one."""


def folders(root: Root) -> tuple[Path, ...]:
    """The registry folders ``root`` reads, first first."""
    return root.folders if isinstance(root, Roots) else (Path(root),)


def writable(root: Root) -> Path:
    """The folder new models and uploads are written to."""
    return root.data if isinstance(root, Roots) else Path(root)


def is_name(text: str) -> bool:
    """Whether ``text`` can name a model or a version (a plain folder name)."""
    return bool(NAME.match(text))


def name_problem(model: str) -> str | None:
    """Why ``model`` cannot name a model in a registry (None: it can)."""
    if not is_name(model):
        return f"model name {model!r} cannot name a folder: use letters, digits, '.', '_' or '-'"
    if model == POLICIES_DIR:
        return f"model name {model!r} is the policy registry's folder: choose another name"
    return None


def pointer_name(substeps: int | None = None) -> str:
    """The pointer file to a model's current version: ``latest``, or ``latest-n<N>`` for super-step N."""
    return LATEST if substeps is None else f"{LATEST}-n{substeps}"


def version_name(substeps: int, when: dt.datetime, repeat: int = 1) -> str:
    """The name of a new version: ``n<N>-<YYYYmmddTHHMMSS>`` (UTC), ``-<repeat>`` added after the first."""
    stamp = when.astimezone(dt.UTC).strftime("%Y%m%dT%H%M%S")
    return f"n{substeps}-{stamp}" if repeat == 1 else f"n{substeps}-{stamp}-{repeat}"


def write_pointer(model_dir: Path, name: str, version: str) -> None:
    """Make pointer ``name`` (``pointer_name``) of a model's folder name ``version``, atomically."""
    fd, tmp = tempfile.mkstemp(dir=model_dir, prefix=".tmp-ptr-")
    os.fchmod(fd, 0o644)  # readable by the services, whichever user they run as
    with os.fdopen(fd, "w") as fh:
        fh.write(version + "\n")
    os.replace(tmp, model_dir / name)


# ---------------------------------------------------------------------------- listing
def list_models(root: Root) -> list[str]:
    """The models with a ``latest`` version, sorted."""
    found = {
        p.name
        for folder in folders(root)
        if folder.is_dir()
        for p in folder.iterdir()
        if name_problem(p.name) is None and root / p.name == p and (p / LATEST).is_file()
    }
    return sorted(found)


def available_substeps(root: Root, model: str) -> list[int]:
    """The super-steps N a model has a ``latest-n<N>`` version for, sorted."""
    model_dir = root / model
    if not is_name(model) or not model_dir.is_dir():
        return []
    found = (_SUBSTEPS_POINTER.fullmatch(p.name) for p in model_dir.iterdir())
    return sorted(int(m.group(1)) for m in found if m)


def _model_dirs(root: Root, model: str) -> list[Path]:
    """The model's folders, its own registry's first: a model lives in one registry, but an emulator
    fine-tuned for a policy from a read-only default is written to the data directory (``Roots``)."""
    if not is_name(model):
        return []
    dirs = [root / model, *(f / model for f in folders(root))]
    return [d for i, d in enumerate(dirs) if d.is_dir() and d not in dirs[:i]]


def versions(root: Root, model: str) -> list[str]:
    """Every complete version of a model (a folder with a manifest) in any registry, sorted by name:
    the versions ``resolve`` finds by name (``version_folder``)."""
    return sorted(
        {
            p.name
            for d in _model_dirs(root, model)
            for p in d.iterdir()
            if is_name(p.name) and (p / MANIFEST_FILE).is_file()
        }
    )


def latest_version(root: Root, model: str, substeps: int | None = None) -> str:
    """The version a model's ``latest`` (or ``latest-n<substeps>``) pointer names."""
    _check_model(root, model)
    pointer = root / model / pointer_name(substeps)
    try:
        return pointer.read_text().strip()
    except OSError:
        if substeps is None:
            raise ArtifactError("version", f"model {model!r} has no latest version") from None
        raise ArtifactError(
            "substeps",
            f"model {model!r} has no emulator for substeps={substeps}; it has {available_substeps(root, model)}",
        ) from None


def _check_model(root: Root, model: str) -> None:
    if not is_name(model) or not (root / model).is_dir():
        raise ArtifactError("model", f"unknown model {model!r}; trained models are {list_models(root)}")


def version_folder(root: Root, model: str, version: str) -> Path | None:
    """The folder of a named version (None: no such complete version): in the model's own registry,
    else in another one. A model's pointers and the versions they name live in one registry; an
    emulator fine-tuned for a policy (``Manifest.tuned``) is written to the data directory even when
    the model it was tuned from is a read-only default, and is found there by its name."""
    if not is_name(version):
        return None
    for d in _model_dirs(root, model):
        if (d / version / MANIFEST_FILE).is_file():
            return d / version
    return None


def resolve(root: Root, model: str, version: str | None = None, substeps: int | None = None) -> Path:
    """The folder of a model's version: the named one, else the latest for ``substeps``, else ``latest``.

    ``ArtifactError`` names what is missing: an unknown model, a version it does not have (or a
    name that is not a plain name), no version for ``substeps``, or a named version whose
    super-step is not ``substeps``.
    """
    _check_model(root, model)
    if version is None:
        version = latest_version(root, model, substeps)
        substeps = None  # the pointer names a version of that n
    path = version_folder(root, model, version)
    if path is None:
        raise ArtifactError(
            "version", f"model {model!r} has no version {version!r}; it has {versions(root, model)}"
        )
    if substeps is not None:
        found = read_manifest(path).substeps
        if found != substeps:
            raise ArtifactError(
                "substeps", f"version {version!r} of {model!r} has substeps={found}, got {substeps}"
            )
    return path


# ---------------------------------------------------------------------------- reading
def read_manifest(path: Path) -> Manifest:
    """The manifest of a version folder, upgraded from an older format if need be.

    ``ArtifactError`` (``what="manifest"``) when it is missing, not JSON, of a format this code does
    not read, or does not fit its format; the message names the file.
    """
    file = path / MANIFEST_FILE
    try:
        data = json.loads(file.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise ArtifactError("manifest", f"cannot read the manifest {str(file)!r}: {exc}") from exc
    if not isinstance(data, dict):
        raise ArtifactError("manifest", f"{str(file)!r} is not a manifest: expected a JSON object")
    try:
        return parse_manifest(data, str(file))
    except ManifestError as exc:
        raise ArtifactError("manifest", str(exc)) from exc


def assets_dir(path: Path) -> Path:
    """The folder of a version's assets (its model's ``assets/``)."""
    return path.parent / ASSETS_DIR


def read_assets(path: Path, manifest: Manifest | None = None) -> dict[str, bytes]:
    """The files a version's MJCF names, by name, each checked against its SHA-256.

    ``ArtifactError`` (``what="manifest"``) names a file that is missing or altered."""
    manifest = manifest or read_manifest(path)
    out: dict[str, bytes] = {}
    for a in manifest.assets:
        file = assets_dir(path) / a.name
        try:
            data = file.read_bytes()
        except OSError as exc:
            raise ArtifactError(
                "manifest",
                f"{manifest.model} {manifest.version}: its {a.kind} {a.source or a.name} is missing ({file})",
            ) from exc
        if hashlib.sha256(data).hexdigest() != a.sha256:
            raise ArtifactError(
                "manifest", f"{manifest.model} {manifest.version}: {file} is not the file it names"
            )
        out[a.name] = data
    return out


def load_physical_model(path: Path, manifest: Manifest | None = None) -> PhysicalModel:
    """Rebuild the physical model an artifact was trained on, from the artifact alone: its MJCF and the
    assets it names, compiled in the sandbox (``sim.sandbox``; imports MuJoCo)."""
    from neuroanimator.sim import sandbox
    from neuroanimator.sim.model import PhysicalModel

    manifest = manifest or read_manifest(path)
    sources = {a.name: a.source for a in manifest.assets}
    xml, assets = (path / MJCF_FILE).read_text(), read_assets(path, manifest)
    # a stored MJCF may be a user's: it is compiled where MuJoCo can read nothing but its assets
    compiled = sandbox.compile_xml(xml, assets)
    return PhysicalModel(xml, manifest.spec, assets, sources, compiled)


def version_size(path: Path, manifest: Manifest | None = None) -> int:
    """Bytes of a version: its folder's files and the assets it names (what a copy of it weighs)."""
    own = sum(f.stat().st_size for f in path.iterdir() if f.is_file())
    manifest = manifest or read_manifest(path)
    return own + sum(a.size for a in manifest.assets)


def model_size(root: Root, model: str) -> int:
    """Bytes a model takes in the registries: every version, its shared assets (once in each
    registry) and its plots."""
    return sum(
        f.stat().st_size
        for d in _model_dirs(root, model)
        for f in d.rglob("*")
        if f.is_file() and not f.is_symlink()
    )


def _read_result(file: Path, kind: type[_R]) -> _R | None:
    if not file.is_file():
        return None
    try:
        return kind.model_validate_json(file.read_bytes())
    except (OSError, ValidationError) as exc:
        raise ArtifactError("results", f"cannot read {str(file)!r} as {kind.__name__}: {exc}") from exc


def read_eval(path: Path) -> VersionEval | None:
    """A version's evaluation (``eval.json``), or None when it has not been evaluated."""
    return _read_result(path / EVAL_FILE, VersionEval)


def read_bench(path: Path) -> VersionBench | None:
    """A version's benchmark (``bench.json``), or None when it has not been benchmarked."""
    return _read_result(path / BENCH_FILE, VersionBench)


def _current_versions(root: Root, model: str) -> list[Path]:
    """The version folders the ``latest-n<N>`` pointers name, by N."""
    return [resolve(root, model, substeps=n) for n in available_substeps(root, model)]


def model_eval(root: Root, model: str) -> ModelEval | None:
    """A model's evaluation over its current versions (``summarize_eval``); None when none is evaluated.

    The primary row is the ``latest`` version's.
    """
    rows = [r for p in _current_versions(root, model) if (r := read_eval(p)) is not None]
    if not rows:
        return None
    latest = read_manifest(resolve(root, model))
    plot = f"{model}/{PLOT_FILE}" if (root / model / PLOT_FILE).is_file() else None  # relative to the root
    return summarize_eval(rows, latest.spec.thesis_hidden, latest.substeps, plot)


def model_bench(root: Root, model: str) -> ModelBench | None:
    """A model's benchmark over its current versions (``summarize_bench``); None when none is measured."""
    rows = [r for p in _current_versions(root, model) if (r := read_bench(p)) is not None]
    return summarize_bench(model, rows) if rows else None


# ---------------------------------------------------------------------------- measurement results
def _write_json(file: Path, record: BaseModel) -> Path:
    """Write atomically: a reader sees the old file or the new one, never half of it."""
    fd, tmp = tempfile.mkstemp(dir=file.parent, prefix=f".tmp-{file.name}-")
    try:
        with os.fdopen(fd, "w") as fh:
            fh.write(record.model_dump_json(indent=1) + "\n")
        os.replace(tmp, file)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return file


def write_eval(root: Root, result: VersionEval) -> Path:
    """Store a version's evaluation in its folder (``eval.json``); returns the file."""
    return _write_json(resolve(root, result.model, result.version) / EVAL_FILE, result)


def write_bench(root: Root, result: VersionBench) -> Path:
    """Store a version's benchmark in its folder (``bench.json``); returns the file."""
    return _write_json(resolve(root, result.model, result.version) / BENCH_FILE, result)
